#include "cli/daemon_process.h"

#include <fcntl.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdlib>
#include <fstream>
#include <sstream>
#include <stdexcept>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>

extern char** environ;

namespace gs360::cli {
namespace {

std::string Tail(const std::filesystem::path& log, std::size_t bytes = 1500) {
  std::ifstream in(log, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  std::string text = ss.str();
  return text.size() > bytes ? "..." + text.substr(text.size() - bytes) : text;
}

}  // namespace

std::filesystem::path FindGs360d() {
  std::error_code ec;
  const auto self = std::filesystem::read_symlink("/proc/self/exe", ec);
  if (!ec) {
    for (const auto& candidate :
         {self.parent_path() / "gs360d", self.parent_path().parent_path() / "daemon" / "gs360d"}) {
      if (::access(candidate.c_str(), X_OK) == 0) return candidate;
    }
  }
  if (const char* path = std::getenv("PATH")) {
    std::stringstream dirs(path);
    for (std::string dir; std::getline(dirs, dir, ':');) {
      const auto candidate = std::filesystem::path(dir) / "gs360d";
      if (!dir.empty() && ::access(candidate.c_str(), X_OK) == 0) return candidate;
    }
  }
  throw std::runtime_error("cannot find gs360d next to this program, in ../daemon/ or on PATH");
}

DaemonProcess::DaemonProcess(const std::filesystem::path& gs360d,
                             const std::filesystem::path& config,
                             const std::filesystem::path& data_dir,
                             const std::filesystem::path& log, std::chrono::seconds timeout)
    : log_(log) {
  std::error_code ec;
  std::filesystem::remove(data_dir / "daemon.json", ec);
  std::vector<std::string> args = {gs360d.string(), "--config", config.string()};
  std::vector<char*> argv;
  for (auto& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, 1, log.c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644);
  posix_spawn_file_actions_adddup2(&actions, 1, 2);
  const int rc = posix_spawn(&pid_, argv[0], &actions, nullptr, argv.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  if (rc != 0) throw std::runtime_error("cannot start " + gs360d.string());
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < deadline) {
    std::ifstream in(data_dir / "daemon.json");
    const auto info = nlohmann::json::parse(in, nullptr, false);
    if (info.is_object() && info.value("pid", 0) == pid_ && info.contains("url")) {
      url_ = info["url"].get<std::string>();
      return;
    }
    if (!Running()) {
      throw std::runtime_error("gs360d exited before it was ready:\n" + Tail(log_));
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  Kill();
  throw std::runtime_error("gs360d was not ready within " + std::to_string(timeout.count()) +
                           " s:\n" + Tail(log_));
}

DaemonProcess::~DaemonProcess() {
  if (pid_ > 0) Stop();
}

bool DaemonProcess::Running() {
  if (pid_ <= 0) return false;
  int status = 0;
  const pid_t r = ::waitpid(pid_, &status, WNOHANG);
  if (r == pid_) {
    pid_ = -1;
    return false;
  }
  return true;
}

int DaemonProcess::Reap(std::chrono::milliseconds timeout) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (pid_ > 0) {
    int status = 0;
    if (::waitpid(pid_, &status, WNOHANG) == pid_) {
      pid_ = -1;
      return WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
    }
    if (std::chrono::steady_clock::now() > deadline) return -2;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  return -1;
}

int DaemonProcess::Stop(std::chrono::seconds timeout) {
  if (pid_ <= 0) return -1;
  ::kill(pid_, SIGTERM);
  const int code = Reap(timeout);
  if (code != -2) return code;
  Kill();
  return 128 + SIGKILL;
}

void DaemonProcess::Kill() {
  if (pid_ <= 0) return;
  ::kill(pid_, SIGKILL);
  Reap(std::chrono::seconds(30));
}

}  // namespace gs360::cli
