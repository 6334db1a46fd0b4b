#include "cli/daemon_client.h"

#include <httplib.h>

#include <cstdlib>
#include <fstream>

namespace gs360::cli {
namespace {

using Json = nlohmann::json;

int ExitCodeFor(int status) {
  switch (status) {
    case 400:
    case 413:
    case 415:
      return kExitUsage;
    case 401:
    case 403:
      return kExitUnauthorized;
    case 404:
      return kExitNotFound;
    case 409:
      return kExitConflict;
    default:
      return kExitError;
  }
}

// What a 409's `state` adds to its message, worded to agree with it. "run is already running"
// comes while the run's session holds the machine, whatever its record says: a run just started
// is still "created", one that has just paused or stopped is already "paused" while its session
// lets go of the machine.
std::string StateNote(const std::string& message, const std::string& state) {
  if (message.find("already running") == std::string::npos) return " (the run is " + state + ")";
  if (state == "running" || state == "starting") return "";
  if (state == "created") return " (its session is starting)";
  return ": its session is still ending (the run is " + state + " now); try again in a moment";
}

}  // namespace

struct DaemonClient::Impl {
  httplib::Client http;
  httplib::Headers headers;
  explicit Impl(const std::string& url) : http(url) {}

  [[noreturn]] void Unreachable(const std::string& url, httplib::Error error) const {
    throw ClientError("cannot reach gs360d at " + url + " (" + httplib::to_string(error) +
                          "). Is it running? Start it with `gs360d --config gs360d.toml`, or "
                          "point --daemon / GS360_DAEMON at it.",
                      kExitUnreachable);
  }

  Json Answer(const std::string& url, const std::string& what, const httplib::Result& r) const {
    if (!r) Unreachable(url, r.error());
    return AnswerOf(r->status, r->body, what);
  }

