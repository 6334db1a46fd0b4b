#include "daemon/http_api.h"

#include <algorithm>
#include <charconv>
#include <cstring>
#include <fstream>
#include <sstream>

#include <strings.h>

#include <spdlog/spdlog.h>

#include "base/json_reader.h"
#include "daemon/http_server.h"
#include "daemon/web_assets.h"
#include "geometry/mesh.h"
#include "storage/storage_error.h"

namespace gs360 {
namespace {

using Json = nlohmann::json;
using Request = HttpRequest;
using Response = HttpResponse;

// An event stream with nothing to say sends a comment this often, so that a proxy or a client
// sees it alive (HttpServerOptions::stream_tick_s asks it at least as often).
constexpr auto kKeepAlive = std::chrono::seconds(9);

void SendJson(Response& res, int status, const Json& body) {
  res.status = status;
  // Messages may quote what a client sent, bytes that are not UTF-8 included.
  res.SetContent(body.dump(-1, ' ', false, Json::error_handler_t::replace),
                 "application/json; charset=utf-8");
}

void SendError(Response& res, int status, const std::string& code, const std::string& message,
               const std::string& field = "") {
  SendJson(res, status,
           {{"error",
             {{"code", code},
              {"message", message},
              {"field", field.empty() ? Json(nullptr) : Json(field)}}}});
}

// Ids are decimal integers; anything else (a path, a huge number) names nothing.
std::optional<std::int64_t> ParseId(const std::string& text) {
  std::int64_t v = 0;
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), v);
  if (ec != std::errc() || end != text.data() + text.size() || v <= 0) return std::nullopt;
  return v;
}

// A literal path as a route pattern.
std::string RegexQuote(const std::string& text) {
  std::string out;
  for (const char ch : text) {
    if (std::strchr(".^$|()[]{}*+?\\", ch) != nullptr) out += '\\';
    out += ch;
  }
  return out;
}

bool HostIsLoopback(const std::string& host_header) {
  std::string host = host_header;
  if (!host.empty() && host[0] == '[') {
    host = host.substr(1, host.find(']') == std::string::npos ? 0 : host.find(']') - 1);
  } else if (const auto colon = host.rfind(':'); colon != std::string::npos) {
    host = host.substr(0, colon);
  }
  return IsLoopbackAddress(host);
}

// The media type of a Content-Type header, lower case, without its parameters
// ("Application/JSON; charset=utf-8" -> "application/json").
std::string MediaType(const std::string& header) {
  std::string type = header.substr(0, header.find(';'));
  const auto first = type.find_first_not_of(" \t");
  const auto last = type.find_last_not_of(" \t");
  type = first == std::string::npos ? "" : type.substr(first, last - first + 1);
  std::transform(type.begin(), type.end(), type.begin(),
                 [](unsigned char ch) { return static_cast<char>(std::tolower(ch)); });
  return type;
}

// The bearer token a request carries: "Authorization: Bearer T" (the scheme in any case, as
// RFC 7235 says), or "?token=T" for EventSource and links.
std::string GivenToken(const Request& req) {
  const std::string auth = req.Header("Authorization");
  if (auth.size() > 7 && strncasecmp(auth.c_str(), "bearer ", 7) == 0) {
    const auto start = auth.find_first_not_of(' ', 7);
    if (start != std::string::npos) return auth.substr(start);
  }
  return req.Param("token");
}

// An optional numeric query argument ("?after=N"): absent is `fallback`, anything but a number
// >= 0 is a 400 naming it.
std::int64_t QueryNumber(const Request& req, const std::string& name, std::int64_t fallback) {
  if (!req.HasParam(name)) return fallback;
  const std::string text = req.Param(name);
  std::int64_t v = 0;
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), v);
  if (text.empty() || ec != std::errc() || end != text.data() + text.size() || v < 0) {
    throw ConfigError("query: " + name + ": expected a whole number >= 0, got \"" + text + "\"",
                      name);
  }
  return v;
}

Json ParseBody(const Request& req, std::int64_t max_bytes) {
  if (req.body.size() > static_cast<std::size_t>(max_bytes)) {
    throw ConfigError("request body: larger than " + std::to_string(max_bytes) + " bytes");
  }
  if (req.body.empty()) return Json::object();
  Json body = ParseJsonText(req.body, "request body");
  if (!body.is_object()) throw ConfigError("request body: expected a JSON object", "");
  return body;
}

