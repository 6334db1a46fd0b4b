#pragma once
// The real `gs360` executable of this build, run as a user would: its exit status and output.

#include <catch2/catch.hpp>

#include <sys/wait.h>

#include <array>
#include <cstdio>
#include <string>

namespace gs360::test {

struct Gs360Result {
  int status = -1;
  std::string out;  // stdout and stderr
};

// Runs `gs360 ARGS` through the shell (ARGS is shell text: quote paths with spaces).
inline Gs360Result Gs360(const std::string& args) {
  const std::string command = std::string(GS360_BINARY_DIR) + "/cli/gs360 " + args + " 2>&1";
  Gs360Result r;
  FILE* pipe = ::popen(command.c_str(), "r");
  REQUIRE(pipe != nullptr);
  std::array<char, 4096> buf{};
  while (std::fgets(buf.data(), buf.size(), pipe)) r.out += buf.data();
  const int status = ::pclose(pipe);
  r.status = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return r;
}

}  // namespace gs360::test
