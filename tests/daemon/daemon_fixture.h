#pragma once
// A virtual rig with gs360d serving it: in this process (Daemon + HttpApi on a free loopback
// port) or as a child process (the gs360d binary), for the API and end-to-end tests.

#include <deque>
#include <fstream>
#include <memory>
#include <string>
#include <thread>

#include "cli/daemon_process.h"
#include "daemon/daemon.h"
#include "daemon/http_api.h"
#include "tests/run/rig_fixture.h"
// After Eigen: <resolv.h>, which httplib.h includes, defines a macro `_res` that Eigen's product
// kernels use as a parameter name.
#include <httplib.h>

namespace gs360::test {

// The gs360d.toml of a fixture's rig.
inline std::string RigToml(const RunConfig& config, const std::string& extra = "",
                           double reconnect_timeout_s = 10.0) {
  return "data_dir = \"data\"\n" + extra + "\n[server]\nport = 0\n[machine]\nuri = \"" +
         config.machine.uri +
         "\"\nstatus_interval_ms = " + std::to_string(config.machine.status_interval_ms) +
         "\n[camera]\nuri = \"" + config.camera.uri +
         "\"\ncapture_timeout_ms = " + std::to_string(config.camera.capture.timeout.count()) +
         "\n[engine]\nreconnect_timeout_s = " + std::to_string(reconnect_timeout_s) +
         "\n[plan]\nreference_every = 25\n";
}

// Daemon and HTTP server in this process.
struct InProcessDaemon {
  std::unique_ptr<Daemon> daemon;
  std::unique_ptr<HttpApi> api;
  std::thread server;
  std::string url;

  explicit InProcessDaemon(DaemonConfig config) {
    daemon = std::make_unique<Daemon>(std::move(config));
    api = std::make_unique<HttpApi>(*daemon, daemon->config().server);
    api->Bind();
    url = api->Url();
    daemon->SetUrl(url);
    server = std::thread([this] { api->Serve(); });
  }
  ~InProcessDaemon() {
    daemon->Shutdown();
    api->Stop();
    if (server.joinable()) server.join();
  }
  httplib::Client Client() const {
    httplib::Client c(url);
    c.set_read_timeout(120, 0);
    return c;
  }
};

inline DaemonConfig ConfigFor(const RigFixture& f, const std::string& extra = "") {
  return DaemonConfigFromToml(RigToml(f.config, extra), "test.toml", f.dir);
}

// The gs360d binary on a fixture's rig.
inline std::unique_ptr<cli::DaemonProcess> StartDaemonProcess(const RigFixture& f,
                                                              const std::string& extra = "") {
  const auto config = f.dir / "gs360d.toml";
  std::ofstream(config) << RigToml(f.config, extra);
  return std::make_unique<cli::DaemonProcess>(std::string(GS360_BINARY_DIR) + "/daemon/gs360d",
                                              config, f.dir / "data", f.dir / "gs360d.log");
}

// The last `n` warning and error lines of a gs360d log, for a failing check's message: CI shows
// only the start of a failure's output, so the daemon's own account goes before the long texts.
inline std::string DaemonLogProblems(const std::filesystem::path& log, std::size_t n = 4) {
  std::ifstream in(log);
  std::deque<std::string> last;
  for (std::string line; std::getline(in, line);) {
    if (line.find("[warning]") == std::string::npos && line.find("[error]") == std::string::npos)
      continue;
    last.push_back(line);
    if (last.size() > n) last.pop_front();
  }
  std::string out;
  for (const auto& line : last) out += line + "\n";
  return out.empty() ? "(no warnings or errors in " + log.string() + ")" : out;
}

}  // namespace gs360::test