void SendAction(Response& res, std::int64_t run_id, const ActionResult& r) {
  switch (r.status) {
    case ActionStatus::kAccepted:
      SendJson(res, 202, {{"id", run_id}, {"state", r.state}, {"message", r.message}});
      return;
    case ActionStatus::kNotFound:
      SendError(res, 404, "not_found", r.message);
      return;
    case ActionStatus::kConflict:
      SendJson(res, 409,
               {{"error", {{"code", "conflict"}, {"message", r.message}, {"field", nullptr}}},
                {"state", r.state}});
      return;
  }
}

void SendPng(Response& res, const std::optional<std::vector<std::uint8_t>>& png,
             const std::string& what) {
  if (!png) return SendError(res, 404, "not_found", what);
  res.SetHeader("Cache-Control", "no-store");
  res.SetContent(std::string(png->begin(), png->end()), "image/png");
}

}  // namespace

bool SameSecret(const std::string& a, const std::string& b) {
  // Touches every byte of the longer string whatever the contents; the length itself is not a
  // secret worth hiding.
  const std::size_t n = std::max(a.size(), b.size());
  unsigned char diff = a.size() == b.size() ? 0 : 1;
  for (std::size_t i = 0; i < n; ++i) {
    const unsigned char x = i < a.size() ? static_cast<unsigned char>(a[i]) : 0;
    const unsigned char y = i < b.size() ? static_cast<unsigned char>(b[i]) : 0;
    diff |= static_cast<unsigned char>(x ^ y);
  }
  return diff == 0;
}

struct HttpApi::Impl {
  Daemon& daemon;
  ServerConfig config;
  HttpServer server;

  Impl(Daemon& d, const ServerConfig& c) : daemon(d), config(c), server(ServerOptions(c)) {}

  static HttpServerOptions ServerOptions(const ServerConfig& c) {
    HttpServerOptions o;
    o.listen = c.listen;
    o.port = c.port;
    o.slow_threads = c.threads;
    o.max_connections = c.max_connections;
    o.max_streams = c.max_event_streams;
    o.request_timeout_s = c.request_timeout_s;
    o.idle_timeout_s = c.idle_timeout_s;
    o.max_body_bytes = c.max_body_bytes;
    return o;
  }

  // Runs a handler, turning exceptions into the API's error bodies.
  template <typename F>
  void Guarded(Response& res, F f) {
    try {
      f();
    } catch (const ConfigError& e) {
      SendError(res, 400, "invalid", e.what(), e.field());
    } catch (const MeshError& e) {
      SendError(res, 400, "invalid_mesh", e.what(), "mesh");
    } catch (const StorageError& e) {
      spdlog::error("storage: {}", e.what());
      SendError(res, 500, "storage", e.what());
    } catch (const std::exception& e) {
      spdlog::error("request failed: {}", e.what());
      SendError(res, 500, "internal", e.what());
    }
  }

  bool Screen(const Request& req, Response& res);
  void Routes();
  void RunRoutes();
  // POST /api/v1/runs/ID/ACTION (start, pause, resume, cancel, calibrate).
  void RunAction(const Request& req, Response& res);
  void FileRoutes();
  void EventStream(const Request& req, Response& res);
  int port = 0;
};

bool HttpApi::Impl::Screen(const Request& req, Response& res) {
  res.SetHeader("X-Content-Type-Options", "nosniff");
  res.SetHeader("Referrer-Policy", "no-referrer");
  if (config.token.empty() && !HostIsLoopback(req.Header("Host"))) {
    SendError(res, 403, "forbidden",
              "this daemon answers only to a loopback Host (no token is configured)");
    return true;
  }
  if (req.path.rfind("/api/", 0) != 0) return false;
  if (!config.token.empty()) {
    const std::string given = GivenToken(req);
    if (given.empty() || !SameSecret(given, config.token)) {
      res.SetHeader("WWW-Authenticate", "Bearer");
      res.SetHeader("Connection", "close");
      SendError(res, 401, "unauthorized",
                given.empty() ? "this daemon needs a token: Authorization: Bearer <token>"
                              : "wrong token");
      return true;
    }
  }
  if (req.method == "POST") {
    const std::string want =
        req.path == "/api/v1/meshes" ? "application/octet-stream" : "application/json";
    if (MediaType(req.Header("Content-Type")) != want) {
      res.SetHeader("Connection", "close");
      SendError(res, 415, "unsupported_media_type",
                "POST " + req.path + " takes Content-Type: " + want);
      return true;
    }
  }
  return false;
}

