#include "daemon/http_api.h"

#include <httplib.h>

#include <algorithm>
#include <charconv>
#include <fstream>
#include <sstream>

#include <spdlog/spdlog.h>

#include "base/json_reader.h"
#include "daemon/web_assets.h"
#include "geometry/mesh.h"
#include "storage/storage_error.h"

namespace gs360 {
namespace {

using Json = nlohmann::json;
using httplib::Request;
using httplib::Response;

void SendJson(Response& res, int status, const Json& body) {
  res.status = status;
  // Messages may quote what a client sent, bytes that are not UTF-8 included.
  res.set_content(body.dump(-1, ' ', false, Json::error_handler_t::replace),
                  // Not the exact type cpp-httplib compresses: brotli at its slowest setting cost
                  // seconds on large bodies (10,000 probes), and JSON polls are latency-bound.
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

bool HostIsLoopback(const std::string& host_header) {
  std::string host = host_header;
  if (!host.empty() && host[0] == '[') {
    host = host.substr(1, host.find(']') == std::string::npos ? 0 : host.find(']') - 1);
  } else if (const auto colon = host.rfind(':'); colon != std::string::npos) {
    host = host.substr(0, colon);
  }
  return IsLoopbackAddress(host);
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
  res.set_header("Cache-Control", "no-store");
  res.set_content(reinterpret_cast<const char*>(png->data()), png->size(), "image/png");
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
  httplib::Server server;
  int port = 0;

  Impl(Daemon& d, const ServerConfig& c) : daemon(d), config(c) {}

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

  httplib::Server::HandlerResponse Screen(const Request& req, Response& res);
  void Routes();
  void RunRoutes();
  void FileRoutes();
  void EventStream(const Request& req, Response& res);
};

httplib::Server::HandlerResponse HttpApi::Impl::Screen(const Request& req, Response& res) {
  using R = httplib::Server::HandlerResponse;
  res.set_header("X-Content-Type-Options", "nosniff");
  res.set_header("Referrer-Policy", "no-referrer");
  if (config.token.empty() && !HostIsLoopback(req.get_header_value("Host"))) {
    SendError(res, 403, "forbidden",
              "this daemon answers only to a loopback Host (no token is configured)");
    return R::Handled;
  }
  if (req.path.rfind("/api/", 0) != 0) return R::Unhandled;
  if (!config.token.empty()) {
    std::string given;
    const std::string auth = req.get_header_value("Authorization");
    if (auth.rfind("Bearer ", 0) == 0) given = auth.substr(7);
    if (given.empty() && req.has_param("token")) given = req.get_param_value("token");
    if (given.empty() || !SameSecret(given, config.token)) {
      res.set_header("WWW-Authenticate", "Bearer");
      res.set_header("Connection", "close");
      SendError(res, 401, "unauthorized",
                given.empty() ? "this daemon needs a token: Authorization: Bearer <token>"
                              : "wrong token");
      return R::Handled;
    }
  }
  if (req.method == "POST") {
    const std::string type = req.get_header_value("Content-Type");
    const bool upload = req.path == "/api/v1/meshes";
    const std::string want = upload ? "application/octet-stream" : "application/json";
    if (type.rfind(want, 0) != 0) {
      res.set_header("Connection", "close");
      SendError(res, 415, "unsupported_media_type",
                "POST " + req.path + " takes Content-Type: " + want);
      return R::Handled;
    }
    // The body is not read yet: judge it by its declared length (a chunked body is capped by
    // the server's payload limit, and JSON bodies again in ParseBody).
    const auto limit =
        static_cast<std::uint64_t>(upload ? config.max_upload_bytes : config.max_body_bytes);
    const std::string length = req.get_header_value("Content-Length");
    std::uint64_t declared = 0;
    std::from_chars(length.data(), length.data() + length.size(), declared);
    if (declared > limit) {
      res.set_header("Connection", "close");
      SendError(res, 413, "too_large",
                "the body is larger than " + std::to_string(limit) + " bytes");
      return R::Handled;
    }
  }
  return R::Unhandled;
}

void HttpApi::Impl::Routes() {
  server.set_pre_routing_handler(
      [this](const Request& req, Response& res) { return Screen(req, res); });
  server.set_error_handler(httplib::Server::HandlerWithResponse(
      [](const Request& req, Response& res) -> httplib::Server::HandlerResponse {
        if (!res.body.empty()) return httplib::Server::HandlerResponse::Unhandled;
        if (res.status == 413) {
          SendError(res, 413, "too_large", "the request body is too large");
        } else if (res.status == 404) {
          SendError(res, 404, "not_found", "no such resource: " + req.method + " " + req.path);
        } else {
          SendError(res, res.status, "http_" + std::to_string(res.status), "request refused");
        }
        return httplib::Server::HandlerResponse::Handled;
      }));
  server.set_exception_handler([](const Request&, Response& res, std::exception_ptr ep) {
    std::string what = "unknown error";
    try {
      if (ep) std::rethrow_exception(ep);
    } catch (const std::exception& e) {
      what = e.what();
    } catch (...) {
    }
    SendError(res, 500, "internal", what);
  });
  for (const WebAsset& asset : WebAssets()) {
    const std::string path = asset.path == "/index.html" ? "/" : std::string(asset.path);
    server.Get(path, [asset](const Request&, Response& res) {
      res.set_header("Content-Security-Policy",
                     "default-src 'self'; img-src 'self' data: blob:; frame-src 'self'; "
                     "object-src 'none'; base-uri 'none'; frame-ancestors 'self'");
      res.set_header("Cache-Control", "no-cache");
      res.set_content(std::string(asset.content), std::string(asset.type));
    });
  }
  server.Get("/api/v1/info", [this](const Request&, Response& res) {
    Guarded(res, [&] { SendJson(res, 200, daemon.Info()); });
  });
  server.Get("/api/v1/events",
             [this](const Request& req, Response& res) { EventStream(req, res); });
  server.Get("/api/v1/meshes", [this](const Request&, Response& res) {
    Guarded(res, [&] { SendJson(res, 200, daemon.ListMeshes()); });
  });
  server.Post("/api/v1/meshes", [this](const Request& req, Response& res) {
    Guarded(res, [&] {
      const std::string format = req.has_param("format") ? req.get_param_value("format") : "stl";
      SendJson(res, 201, daemon.UploadMesh(req.body, format));
    });
  });
  RunRoutes();
  FileRoutes();
}

void HttpApi::Impl::RunRoutes() {
  server.Get("/api/v1/runs", [this](const Request&, Response& res) {
    Guarded(res, [&] { SendJson(res, 200, daemon.ListRuns()); });
  });
  server.Post("/api/v1/runs", [this](const Request& req, Response& res) {
    Guarded(res, [&] {
      bool created = false;
      const Json view = daemon.CreateRun(ParseBody(req, config.max_body_bytes), &created);
      SendJson(res, created ? 201 : 200, view);
    });
  });
  server.Get(R"(/api/v1/runs/([^/]+))", [this](const Request& req, Response& res) {
    Guarded(res, [&] {
      const auto id = ParseId(req.matches[1]);
      const auto view = id ? daemon.GetRun(*id) : std::nullopt;
      if (!view) return SendError(res, 404, "not_found", "no run " + std::string(req.matches[1]));
      SendJson(res, 200, *view);
    });
  });
  server.Delete(R"(/api/v1/runs/([^/]+))", [this](const Request& req, Response& res) {
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
  server.Post(R"(/api/v1/runs/([^/]+)/(start|pause|resume|cancel|calibrate))",
              [this](const Request& req, Response& res) {
                Guarded(res, [&] {
                  const auto id = ParseId(req.matches[1]);
                  if (!id) {
                    return SendError(res, 404, "not_found",
                                     "no run " + std::string(req.matches[1]));
                  }
                  const Json body = ParseBody(req, config.max_body_bytes);
                  const std::string action = req.matches[2];
                  std::string confirm;
                  if (action == "start" || action == "resume") {
                    JsonReader reader(body, "request");
                    reader.Get("confirm", confirm);
                    reader.RejectUnknown();
                  } else if (action != "calibrate" && !body.empty()) {
                    throw ConfigError(
                        "request body: " + action + " takes no fields, got " + body.begin().key(),
                        body.begin().key());
                  }
                  ActionResult r;
                  if (action == "start") r = daemon.Start(*id, confirm);
                  if (action == "pause") r = daemon.Pause(*id);
                  if (action == "resume") r = daemon.Resume(*id, confirm);
                  if (action == "cancel") r = daemon.Cancel(*id);
                  if (action == "calibrate") r = daemon.Calibrate(*id, body);
                  SendAction(res, *id, r);
                });
              });
  server.Get(R"(/api/v1/runs/([^/]+)/probes)", [this](const Request& req, Response& res) {
    Guarded(res, [&] {
      const auto id = ParseId(req.matches[1]);
      const auto probes = id ? daemon.ListProbes(*id) : std::nullopt;
      if (!probes) return SendError(res, 404, "not_found", "no run " + std::string(req.matches[1]));
      SendJson(res, 200, *probes);
    });
  });
  server.Get(R"(/api/v1/runs/([^/]+)/log)", [this](const Request& req, Response& res) {
    Guarded(res, [&] {
      const auto id = ParseId(req.matches[1]);
      std::int64_t after = 0;
      if (req.has_param("after")) after = ParseId(req.get_param_value("after")).value_or(0);
      const auto log = id ? daemon.RunLog(*id, after, 1000) : std::nullopt;
      if (!log) return SendError(res, 404, "not_found", "no run " + std::string(req.matches[1]));
      SendJson(res, 200, *log);
    });
  });
  server.Get(R"(/api/v1/runs/([^/]+)/calibration)", [this](const Request& req, Response& res) {
    Guarded(res, [&] {
      const auto id = ParseId(req.matches[1]);
      const auto view = id ? daemon.Calibration(*id) : std::nullopt;
      if (!view) return SendError(res, 404, "not_found", "no run " + std::string(req.matches[1]));
      SendJson(res, 200, *view);
    });
  });
}

void HttpApi::Impl::FileRoutes() {
  server.Get(R"(/api/v1/runs/([^/]+)/frames/latest\.png)",
             [this](const Request& req, Response& res) {
               Guarded(res, [&] {
                 const auto id = ParseId(req.matches[1]);
                 SendPng(res, id ? daemon.LatestFramePng(*id) : std::nullopt,
                         "no frame of run " + std::string(req.matches[1]) + " yet");
               });
             });
  server.Get(R"(/api/v1/runs/([^/]+)/probes/([^/]+)/frame\.png)", [this](const Request& req,
                                                                         Response& res) {
    Guarded(res, [&] {
      const auto id = ParseId(req.matches[1]);
      const std::string n = req.matches[2];
      const bool index_ok =
          !n.empty() && n.size() < 9 && n.find_first_not_of("0123456789") == std::string::npos;
      SendPng(res, id && index_ok ? daemon.ProbeFramePng(*id, std::stoi(n)) : std::nullopt,
              "no captured probe " + n + " in run " + std::string(req.matches[1]));
    });
  });
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
    server.Get(std::string(R"(/api/v1/runs/([^/]+)/)") + kind.suffix,
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
                     res.set_header("Content-Disposition",
                                    "attachment; filename=\"" + path->filename().string() + "\"");
                   }
                   if (kind.file == RunFile::kReport) {
                     // The report is self-contained (inline styles, SVG, data: images).
                     res.set_header("Content-Security-Policy",
                                    "default-src 'none'; style-src 'unsafe-inline'; img-src "
                                    "data:; frame-ancestors 'self'");
                   }
                   res.set_content(ss.str(), kind.type);
                 });
               });
  }
}

void HttpApi::Impl::EventStream(const Request& req, Response& res) {
  std::int64_t after = daemon.events().LastId();
  // A reconnecting EventSource says where it stopped; ?after= does the same for other clients.
  const std::string last = req.has_header("Last-Event-ID") ? req.get_header_value("Last-Event-ID")
                           : req.has_param("after")        ? req.get_param_value("after")
                                                           : "";
  if (!last.empty()) {
    if (last == "0") after = 0;
    if (const auto id = ParseId(last)) after = *id;
  }
  std::optional<std::int64_t> run;
  if (req.has_param("run")) run = ParseId(req.get_param_value("run"));
  res.set_header("Cache-Control", "no-store");
  res.set_header("X-Accel-Buffering", "no");
  EventHub& hub = daemon.events();
  res.set_chunked_content_provider(
      "text/event-stream", [&hub, after, run](std::size_t, httplib::DataSink& sink) mutable {
        const auto events = hub.WaitAfter(after, std::chrono::seconds(10));
        if (hub.Closed()) {
          sink.done();
          return true;
        }
        std::string out;
        for (const HubEvent& e : events) {
          after = e.id;
          if (run && e.data.contains("run") && e.data["run"] != *run) continue;
          out += "id: " + std::to_string(e.id) + "\nevent: " + e.type + "\ndata: " + e.data.dump() +
                 "\n\n";
        }
        if (out.empty()) out = ": keep-alive\n\n";
        return sink.write(out.data(), out.size());
      });
}

HttpApi::HttpApi(Daemon& daemon, const ServerConfig& config)
    : impl_(std::make_unique<Impl>(daemon, config)) {
  const int threads = config.threads;
  impl_->server.new_task_queue = [threads] { return new httplib::ThreadPool(threads); };
  // The transport's own cap, above which cpp-httplib answers 413 without reading the body;
  // Screen() applies the per-endpoint limits below it.
  impl_->server.set_payload_max_length(
      static_cast<std::size_t>(std::max(config.max_upload_bytes, config.max_body_bytes)));
  impl_->server.set_read_timeout(10, 0);
  impl_->server.set_write_timeout(10, 0);
  impl_->server.set_keep_alive_max_count(1000);
  impl_->server.set_keep_alive_timeout(5);
  impl_->Routes();
}

HttpApi::~HttpApi() {
  Stop();
}

int HttpApi::Bind() {
  const ServerConfig& c = impl_->config;
  if (c.port == 0) {
    impl_->port = impl_->server.bind_to_any_port(c.listen);
    if (impl_->port < 0) impl_->port = 0;
  } else if (impl_->server.bind_to_port(c.listen, c.port)) {
    impl_->port = c.port;
  }
  if (impl_->port <= 0) {
    throw ListenError("cannot listen on " + c.listen + ":" + std::to_string(c.port) +
                      " (in use, or not an address of this machine)");
  }
  return impl_->port;
}

void HttpApi::Serve() {
  impl_->server.listen_after_bind();
}

void HttpApi::Stop() {
  // Event streams would otherwise hold their worker threads (and this stop) until their next
  // keep-alive.
  impl_->daemon.events().Close();
  impl_->server.stop();
}

std::string HttpApi::Url() const {
  const std::string host = impl_->config.listen.find(':') != std::string::npos
                               ? "[" + impl_->config.listen + "]"
                               : impl_->config.listen;
  return "http://" + host + ":" + std::to_string(impl_->port);
}

}  // namespace gs360
