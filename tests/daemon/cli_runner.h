#pragma once
// Runs a program of the build (gs360, gs360d) as a user would, collecting its exit code, stdout
// and stderr, for the tests that hold the executables to what they print.

#include <fcntl.h>
#include <spawn.h>
#include <sys/wait.h>

#include <catch2/catch.hpp>

#include <atomic>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

extern char** environ;

namespace gs360::test {

struct CliResult {
  int exit_code = -1;
  std::string out;
  std::string err;
};

inline std::string ReadWholeFile(const std::filesystem::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

// Starts `argv` with stdout and stderr in files of `dir` (named by `out` and `err`); the pid.
inline pid_t SpawnProgram(const std::vector<std::string>& args, const std::filesystem::path& out,
                          const std::filesystem::path& err) {
  std::vector<std::string> full = args;
  std::vector<char*> argv;
  for (auto& a : full) argv.push_back(a.data());
  argv.push_back(nullptr);
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, 1, out.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  posix_spawn_file_actions_addopen(&actions, 2, err.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  pid_t pid = -1;
  const int rc = posix_spawn(&pid, argv[0], &actions, nullptr, argv.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  REQUIRE(rc == 0);
  return pid;
}

// Runs `args` (args[0] the program's path) to its end in `dir`.
inline CliResult RunProgram(const std::filesystem::path& dir,
                            const std::vector<std::string>& args) {
  static std::atomic<int> n{0};
  const int k = ++n;
  const auto out = dir / ("run-" + std::to_string(k) + ".out");
  const auto err = dir / ("run-" + std::to_string(k) + ".err");
  const pid_t pid = SpawnProgram(args, out, err);
  int status = 0;
  waitpid(pid, &status, 0);
  CliResult r;
  r.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
  r.out = ReadWholeFile(out);
  r.err = ReadWholeFile(err);
  return r;
}

inline std::string Gs360Path() {
  return std::string(GS360_BINARY_DIR) + "/cli/gs360";
}

// `gs360 --daemon URL ARGS...`.
inline CliResult RunGs360(const std::filesystem::path& dir, const std::string& url,
                          const std::vector<std::string>& args) {
  std::vector<std::string> full = {Gs360Path(), "--daemon", url};
  full.insert(full.end(), args.begin(), args.end());
  return RunProgram(dir, full);
}

}  // namespace gs360::test