void HttpApi::Impl::Routes() {
  server.SetScreen([this](const Request& req, Response& res) { return Screen(req, res); });
  server.SetBodyLimit([this](const Request& req) {
    return req.path == "/api/v1/meshes" ? config.max_upload_bytes : config.max_body_bytes;
  });
  server.SetErrorPage([this](const Request& req, Response& res) {
    res.SetHeader("X-Content-Type-Options", "nosniff");
    switch (res.status) {
      case 404:
        return SendError(res, 404, "not_found", "no such resource: " + req.method + " " + req.path);
      case 405:
        return SendError(res, 405, "method_not_allowed",
                         req.method + " is not used on " + req.path);
      case 413:
        return SendError(res, 413, "too_large",
                         "the body is larger than " +
                             std::to_string(req.path == "/api/v1/meshes" ? config.max_upload_bytes
                                                                         : config.max_body_bytes) +
                             " bytes");
      case 503:
        return SendError(res, 503, "unavailable",
                         "the daemon is stopping, or has " +
                             std::to_string(config.max_event_streams) +
                             " event streams open (server.max_event_streams): poll instead");
      default:
        return SendError(res, res.status, "internal", "the request failed (see the daemon's log)");
    }
  });
  for (const WebAsset& asset : WebAssets()) {
    const std::string path = asset.path == "/index.html" ? "/" : std::string(asset.path);
    server.Route("GET", RegexQuote(path), [asset](const Request&, Response& res) {
      res.SetHeader("Content-Security-Policy",
                    "default-src 'self'; img-src 'self' data: blob:; frame-src 'self'; "
                    "object-src 'none'; base-uri 'none'; frame-ancestors 'self'");
      res.SetHeader("Cache-Control", "no-cache");
      res.SetContent(std::string(asset.content), std::string(asset.type));
    });
  }
  server.Route("GET", "/api/v1/info", [this](const Request&, Response& res) {
    Guarded(res, [&] { SendJson(res, 200, daemon.Info()); });
  });
  server.Route("GET", "/api/v1/events", [this](const Request& req, Response& res) {
    Guarded(res, [&] { EventStream(req, res); });
  });
  server.Route("GET", "/api/v1/meshes", [this](const Request&, Response& res) {
    Guarded(res, [&] { SendJson(res, 200, daemon.ListMeshes()); });
  });
  server.Route(
      "POST", "/api/v1/meshes",
      [this](const Request& req, Response& res) {
        Guarded(res, [&] {
          const std::string format = req.HasParam("format") ? req.Param("format") : "stl";
          SendJson(res, 201, daemon.UploadMesh(req.body, format));
        });
      },
      Lane::kSlow);
  server.Route("GET", "/api/v1/notify", [this](const Request&, Response& res) {
    Guarded(res, [&] { SendJson(res, 200, daemon.NotifyView()); });
  });
  server.Route("POST", "/api/v1/notify/test", [this](const Request& req, Response& res) {
    Guarded(res, [&] {
      const Json body = ParseBody(req, config.max_body_bytes);
      JsonReader reader(body, "request");
      std::int64_t run = 0;
      reader.Get("run", run);
      reader.RejectUnknown();
      const auto sent = daemon.NotifyTest(run);
      if (!sent) return SendError(res, 404, "not_found", "no run " + std::to_string(run));
      SendJson(res, 202, *sent);
    });
  });
  RunRoutes();
  FileRoutes();
}

