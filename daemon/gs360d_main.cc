// gs360d: the long-running daemon (docs/daemon.md). Exit codes: 0 stopped by a signal, 1
// unexpected error, 2 bad configuration or usage, 3 the data folder or the machine port is held
// by another process, 4 cannot listen on the address.

#include <signal.h>
#include <sys/resource.h>
#include <systemd/sd-daemon.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <optional>
#include <thread>

#include <spdlog/sinks/rotating_file_sink.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include "base/json_reader.h"
#include "base/version.h"
#include "daemon/daemon.h"
#include "daemon/http_api.h"

namespace {

struct Args {
  std::string config;
  std::optional<std::string> listen;
  std::optional<int> port;
  std::optional<std::string> data_dir;
  int verbosity = 0;
  bool print_config = false;
};

gs360::DaemonConfig LoadConfig(const Args& a) {
  gs360::DaemonConfig config =
      a.config.empty() ? gs360::DaemonConfig{} : gs360::LoadDaemonConfig(a.config);
  if (a.listen) config.server.listen = *a.listen;
  if (a.port) config.server.port = *a.port;
  if (a.data_dir) config.data_dir = *a.data_dir;
  if (const char* token = std::getenv("GS360D_TOKEN"); token != nullptr && *token != '\0') {
    config.server.token = token;
  }
  config.Check();
  return config;
}

void SetUpLogging(const gs360::DaemonConfig& config, int verbosity) {
  auto err = std::make_shared<spdlog::sinks::stderr_color_sink_mt>();
  const auto dir = config.data_dir / "log";
  std::filesystem::create_directories(dir);
  auto file = std::make_shared<spdlog::sinks::rotating_file_sink_mt>(
      (dir / "gs360d.log").string(), static_cast<std::size_t>(config.log.file_max_bytes),
      static_cast<std::size_t>(config.log.files));
  auto logger = std::make_shared<spdlog::logger>("gs360d", spdlog::sinks_init_list{err, file});
  spdlog::level::level_enum level = spdlog::level::from_str(config.log.level);
  if (verbosity >= 2) level = spdlog::level::trace;
  if (verbosity == 1) level = std::min(level, spdlog::level::debug);
  logger->set_level(level);
  logger->flush_on(spdlog::level::info);
  spdlog::set_default_logger(logger);
}

// Tells systemd (when it started us: NOTIFY_SOCKET) how we are, until `done`.
void NotifyLoop(gs360::Daemon& daemon, const std::atomic<bool>& done) {
  std::uint64_t watchdog_us = 0;
  const bool watchdog = sd_watchdog_enabled(0, &watchdog_us) > 0;
  const auto period =
      watchdog ? std::chrono::microseconds(watchdog_us / 3) : std::chrono::microseconds(5'000'000);
  while (!done) {
    // StatusLine() takes the daemon's lock: a daemon stuck on it misses its watchdog and is
    // restarted by systemd.
    const std::string status = "STATUS=" + daemon.StatusLine();
    sd_notify(0, status.c_str());
    if (watchdog) sd_notify(0, "WATCHDOG=1");
    const auto until = std::chrono::steady_clock::now() + period;
    while (!done && std::chrono::steady_clock::now() < until) {
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
  }
}

// Every connection is a file descriptor: room for server.max_connections and the daemon's own
// files (database, logs, serial port, camera).
void RaiseOpenFileLimit(int connections) {
  rlimit limit{};
  if (getrlimit(RLIMIT_NOFILE, &limit) != 0) return;
  const auto want = static_cast<rlim_t>(connections) + 256;
  if (limit.rlim_cur >= want) return;
  limit.rlim_cur = std::min(want, limit.rlim_max);
  setrlimit(RLIMIT_NOFILE, &limit);
  if (limit.rlim_cur < want) {
    spdlog::warn(
        "gs360d: open files limited to {} (hard limit): server.max_connections = {} "
        "cannot all be open",
        limit.rlim_cur, connections);
  }
}

int Serve(const gs360::DaemonConfig& config, sigset_t signals) {
  RaiseOpenFileLimit(config.server.max_connections);
  gs360::Daemon daemon(config);
  gs360::HttpApi api(daemon, config.server);
  api.Bind();
  daemon.SetUrl(api.Url());
  spdlog::info("gs360d listening on {} (data folder {})", api.Url(),
               daemon.config().data_dir.string());
  std::atomic<bool> done{false};
  std::thread signal_thread([&] {
    int sig = 0;
    sigwait(&signals, &sig);
    if (done) return;
    spdlog::info("gs360d: signal {}: stopping (the current probe is finished first)", sig);
    sd_notify(0, "STOPPING=1");
    api.Stop();
  });
  sd_notifyf(0, "READY=1\nMAINPID=%d\nSTATUS=listening on %s", static_cast<int>(getpid()),
             api.Url().c_str());
  std::thread notifier([&] { NotifyLoop(daemon, done); });
  api.Serve();
  daemon.Shutdown();
  done = true;
  // Wake the signal thread if it is still waiting (we were stopped some other way).
  if (signal_thread.joinable()) {
    pthread_kill(signal_thread.native_handle(), SIGTERM);
    signal_thread.join();
  }
  notifier.join();
  spdlog::info("gs360d stopped");
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "gs360d: the gs360 daemon. Runs calibration acquisitions on one rig, serves the HTTP API "
      "(/api/v1) and the dashboard (/). See docs/daemon.md."};
  app.set_version_flag("--version", gs360::VersionLine("gs360d"));
  Args a;
  app.add_option("-c,--config", a.config, "Configuration file (TOML); without it, the defaults");
  app.add_option("--listen", a.listen, "Address to bind (default 127.0.0.1)");
  app.add_option("--port", a.port, "Port (default 7360; 0 = any free port)");
  app.add_option("--data-dir", a.data_dir, "Data folder (database, logs, models)");
  app.add_flag("-v,--verbose", a.verbosity, "More log output (-vv for everything)");
  app.add_flag("--print-config", a.print_config,
               "Print the effective configuration (TOML) and exit");
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    const int code = app.exit(e);
    return code == 0 ? 0 : 2;
  }
  // Signals are taken by one thread (sigwait); every thread started from here inherits the mask.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGTERM);
  sigaddset(&signals, SIGINT);
  sigaddset(&signals, SIGHUP);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);
  signal(SIGPIPE, SIG_IGN);
  gs360::DaemonConfig config;
  try {
    config = LoadConfig(a);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "gs360d: %s\n", e.what());
    return 2;
  }
  if (a.print_config) {
    std::fputs(gs360::DaemonConfigToToml(config).c_str(), stdout);
    return 0;
  }
  try {
    SetUpLogging(config, a.verbosity);
    return Serve(config, signals);
  } catch (const gs360::LockHeldError& e) {
    spdlog::error("{}", e.what());
    return 3;
  } catch (const gs360::ConfigError& e) {
    spdlog::error("{}", e.what());
    return 2;
  } catch (const gs360::ListenError& e) {
    spdlog::error("{}", e.what());
    return 4;
  } catch (const std::exception& e) {
    spdlog::error("{}", e.what());
    return 1;
  }
}
