#pragma once
// Waiting in tests for what another thread or process does. WaitUntil polls the condition and
// returns as soon as it holds (true), or false at the deadline; the poll starts at 1 ms and backs
// off to 20 ms. It is the tests' only way to wait: no test sleeps a fixed time hoping that
// something has happened by then (fixed sleeps left in tests are part of a scenario: a device
// that comes back later, a kill at a random moment).

#include <algorithm>
#include <chrono>
#include <thread>

namespace gs360::test {

template <typename Predicate>
bool WaitUntil(Predicate done, std::chrono::milliseconds timeout) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  auto poll = std::chrono::milliseconds(1);
  while (!done()) {
    if (std::chrono::steady_clock::now() >= deadline) return done();
    std::this_thread::sleep_for(poll);
    poll = std::min(poll * 2, std::chrono::milliseconds(20));
  }
  return true;
}

}  // namespace gs360::test
