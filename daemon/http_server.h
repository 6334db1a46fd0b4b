#pragma once
// An event-driven HTTP/1.1 server (libmicrohttpd, behind this interface). One thread does the
// network I/O of every connection, so an idle socket, a client that sends its headers a byte at a
// time or a long-lived event stream costs a socket and a few kB, never a thread. Handlers run on
// two small pools ("lanes"): a slow request (planning a run, an upload, a large file) waits for a
// slow-lane thread and never delays a quick one (a status poll, a pause).
//
// Bounds (HttpServerOptions): open connections (beyond: closed at once), the time a client may
// take to send a whole request, headers and body (beyond: the connection is cut), the time a
// connection may stay silent, the header size (431), each request's body (413, chunked or not: a
// chunked body past its limit is read on and dropped; past kMaxDiscardBytes more it gets its 413 at
// once and the connection is closed), and open streamed responses (503 beyond).
//
// The listening socket is the server's own: SO_REUSEADDR without SO_REUSEPORT, so a second
// server on a port that is taken fails to bind (ListenError) instead of sharing the port.
//
// Thread-safety: Route/Set* before Bind(); Stop() and WakeStreams() from any thread.

#include <cstdint>
#include <functional>
#include <memory>
#include <stdexcept>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

namespace gs360 {

// The address cannot be bound (in use, or not an address of this machine).
class ListenError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

using HttpFields = std::vector<std::pair<std::string, std::string>>;

struct HttpRequest {
  std::string method;
  std::string path;                  // percent-decoded, without the query
  HttpFields headers;                // as received
  HttpFields params;                 // the query's arguments, decoded
  std::string body;                  // complete once a handler runs; empty in a Screen
  std::vector<std::string> matches;  // the route's groups: [0] the whole path, then each group

  // Header names are case-insensitive; "" when absent.
  std::string Header(std::string_view name) const;
  bool HasHeader(std::string_view name) const;
  std::string Param(std::string_view name) const;
  bool HasParam(std::string_view name) const;
};

// What a streamed body's producer returns each time the server asks it for more.
enum class StreamStep {
  kData,  // `out` holds the next bytes
  kWait,  // nothing yet: asked again after HttpServer::WakeStreams() (or its periodic tick)
  kEnd,   // the body is complete
};
// Runs on the I/O thread: must not block.
using StreamProducer = std::function<StreamStep(std::string& out)>;

struct HttpResponse {
  int status = 200;
  HttpFields headers;
  std::string body;
  StreamProducer stream;  // when set, the body is streamed (chunked) and `body` is unused

  void SetHeader(std::string name, std::string value);
  void SetContent(std::string content, std::string content_type);
};

enum class Lane { kQuick, kSlow };

struct HttpServerOptions {
  std::string listen = "127.0.0.1";
  int port = 0;                   // 0: any free port
  int quick_threads = 2;          // status, control, small reads
  int slow_threads = 4;           // planning, uploads, files
  int max_connections = 2048;     // open sockets, streams and idle ones included
  int max_streams = 256;          // streamed responses (event streams) open at once
  double request_timeout_s = 15;  // to send a whole request, from the connection's start or the
                                  // end of its previous response (idle keep-alive included)
  int idle_timeout_s = 10;        // a connection with no byte either way is closed
  double stream_tick_s = 4;       // streams are woken this often (their keep-alives)
  std::int64_t max_header_bytes = 32 << 10;
  std::int64_t max_body_bytes = 1 << 20;  // unless the BodyLimit says otherwise
  void Check() const;                     // throws ConfigError naming the field
};

class HttpServer {
 public:
  // A chunked body past its limit is read on, dropped, for at most this many bytes more.
  static constexpr std::int64_t kMaxDiscardBytes = 64 << 20;

  using Handler = std::function<void(const HttpRequest&, HttpResponse&)>;
  // Sees each request once its headers are in, before its body is read, on the I/O thread
  // (must not block). Returns true when it has answered (the body is then not read).
  using Screen = std::function<bool(const HttpRequest&, HttpResponse&)>;
  // The largest body a request may send (bytes).
  using BodyLimit = std::function<std::int64_t(const HttpRequest&)>;
  // Fills the body of an error the server itself answers: 404, 405, 413, 500, 503.
  using ErrorPage = std::function<void(const HttpRequest&, HttpResponse&)>;

  explicit HttpServer(HttpServerOptions options);
  ~HttpServer();
  HttpServer(const HttpServer&) = delete;
  HttpServer& operator=(const HttpServer&) = delete;

  // `pattern` is an ECMAScript regex matched against the whole path.
  void Route(const std::string& method, const std::string& pattern, Handler handler,
             Lane lane = Lane::kQuick);
  void SetScreen(Screen screen);
  void SetBodyLimit(BodyLimit limit);
  void SetErrorPage(ErrorPage page);

  // Binds listen:port and starts serving on the I/O thread. Returns the port. Throws ListenError
  // naming the address and the reason.
  int Bind();
  // Blocks until Stop().
  void Serve();
  // Stops accepting, ends streams (their producers are asked once more, then the connection is
  // closed), finishes the handlers under way, closes every connection. Idempotent.
  void Stop();
  // Asks every waiting stream's producer again (new data to send).
  void WakeStreams();

  struct Stats {
    int connections = 0;
    int streams = 0;
    std::int64_t timed_out = 0;  // connections cut for a request too slow to arrive
  };
  Stats GetStats() const;

  struct Impl;  // the backend's (opaque; public for its C callbacks)

 private:
  std::unique_ptr<Impl> impl_;
};

}  // namespace gs360