  static Json AnswerOf(int status, const std::string& text, const std::string& what) {
    if (status >= 200 && status < 300) {
      if (text.empty()) return nullptr;
      Json body = Json::parse(text, nullptr, false);
      if (body.is_discarded()) {
        throw ClientError(what + ": the daemon answered something that is not JSON", kExitError);
      }
      return body;
    }
    const Json body = Json::parse(text, nullptr, false);
    std::string message = "HTTP " + std::to_string(status);
    std::string field;
    if (body.is_object() && body.contains("error") && body["error"].is_object()) {
      message = body["error"].value("message", message);
      if (body["error"].contains("field") && body["error"]["field"].is_string()) {
        field = body["error"]["field"].get<std::string>();
      }
      const std::string state = body.contains("state") && body["state"].is_string()
                                    ? body["state"].get<std::string>()
                                    : "";
      if (!state.empty()) message += StateNote(message, state);
    }
    throw ClientError(message, ExitCodeFor(status), status, field);
  }
};

DaemonClient::DaemonClient(const std::string& url, std::string token) : url_(url) {
  if (url.rfind("http://", 0) != 0 || url.size() <= 7) {
    throw ClientError("--daemon: expected http://HOST:PORT, got \"" + url + "\"", kExitUsage);
  }
  while (!url_.empty() && url_.back() == '/') url_.pop_back();
  impl_ = std::make_unique<Impl>(url_);
  impl_->http.set_connection_timeout(5, 0);
  impl_->http.set_read_timeout(120, 0);  // creating a 10,000-probe plan takes a while
  impl_->http.set_write_timeout(60, 0);
  if (!token.empty()) impl_->headers.emplace("Authorization", "Bearer " + token);
}

DaemonClient::~DaemonClient() = default;

std::string DaemonClient::DefaultUrl() {
  const char* env = std::getenv("GS360_DAEMON");
  return env != nullptr && *env != '\0' ? std::string(env) : std::string("http://127.0.0.1:7360");
}

std::string DaemonClient::DefaultToken() {
  const char* env = std::getenv("GS360_TOKEN");
  return env != nullptr ? std::string(env) : std::string();
}

Json DaemonClient::Get(const std::string& path) {
  return impl_->Answer(url_, "GET " + path, impl_->http.Get(path.c_str(), impl_->headers));
}

Json DaemonClient::Post(const std::string& path, const Json& body) {
  return impl_->Answer(
      url_, "POST " + path,
      impl_->http.Post(path.c_str(), impl_->headers, body.dump(), "application/json"));
}

Json DaemonClient::PostBytes(const std::string& path, const std::string& bytes) {
  return impl_->Answer(
      url_, "POST " + path,
      impl_->http.Post(path.c_str(), impl_->headers, bytes, "application/octet-stream"));
}

Json DaemonClient::Delete(const std::string& path) {
  return impl_->Answer(url_, "DELETE " + path, impl_->http.Delete(path.c_str(), impl_->headers));
}

std::int64_t DaemonClient::Download(const std::string& path, const std::filesystem::path& out) {
  const std::filesystem::path tmp = out.string() + ".part";
  std::int64_t size = 0;
  int status = 0;
  std::string error_body;
  {
    std::ofstream file(tmp, std::ios::binary | std::ios::trunc);
    if (!file) throw ClientError("cannot write " + tmp.string(), kExitError);
    const auto r = impl_->http.Get(
        path.c_str(), impl_->headers,
        [&](const httplib::Response& response) {
          status = response.status;
          return true;
        },
        [&](const char* data, std::size_t n) {
          if (status >= 200 && status < 300) {
            file.write(data, static_cast<std::streamsize>(n));
            size += static_cast<std::int64_t>(n);
          } else {
            error_body.append(data, n);
          }
          return static_cast<bool>(file);
        });
    if (!r) {
      std::filesystem::remove(tmp);
      impl_->Unreachable(url_, r.error());
    }
    if (!file.flush()) {
      std::filesystem::remove(tmp);
      throw ClientError("cannot write " + tmp.string() + " (disk full?)", kExitError);
    }
    if (r->status < 200 || r->status >= 300) {
      file.close();
      std::filesystem::remove(tmp);
      Impl::AnswerOf(r->status, error_body, "GET " + path);
    }
  }
  std::filesystem::rename(tmp, out);
  return size;
}

void DaemonClient::Events(const std::string& query,
                          const std::function<bool(const std::string&, const Json&)>& on_event) {
  httplib::Client stream(url_);
  stream.set_connection_timeout(5, 0);
  stream.set_read_timeout(30, 0);  // the daemon sends a keep-alive every 10 s
  std::string buffer;
  bool stopped = false;
  int status = 0;
  const std::string path = "/api/v1/events" + (query.empty() ? "" : "?" + query);
  const auto r = stream.Get(
      path.c_str(), impl_->headers,
      [&](const httplib::Response& response) {
        status = response.status;
        return status == 200;
      },
      [&](const char* data, std::size_t n) {
        buffer.append(data, n);
        for (std::size_t end; (end = buffer.find("\n\n")) != std::string::npos;) {
          const std::string block = buffer.substr(0, end);
          buffer.erase(0, end + 2);
          std::string type = "message";
          std::string payload;
          std::size_t at = 0;
          while (at < block.size()) {
            std::size_t eol = block.find('\n', at);
            if (eol == std::string::npos) eol = block.size();
            const std::string line = block.substr(at, eol - at);
            if (line.rfind("event: ", 0) == 0) type = line.substr(7);
            if (line.rfind("data: ", 0) == 0) payload += line.substr(6);
            at = eol + 1;
          }
          if (payload.empty()) continue;  // a comment (keep-alive)
          const Json event = Json::parse(payload, nullptr, false);
          if (!on_event(type, event)) {
            stopped = true;
            return false;
          }
        }
        return true;
      });
  if (stopped) return;
  if (!r && status == 0) impl_->Unreachable(url_, r.error());
  if (status != 200) {
    throw ClientError("the event stream was refused (HTTP " + std::to_string(status) + ")",
                      ExitCodeFor(status), status);
  }
  throw ClientError("the event stream from " + url_ + " ended", kExitError);
}

}  // namespace gs360::cli
