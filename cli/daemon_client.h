#pragma once
// The gs360 command line as gs360d's client: JSON requests to /api/v1 (docs/api.md), downloads,
// and the event stream. Errors become ClientError carrying the exit code the command returns
// (docs/cli.md lists them).

#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <stdexcept>
#include <string>

#include <nlohmann/json.hpp>

namespace gs360::cli {

// gs360's exit codes.
enum ExitCode : int {
  kExitOk = 0,
  kExitError = 1,          // anything else (the daemon failed, a file could not be written)
  kExitUsage = 2,          // bad arguments, or a request the daemon refused as invalid (400)
  kExitNotFound = 3,       // no such run (404)
  kExitConflict = 4,       // the run's state does not allow it (409)
  kExitUnreachable = 5,    // no daemon answers at the URL
  kExitUnauthorized = 6,   // token missing or wrong (401)
  kExitRunStopped = 7,     // a watched run or calibration ended without finishing
  kExitAwaiting = 8,       // the run stopped to ask you to confirm something (it says what)
  kExitNoCalibration = 9,  // export: the run exists but has no finished calibration
};

class ClientError : public std::runtime_error {
 public:
  ClientError(const std::string& message, int exit_code, int http_status = 0,
              std::string field = "")
      : std::runtime_error(message),
        exit_code_(exit_code),
        http_status_(http_status),
        field_(std::move(field)) {}
  int exit_code() const { return exit_code_; }
  int http_status() const { return http_status_; }
  const std::string& field() const { return field_; }

 private:
  int exit_code_;
  int http_status_;
  std::string field_;
};

class DaemonClient {
 public:
  // `url`: "http://host:port"; `token`: bearer token or empty. Throws ClientError (usage) for a
  // URL that is not http://host[:port].
  DaemonClient(const std::string& url, std::string token);
  ~DaemonClient();
  DaemonClient(const DaemonClient&) = delete;
  DaemonClient& operator=(const DaemonClient&) = delete;

  // $GS360_DAEMON, else http://127.0.0.1:7360.
  static std::string DefaultUrl();
  // $GS360_TOKEN, else empty.
  static std::string DefaultToken();

  const std::string& url() const { return url_; }
  // JSON in, JSON out; a 2xx answer's body (null for 204). Throws ClientError with the daemon's
  // error message and the matching exit code otherwise.
  nlohmann::json Get(const std::string& path);
  nlohmann::json Post(const std::string& path,
                      const nlohmann::json& body = nlohmann::json::object());
  nlohmann::json PostBytes(const std::string& path, const std::string& bytes);
  nlohmann::json Delete(const std::string& path);
  // Writes the body of a GET to `out` (through a temporary file, renamed when complete). Returns
  // its size. Throws ClientError.
  std::int64_t Download(const std::string& path, const std::filesystem::path& out);
  // Follows /api/v1/events (with `query`, e.g. "run=3"): on_event(type, data) for each event
  // until it returns false. Throws ClientError when the stream cannot be opened or breaks.
  void Events(const std::string& query,
              const std::function<bool(const std::string&, const nlohmann::json&)>& on_event);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
  std::string url_;
};

}  // namespace gs360::cli
