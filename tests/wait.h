#pragma once
// Waiting in tests for what another thread or process does. WaitUntil polls the condition and
// returns as soon as it holds (true), or false at the deadline; the poll starts at 1 ms and backs
// off to 20 ms. It is the tests' only way to wait: no test sleeps a fixed time hoping that
// something has happened by then (fixed sleeps left in tests are part of a scenario: a device
// that comes back later, a kill at a random moment).

#include <algorithm>
#include <chrono>
#include <cstdlib>
#include <string>
#include <thread>

namespace gs360::test {

// How much slower than a Release build the code under test runs: GS360_TEST_TIME_SCALE (default
// 1; scripts/sanitize.sh sets it, a sanitizer build on a loaded machine being several times
// slower). Every deadline of the tests that only catches a hang scales by it, never one that a
// test asserts.
inline double TimeScale() {
  const char* s = std::getenv("GS360_TEST_TIME_SCALE");
  if (s == nullptr) return 1.0;
  try {
    return std::max(1.0, std::stod(s));
  } catch (...) {
    return 1.0;
  }
}

template <typename Duration>
std::chrono::milliseconds Scaled(Duration d) {
  return std::chrono::milliseconds(
      static_cast<long long>(std::chrono::duration<double, std::milli>(d).count() * TimeScale()));
}

// The deadline `timeout` is Scaled().
template <typename Predicate>
bool WaitUntil(Predicate done, std::chrono::milliseconds timeout) {
  const auto deadline = std::chrono::steady_clock::now() + Scaled(timeout);
  auto poll = std::chrono::milliseconds(1);
  while (!done()) {
    if (std::chrono::steady_clock::now() >= deadline) return done();
    std::this_thread::sleep_for(poll);
    poll = std::min(poll * 2, std::chrono::milliseconds(20));
  }
  return true;
}

}  // namespace gs360::test