void HttpApi::Impl::RunRoutes() {
  server.Route("GET", "/api/v1/runs", [this](const Request&, Response& res) {
    Guarded(res, [&] { SendJson(res, 200, daemon.ListRuns()); });
  });
  server.Route(
      "POST", "/api/v1/runs",
      [this](const Request& req, Response& res) {
        Guarded(res, [&] {
          bool created = false;
          const Json view = daemon.CreateRun(ParseBody(req, config.max_body_bytes), &created);
          SendJson(res, created ? 201 : 200, view);
        });
      },
      Lane::kSlow);
  server.Route("GET", R"(/api/v1/runs/([^/]+))", [this](const Request& req, Response& res) {
    Guarded(res, [&] {
      const auto id = ParseId(req.matches[1]);
      const auto view = id ? daemon.GetRun(*id) : std::nullopt;
      if (!view) return SendError(res, 404, "not_found", "no run " + std::string(req.matches[1]));
      SendJson(res, 200, *view);
    });
  });
  server.Route("DELETE", R"(/api/v1/runs/([^/]+))", [this](const Request& req, Response& res) {
    Guarded(res, [&] {
      const auto id = ParseId(req.matches[1]);
      if (!id) return SendError(res, 404, "not_found", "no run " + std::string(req.matches[1]));
      const ActionResult r = daemon.Delete(*id);
      if (r.status == ActionStatus::kAccepted) {
        res.status = 204;
        return;
      }
      SendAction(res, *id, r);
    });
  });
  server.Route(
      "POST", R"(/api/v1/runs/([^/]+)/(start|pause|resume|cancel|calibrate))",
      [this](const Request& req, Response& res) { Guarded(res, [&] { RunAction(req, res); }); });
  server.Route(
      "GET", R"(/api/v1/runs/([^/]+)/probes)",
      [this](const Request& req, Response& res) {
        Guarded(res, [&] {
          const auto id = ParseId(req.matches[1]);
          const auto probes = id ? daemon.ListProbes(*id) : std::nullopt;
          if (!probes)
            return SendError(res, 404, "not_found", "no run " + std::string(req.matches[1]));
          SendJson(res, 200, *probes);
        });
      },
      Lane::kSlow);
  server.Route("GET", R"(/api/v1/runs/([^/]+)/log)", [this](const Request& req, Response& res) {
    Guarded(res, [&] {
      const auto id = ParseId(req.matches[1]);
      const std::int64_t after = QueryNumber(req, "after", 0);
      const auto log = id ? daemon.RunLog(*id, after, 1000) : std::nullopt;
      if (!log) return SendError(res, 404, "not_found", "no run " + std::string(req.matches[1]));
      SendJson(res, 200, *log);
    });
  });
  server.Route(
      "GET", R"(/api/v1/runs/([^/]+)/calibration)",
      [this](const Request& req, Response& res) {
        Guarded(res, [&] {
          const auto id = ParseId(req.matches[1]);
          const auto view = id ? daemon.Calibration(*id) : std::nullopt;
          if (!view)
            return SendError(res, 404, "not_found", "no run " + std::string(req.matches[1]));
          SendJson(res, 200, *view);
        });
      },
      Lane::kSlow);
}

void HttpApi::Impl::RunAction(const Request& req, Response& res) {
  const auto id = ParseId(req.matches[1]);
  if (!id) return SendError(res, 404, "not_found", "no run " + std::string(req.matches[1]));
  const Json body = ParseBody(req, config.max_body_bytes);
  const std::string action = req.matches[2];
  std::string confirm;
  if (action == "start" || action == "resume") {
    JsonReader reader(body, "request");
    reader.Get("confirm", confirm);
    reader.RejectUnknown();
  } else if (action != "calibrate" && !body.empty()) {
    throw ConfigError("request body: " + action + " takes no fields, got " + body.begin().key(),
                      body.begin().key());
  }
  ActionResult r;
  if (action == "start") r = daemon.Start(*id, confirm);
  if (action == "pause") r = daemon.Pause(*id);
  if (action == "resume") r = daemon.Resume(*id, confirm);
  if (action == "cancel") r = daemon.Cancel(*id);
  if (action == "calibrate") r = daemon.Calibrate(*id, body);
  SendAction(res, *id, r);
}

