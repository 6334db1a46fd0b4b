#pragma once
// gs360d's HTTP server: the JSON API under /api/v1 (docs/api.md), its server-sent event stream,
// and the dashboard at / (static files compiled into the binary; nothing fetched from elsewhere),
// on the event-driven HttpServer (http_server.h: its bounds on connections, time and bodies).
//
// Security (docs/api.md, "Security"):
// - a bearer token (ServerConfig::token), when set, on every /api request (header
//   "Authorization: Bearer T", the scheme in any case, or "?token=T" for EventSource and links),
//   compared in constant time; 401 otherwise;
// - without a token (loopback only) the Host header must name a loopback host, so a web page
//   elsewhere cannot reach the daemon through DNS rebinding;
// - POST bodies must be application/json (application/octet-stream for uploads; the media type
//   exactly, in any case, parameters allowed), which a page on another origin cannot send without
//   the browser asking first (CSRF);
// - bodies above server.max_body_bytes (uploads: max_upload_bytes) get 413, chunked or not; runs
//   and meshes are addressed by id, never by path;
// - event streams beyond server.max_event_streams get 503;
// - malformed JSON, wrong types and unknown fields get 400 naming the field.
// Every error is {"error": {"code", "message", "field"}}.

#include <memory>
#include <stdexcept>
#include <string>

#include "daemon/daemon.h"
#include "daemon/http_server.h"

namespace gs360 {

class HttpApi {
 public:
  HttpApi(Daemon& daemon, const ServerConfig& config);
  ~HttpApi();
  HttpApi(const HttpApi&) = delete;
  HttpApi& operator=(const HttpApi&) = delete;

  // Binds server.listen:server.port (port 0: any free one) and starts answering. Returns the
  // port. Throws ListenError naming the address when it cannot bind (a port that is taken, by
  // another gs360d too, is never shared).
  int Bind();
  // Serves until Stop() (from another thread or a signal handler's thread).
  void Serve();
  // Stops serving; ends the event streams (closes the daemon's event hub).
  void Stop();
  // "http://127.0.0.1:7360" once bound.
  std::string Url() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// Constant-time comparison (the token check).
bool SameSecret(const std::string& a, const std::string& b);

}  // namespace gs360
