#pragma once
// gs360d as a child process, for `gs360 demo`, the benchmarks and the end-to-end tests: started
// with a configuration file, ready once DATA/daemon.json names its URL (and its pid).

#include <sys/types.h>

#include <chrono>
#include <filesystem>
#include <string>

namespace gs360::cli {

// gs360d next to this program (the install), in ../daemon/ (the build tree), or on PATH. Throws
// std::runtime_error when none is found.
std::filesystem::path FindGs360d();

class DaemonProcess {
 public:
  // Starts `gs360d --config CONFIG` with stdout and stderr appended to `log`, and waits for it to
  // write DATA/daemon.json. Throws std::runtime_error (quoting the end of the log) when it exits
  // or is not ready within `timeout`.
  DaemonProcess(const std::filesystem::path& gs360d, const std::filesystem::path& config,
                const std::filesystem::path& data_dir, const std::filesystem::path& log,
                std::chrono::seconds timeout = std::chrono::seconds(60));
  // Stop(): SIGTERM, then SIGKILL if it has not exited within 120 s.
  ~DaemonProcess();
  DaemonProcess(const DaemonProcess&) = delete;
  DaemonProcess& operator=(const DaemonProcess&) = delete;

  const std::string& url() const { return url_; }
  pid_t pid() const { return pid_; }
  bool Running();
  // SIGTERM and wait: the exit code (128 + signal if killed), -1 if already reaped.
  int Stop(std::chrono::seconds timeout = std::chrono::seconds(120));
  // SIGKILL and reap (a power cut, as far as the daemon can tell).
  void Kill();

 private:
  int Reap(std::chrono::milliseconds timeout);
  pid_t pid_ = -1;
  std::string url_;
  std::filesystem::path log_;
};

}  // namespace gs360::cli