void HttpApi::Impl::FileRoutes() {
  server.Route(
      "GET", R"(/api/v1/runs/([^/]+)/frames/latest\.png)",
      [this](const Request& req, Response& res) {
        Guarded(res, [&] {
          const auto id = ParseId(req.matches[1]);
          SendPng(res, id ? daemon.LatestFramePng(*id) : std::nullopt,
                  "no frame of run " + std::string(req.matches[1]) + " yet");
        });
      },
      Lane::kSlow);
  server.Route(
      "GET", R"(/api/v1/runs/([^/]+)/probes/([^/]+)/frame\.png)",
      [this](const Request& req, Response& res) {
        Guarded(res, [&] {
          const auto id = ParseId(req.matches[1]);
          const std::string n = req.matches[2];
          const bool index_ok =
              !n.empty() && n.size() < 9 && n.find_first_not_of("0123456789") == std::string::npos;
          SendPng(res, id && index_ok ? daemon.ProbeFramePng(*id, std::stoi(n)) : std::nullopt,
                  "no captured probe " + n + " in run " + std::string(req.matches[1]));
        });
      },
      Lane::kSlow);
  struct Kind {
    const char* suffix;
    RunFile file;
    const char* type;
    const char* ext;
  };
  static constexpr Kind kKinds[] = {
      {"model", RunFile::kModel, "application/octet-stream", ".gs360model"},
      {"model\\.onnx", RunFile::kOnnx, "application/octet-stream", ".onnx"},
      {"report", RunFile::kReport, "text/html; charset=utf-8", ""},
      {"validation\\.json", RunFile::kValidation, "application/json; charset=utf-8", ""},
  };
  for (const Kind& kind : kKinds) {
    server.Route(
        "GET", std::string(R"(/api/v1/runs/([^/]+)/)") + kind.suffix,
        [this, kind](const Request& req, Response& res) {
          Guarded(res, [&] {
            const auto id = ParseId(req.matches[1]);
            const auto path = id ? daemon.FileOf(*id, kind.file) : std::nullopt;
            if (!path) {
              return SendError(
                  res, 404, "not_found",
                  "run " + std::string(req.matches[1]) + " has no finished calibration");
            }
            std::ifstream in(*path, std::ios::binary);
            std::stringstream ss;
            ss << in.rdbuf();
            if (*kind.ext != '\0') {
              res.SetHeader("Content-Disposition",
                            "attachment; filename=\"" + path->filename().string() + "\"");
            }
            if (kind.file == RunFile::kReport) {
              // The report is self-contained (inline styles, SVG, data: images).
              res.SetHeader("Content-Security-Policy",
                            "default-src 'none'; style-src 'unsafe-inline'; img-src "
                            "data:; frame-ancestors 'self'");
            }
            res.SetContent(ss.str(), kind.type);
          });
        },
        Lane::kSlow);
  }
}

void HttpApi::Impl::EventStream(const Request& req, Response& res) {
  std::int64_t after = daemon.events().LastId();
  // A reconnecting EventSource says where it stopped; ?after= does the same for other clients.
  if (req.HasHeader("Last-Event-ID")) {
    if (const auto id = ParseId(req.Header("Last-Event-ID"))) after = *id;
    if (req.Header("Last-Event-ID") == "0") after = 0;
  } else if (req.HasParam("after")) {
    after = QueryNumber(req, "after", after);
  }
  std::optional<std::int64_t> run;
  if (req.HasParam("run")) {
    run = ParseId(req.Param("run"));
    if (!run) {
      throw ConfigError("query: run: expected a run id, got \"" + req.Param("run") + "\"", "run");
    }
  }
  res.SetHeader("Cache-Control", "no-store");
  res.SetHeader("X-Accel-Buffering", "no");
  res.SetHeader("Content-Type", "text/event-stream");
  // Runs on the server's I/O thread whenever the hub has published (or at the server's tick):
  // takes what is new without waiting, and says so with a comment when a tick finds nothing.
  EventHub& hub = daemon.events();
  auto last_write = std::chrono::steady_clock::now();
  res.stream = [&hub, after, run, last_write](std::string& out) mutable {
    if (hub.Closed()) return StreamStep::kEnd;
    for (const HubEvent& e : hub.WaitAfter(after, std::chrono::milliseconds(0))) {
      after = e.id;
      if (run && e.data.contains("run") && e.data["run"] != *run) continue;
      out += "id: " + std::to_string(e.id) + "\nevent: " + e.type + "\ndata: " + e.data.dump() +
             "\n\n";
    }
    const auto now = std::chrono::steady_clock::now();
    if (out.empty() && now - last_write >= kKeepAlive) out = ": keep-alive\n\n";
    if (out.empty()) return StreamStep::kWait;
    last_write = now;
    return StreamStep::kData;
  };
}

HttpApi::HttpApi(Daemon& daemon, const ServerConfig& config)
    : impl_(std::make_unique<Impl>(daemon, config)) {
  impl_->Routes();
  // Whatever is published wakes the event streams waiting for it.
  HttpServer& server = impl_->server;
  daemon.events().SetListener([&server] { server.WakeStreams(); });
}

HttpApi::~HttpApi() {
  Stop();
  impl_->daemon.events().SetListener(nullptr);
}

int HttpApi::Bind() {
  impl_->port = impl_->server.Bind();
  return impl_->port;
}

void HttpApi::Serve() {
  impl_->server.Serve();
}

void HttpApi::Stop() {
  impl_->daemon.events().Close();
  impl_->server.Stop();
}

std::string HttpApi::Url() const {
  const std::string host = impl_->config.listen.find(':') != std::string::npos
                               ? "[" + impl_->config.listen + "]"
                               : impl_->config.listen;
  return "http://" + host + ":" + std::to_string(impl_->port);
}

}  // namespace gs360
