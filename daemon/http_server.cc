#include "daemon/http_server.h"

#include <arpa/inet.h>
#include <microhttpd.h>
#include <netdb.h>
#include <netinet/in.h>
#include <strings.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdarg>
#include <cstring>
#include <deque>
#include <mutex>
#include <regex>
#include <set>
#include <thread>

#include <spdlog/spdlog.h>

#include "base/json_reader.h"

namespace gs360 {
namespace {

using Clock = std::chrono::steady_clock;

bool SameName(std::string_view a, std::string_view b) {
  return a.size() == b.size() && strncasecmp(a.data(), b.data(), a.size()) == 0;
}

const std::string* Find(const HttpFields& fields, std::string_view name, bool any_case) {
  for (const auto& [key, value] : fields) {
    if (any_case ? SameName(key, name) : key == name) return &value;
  }
  return nullptr;
}

// A fixed set of threads taking jobs in order. Stop() runs what is queued, then joins.
class WorkerPool {
 public:
  explicit WorkerPool(int threads) {
    for (int i = 0; i < threads; ++i) threads_.emplace_back([this] { Work(); });
  }
  ~WorkerPool() { Stop(); }
  void Post(std::function<void()> job) {
    {
      std::lock_guard lock(mutex_);
      jobs_.push_back(std::move(job));
    }
    ready_.notify_one();
  }
  void Stop() {
    {
      std::lock_guard lock(mutex_);
      stopping_ = true;
    }
    ready_.notify_all();
    for (std::thread& t : threads_) {
      if (t.joinable()) t.join();
    }
  }

 private:
  void Work() {
    for (;;) {
      std::function<void()> job;
      {
        std::unique_lock lock(mutex_);
        ready_.wait(lock, [this] { return stopping_ || !jobs_.empty(); });
        if (jobs_.empty()) return;
        job = std::move(jobs_.front());
        jobs_.pop_front();
      }
      job();
    }
  }
  std::mutex mutex_;
  std::condition_variable ready_;
  std::deque<std::function<void()>> jobs_;
  std::vector<std::thread> threads_;
  bool stopping_ = false;
};

struct RouteEntry {
  std::string method;
  std::regex pattern;
  HttpServer::Handler handler;
  Lane lane;
};

// One connection (libmicrohttpd's socket context): how long it has been waiting for a request.
struct Connection {
  int fd = -1;
  Clock::time_point waiting_since = Clock::now();
  bool receiving = true;  // between requests, or reading one
  bool cut = false;
};

// One request (libmicrohttpd's request context), from its headers to its response.
struct Exchange {
  enum State { kReceiving, kHandling, kReady };
  HttpRequest request;
  HttpResponse response;
  const RouteEntry* route = nullptr;
  std::int64_t limit = 0;
  std::int64_t discarded = 0;
  bool too_large = false;
  std::atomic<int> state{kReceiving};
};

struct Stream;

int MakeListenSocket(const std::string& host, int port, int* bound_port);

}  // namespace

struct HttpServer::Impl {
  HttpServerOptions options;
  std::vector<RouteEntry> routes;
  Screen screen;
  BodyLimit body_limit;
  ErrorPage error_page;
  MHD_Daemon* mhd = nullptr;
  int listen_fd = -1;
  int port = 0;
  std::unique_ptr<WorkerPool> quick;
  std::unique_ptr<WorkerPool> slow;
  std::thread sweeper;

  mutable std::mutex mutex;  // guards everything below
  std::condition_variable stopped_cv;
  bool stopping = false;
  bool stopped = false;
  std::set<Connection*> connections;
  std::set<Stream*> streams;
  std::int64_t timed_out = 0;

  explicit Impl(HttpServerOptions o) : options(std::move(o)) {}

  void Error(const HttpRequest& request, HttpResponse& response, int status) {
    response = HttpResponse{};
    response.status = status;
    if (error_page) error_page(request, response);
  }
  MHD_Result Queue(MHD_Connection* c, Exchange& ex);
  MHD_Result Access(MHD_Connection* c, const char* url, const char* method, const char* data,
                    std::size_t* size, void** context);
  MHD_Result Begin(MHD_Connection* c, const char* url, const char* method, Exchange& ex);
  MHD_Result Dispatch(MHD_Connection* c, Exchange& ex);
  void CutOff(MHD_Connection* c, Exchange& ex);
  void Sweep();
  void WakeLocked();
};

namespace {

// A streamed response: the producer, the bytes not yet taken, and whether it is suspended.
struct Stream {
  HttpServer::Impl* server = nullptr;
  MHD_Connection* connection = nullptr;
  StreamProducer producer;
  std::string pending;
  std::size_t offset = 0;
  bool suspended = false;  // under server->mutex
  bool woken = false;      // under server->mutex: woken while it was not suspended
};

ssize_t StreamRead(void* cls, std::uint64_t, char* buf, std::size_t max) {
  auto* s = static_cast<Stream*>(cls);
  for (;;) {
    if (s->offset < s->pending.size()) {
      const std::size_t n = std::min(max, s->pending.size() - s->offset);
      std::memcpy(buf, s->pending.data() + s->offset, n);
      s->offset += n;
      return static_cast<ssize_t>(n);
    }
    s->pending.clear();
    s->offset = 0;
    if (s->producer(s->pending) == StreamStep::kEnd) return MHD_CONTENT_READER_END_OF_STREAM;
    if (!s->pending.empty()) continue;
    std::lock_guard lock(s->server->mutex);
    if (s->server->stopping) return MHD_CONTENT_READER_END_OF_STREAM;
    // Woken between the producer's answer and here: ask it again rather than sleep through it.
    if (s->woken) {
      s->woken = false;
      continue;
    }
    s->suspended = true;
    MHD_suspend_connection(s->connection);
    return 0;
  }
}

void StreamFree(void* cls) {
  auto* s = static_cast<Stream*>(cls);
  {
    std::lock_guard lock(s->server->mutex);
    s->server->streams.erase(s);
  }
  delete s;
}

MHD_Result CollectField(void* cls, MHD_ValueKind, const char* key, const char* value) {
  static_cast<HttpFields*>(cls)->emplace_back(key ? key : "", value ? value : "");
  return MHD_YES;
}

void LogFromLibrary(void*, const char* format, va_list args) {
  char line[512];
  std::vsnprintf(line, sizeof line, format, args);
  std::string text(line);
  while (!text.empty() && (text.back() == '\n' || text.back() == '\r')) text.pop_back();
  spdlog::debug("http: {}", text);
}

int MakeListenSocket(const std::string& host, int port, int* bound_port) {
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  hints.ai_flags = AI_PASSIVE | AI_NUMERICSERV;
  addrinfo* found = nullptr;
  const std::string where = host + ":" + std::to_string(port);
  if (const int rc = getaddrinfo(host.c_str(), std::to_string(port).c_str(), &hints, &found)) {
    throw ListenError("cannot listen on " + where + ": " + gai_strerror(rc));
  }
  std::string reason = "no address";
  int fd = -1;
  for (addrinfo* a = found; a != nullptr && fd < 0; a = a->ai_next) {
    fd = socket(a->ai_family, a->ai_socktype | SOCK_CLOEXEC, a->ai_protocol);
    if (fd < 0) continue;
    // SO_REUSEADDR lets a restarted daemon bind while old connections linger in TIME_WAIT; it
    // does not let two sockets listen on one port. SO_REUSEPORT (never set) would.
    const int one = 1;
    setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
    if (bind(fd, a->ai_addr, a->ai_addrlen) != 0 || listen(fd, SOMAXCONN) != 0) {
      reason = std::strerror(errno);
      close(fd);
      fd = -1;
    }
  }
  freeaddrinfo(found);
  if (fd < 0) {
    throw ListenError("cannot listen on " + where + ": " + reason +
                      (reason == std::strerror(EADDRINUSE)
                           ? " (another gs360d, or another program, has this port)"
                           : ""));
  }
  sockaddr_storage addr{};
  socklen_t len = sizeof addr;
  getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len);
  *bound_port = ntohs(addr.ss_family == AF_INET6 ? reinterpret_cast<sockaddr_in6*>(&addr)->sin6_port
                                                 : reinterpret_cast<sockaddr_in*>(&addr)->sin_port);
  return fd;
}

}  // namespace

std::string HttpRequest::Header(std::string_view name) const {
  const std::string* v = Find(headers, name, true);
  return v ? *v : std::string();
}
bool HttpRequest::HasHeader(std::string_view name) const {
  return Find(headers, name, true) != nullptr;
}
std::string HttpRequest::Param(std::string_view name) const {
  const std::string* v = Find(params, name, false);
  return v ? *v : std::string();
}
bool HttpRequest::HasParam(std::string_view name) const {
  return Find(params, name, false) != nullptr;
}

void HttpResponse::SetHeader(std::string name, std::string value) {
  for (auto& [key, v] : headers) {
    if (SameName(key, name)) {
      v = std::move(value);
      return;
    }
  }
  headers.emplace_back(std::move(name), std::move(value));
}

void HttpResponse::SetContent(std::string content, std::string content_type) {
  body = std::move(content);
  SetHeader("Content-Type", std::move(content_type));
}

void HttpServerOptions::Check() const {
  auto positive = [](const char* field, double v) {
    if (!(v > 0))
      throw ConfigError(std::string(field) + ": must be > 0, got " + std::to_string(v), field);
  };
  positive("server.quick_threads", quick_threads);
  positive("server.threads", slow_threads);
  positive("server.max_connections", max_connections);
  positive("server.max_event_streams", max_streams);
  positive("server.request_timeout_s", request_timeout_s);
  positive("server.idle_timeout_s", idle_timeout_s);
  positive("stream_tick_s", stream_tick_s);
  positive("max_header_bytes", static_cast<double>(max_header_bytes));
  positive("server.max_body_bytes", static_cast<double>(max_body_bytes));
}

MHD_Result HttpServer::Impl::Queue(MHD_Connection* c, Exchange& ex) {
  HttpResponse& res = ex.response;
  MHD_Response* r = nullptr;
  if (res.stream) {
    std::lock_guard lock(mutex);
    if (static_cast<int>(streams.size()) >= options.max_streams || stopping) {
      const bool full = !stopping;
      Error(ex.request, res, 503);
      res.SetHeader("Retry-After", "30");
      if (full) spdlog::warn("http: {} streams open, refused one more", streams.size());
    } else {
      auto* s = new Stream;
      s->server = this;
      s->connection = c;
      s->producer = std::move(res.stream);
      streams.insert(s);
      r = MHD_create_response_from_callback(MHD_SIZE_UNKNOWN, 8192, &StreamRead, s, &StreamFree);
    }
  }
  if (r == nullptr) {
    r = MHD_create_response_from_buffer(res.body.size(), res.body.data(), MHD_RESPMEM_MUST_COPY);
  }
  for (const auto& [name, value] : res.headers) {
    MHD_add_response_header(r, name.c_str(), value.c_str());
  }
  const MHD_Result ok = MHD_queue_response(c, static_cast<unsigned>(res.status), r);
  MHD_destroy_response(r);
  return ok;
}

MHD_Result HttpServer::Impl::Begin(MHD_Connection* c, const char* url, const char* method,
                                   Exchange& ex) {
  HttpRequest& req = ex.request;
  req.method = method;
  req.path = url;
  MHD_get_connection_values(c, MHD_HEADER_KIND, &CollectField, &req.headers);
  MHD_get_connection_values(c, MHD_GET_ARGUMENT_KIND, &CollectField, &req.params);
  if (screen && screen(req, ex.response)) return Queue(c, ex);
  ex.limit = body_limit ? body_limit(req) : options.max_body_bytes;
  // A declared length over the limit is refused before a byte of the body is read.
  const std::string length = req.Header("Content-Length");
  if (!length.empty() &&
      std::strtoull(length.c_str(), nullptr, 10) > static_cast<unsigned long long>(ex.limit)) {
    Error(req, ex.response, 413);
    return Queue(c, ex);
  }
  return MHD_YES;
}

// A body that goes on long past its limit: the 413 is written straight to the socket (the library
// answers only once a body has ended) and the connection is then closed. A client that reads
// while it sends sees the 413; one that only sends sees the connection cut.
void HttpServer::Impl::CutOff(MHD_Connection* c, Exchange& ex) {
  const auto* info = MHD_get_connection_info(c, MHD_CONNECTION_INFO_CONNECTION_FD);
  if (info == nullptr) return;
  Error(ex.request, ex.response, 413);
  std::string head = "HTTP/1.1 413 Content Too Large\r\nConnection: close\r\nContent-Length: " +
                     std::to_string(ex.response.body.size()) + "\r\n";
  for (const auto& [name, value] : ex.response.headers) head += name + ": " + value + "\r\n";
  const std::string out = head + "\r\n" + ex.response.body;
  ::send(info->connect_fd, out.data(), out.size(), MSG_NOSIGNAL | MSG_DONTWAIT);
  ::shutdown(info->connect_fd, SHUT_WR);
}

MHD_Result HttpServer::Impl::Dispatch(MHD_Connection* c, Exchange& ex) {
  if (ex.too_large) {
    Error(ex.request, ex.response, 413);
    ex.response.SetHeader("Connection", "close");
    return Queue(c, ex);
  }
  bool path_known = false;
  for (const RouteEntry& route : routes) {
    std::smatch m;
    if (!std::regex_match(ex.request.path, m, route.pattern)) continue;
    path_known = true;
    if (route.method != ex.request.method &&
        !(route.method == "GET" && ex.request.method == "HEAD")) {
      continue;
    }
    ex.request.matches.assign(m.begin(), m.end());
    ex.route = &route;
    break;
  }
  if (ex.route == nullptr) {
    Error(ex.request, ex.response, path_known ? 405 : 404);
    return Queue(c, ex);
  }
  // The connection stays suspended (the request context alive) until the job resumes it. Posted
  // under the lock that Stop() takes first, so that no job lands in a pool that has stopped.
  {
    std::lock_guard lock(mutex);
    if (!stopping) {
      ex.state = Exchange::kHandling;
      MHD_suspend_connection(c);
      WorkerPool& pool = ex.route->lane == Lane::kSlow ? *slow : *quick;
      pool.Post([this, c, &ex] {
        try {
          ex.route->handler(ex.request, ex.response);
        } catch (const std::exception& e) {
          spdlog::error("http: {} {}: {}", ex.request.method, ex.request.path, e.what());
          Error(ex.request, ex.response, 500);
        }
        ex.state = Exchange::kReady;
        MHD_resume_connection(c);
      });
      return MHD_YES;
    }
  }
  Error(ex.request, ex.response, 503);
  return Queue(c, ex);
}

MHD_Result HttpServer::Impl::Access(MHD_Connection* c, const char* url, const char* method,
                                    const char* data, std::size_t* size, void** context) {
  auto* ex = static_cast<Exchange*>(*context);
  if (ex == nullptr) {
    ex = new Exchange;
    *context = ex;
    return Begin(c, url, method, *ex);
  }
  if (*size > 0) {
    const auto n = static_cast<std::int64_t>(*size);
    if (!ex->too_large && static_cast<std::int64_t>(ex->request.body.size()) + n <= ex->limit) {
      ex->request.body.append(data, *size);
    } else {
      // libmicrohttpd cannot answer before the body's end: drop it, answer 413 at its end.
      ex->too_large = true;
      ex->request.body.clear();
      ex->request.body.shrink_to_fit();
      ex->discarded += n;
      if (ex->discarded > kMaxDiscardBytes) {
        CutOff(c, *ex);
        return MHD_NO;
      }
    }
    *size = 0;
    return MHD_YES;
  }
  if (ex->state == Exchange::kReady) return Queue(c, *ex);
  if (ex->state == Exchange::kHandling) return MHD_YES;
  const auto* info = MHD_get_connection_info(c, MHD_CONNECTION_INFO_SOCKET_CONTEXT);
  if (info != nullptr && info->socket_context != nullptr) {
    std::lock_guard lock(mutex);
    static_cast<Connection*>(info->socket_context)->receiving = false;
  }
  return Dispatch(c, *ex);
}

void HttpServer::Impl::Sweep() {
  auto next_tick = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                      std::chrono::duration<double>(options.stream_tick_s));
  const auto limit = std::chrono::duration_cast<Clock::duration>(
      std::chrono::duration<double>(options.request_timeout_s));
  std::unique_lock lock(mutex);
  while (!stopping) {
    stopped_cv.wait_for(lock, std::chrono::milliseconds(200));
    if (stopping) break;
    const auto now = Clock::now();
    for (Connection* conn : connections) {
      if (conn->receiving && !conn->cut && now - conn->waiting_since > limit) {
        // The I/O thread then reads the end of the stream and closes the connection; the fd
        // is still its own (a connection is forgotten here before its socket is closed).
        shutdown(conn->fd, SHUT_RDWR);
        conn->cut = true;
        ++timed_out;
      }
    }
    if (now >= next_tick) {
      WakeLocked();
      next_tick = now + std::chrono::duration_cast<Clock::duration>(
                            std::chrono::duration<double>(options.stream_tick_s));
    }
  }
}

void HttpServer::Impl::WakeLocked() {
  for (Stream* s : streams) {
    if (s->suspended) {
      s->suspended = false;
      MHD_resume_connection(s->connection);
    } else {
      s->woken = true;
    }
  }
}

HttpServer::HttpServer(HttpServerOptions options)
    : impl_(std::make_unique<Impl>(std::move(options))) {
  impl_->options.Check();
}

HttpServer::~HttpServer() {
  Stop();
}

void HttpServer::Route(const std::string& method, const std::string& pattern, Handler handler,
                       Lane lane) {
  impl_->routes.push_back({method, std::regex(pattern), std::move(handler), lane});
}
void HttpServer::SetScreen(Screen screen) {
  impl_->screen = std::move(screen);
}
void HttpServer::SetBodyLimit(BodyLimit limit) {
  impl_->body_limit = std::move(limit);
}
void HttpServer::SetErrorPage(ErrorPage page) {
  impl_->error_page = std::move(page);
}

namespace {

MHD_Result AccessThunk(void* cls, MHD_Connection* c, const char* url, const char* method,
                       const char*, const char* data, std::size_t* size, void** context) {
  return static_cast<HttpServer::Impl*>(cls)->Access(c, url, method, data, size, context);
}

void CompletedThunk(void* cls, MHD_Connection* c, void** context, MHD_RequestTerminationCode) {
  delete static_cast<Exchange*>(*context);
  *context = nullptr;
  auto* impl = static_cast<HttpServer::Impl*>(cls);
  const auto* info = MHD_get_connection_info(c, MHD_CONNECTION_INFO_SOCKET_CONTEXT);
  if (info == nullptr || info->socket_context == nullptr) return;
  std::lock_guard lock(impl->mutex);
  auto* conn = static_cast<Connection*>(info->socket_context);
  conn->receiving = true;
  conn->waiting_since = Clock::now();
}

void ConnectionThunk(void* cls, MHD_Connection* c, void** socket_context,
                     MHD_ConnectionNotificationCode code) {
  auto* impl = static_cast<HttpServer::Impl*>(cls);
  std::lock_guard lock(impl->mutex);
  if (code == MHD_CONNECTION_NOTIFY_STARTED) {
    auto* conn = new Connection;
    const auto* info = MHD_get_connection_info(c, MHD_CONNECTION_INFO_CONNECTION_FD);
    conn->fd = info ? info->connect_fd : -1;
    impl->connections.insert(conn);
    *socket_context = conn;
  } else if (*socket_context != nullptr) {
    // Called before libmicrohttpd closes the socket: the sweeper never sees a reused fd.
    auto* conn = static_cast<Connection*>(*socket_context);
    impl->connections.erase(conn);
    delete conn;
    *socket_context = nullptr;
  }
}

}  // namespace

int HttpServer::Bind() {
  Impl& s = *impl_;
  s.listen_fd = MakeListenSocket(s.options.listen, s.options.port, &s.port);
  s.quick = std::make_unique<WorkerPool>(s.options.quick_threads);
  s.slow = std::make_unique<WorkerPool>(s.options.slow_threads);
  MHD_OptionItem items[] = {
      {MHD_OPTION_LISTEN_SOCKET, s.listen_fd, nullptr},
      {MHD_OPTION_CONNECTION_LIMIT, s.options.max_connections, nullptr},
      {MHD_OPTION_CONNECTION_TIMEOUT, s.options.idle_timeout_s, nullptr},
      {MHD_OPTION_CONNECTION_MEMORY_LIMIT, static_cast<intptr_t>(s.options.max_header_bytes),
       nullptr},
      {MHD_OPTION_NOTIFY_COMPLETED, reinterpret_cast<intptr_t>(&CompletedThunk), &s},
      {MHD_OPTION_NOTIFY_CONNECTION, reinterpret_cast<intptr_t>(&ConnectionThunk), &s},
      {MHD_OPTION_EXTERNAL_LOGGER, reinterpret_cast<intptr_t>(&LogFromLibrary), nullptr},
      {MHD_OPTION_END, 0, nullptr},
  };
  s.mhd = MHD_start_daemon(
      MHD_USE_EPOLL_INTERNAL_THREAD | MHD_ALLOW_SUSPEND_RESUME | MHD_USE_ERROR_LOG, 0, nullptr,
      nullptr, &AccessThunk, &s, MHD_OPTION_ARRAY, items, MHD_OPTION_END);
  if (s.mhd == nullptr) {
    close(s.listen_fd);
    s.listen_fd = -1;
    throw ListenError("cannot serve on " + s.options.listen + ":" + std::to_string(s.port) +
                      ": the HTTP server did not start");
  }
  s.sweeper = std::thread([&s] { s.Sweep(); });
  return s.port;
}

void HttpServer::Serve() {
  std::unique_lock lock(impl_->mutex);
  impl_->stopped_cv.wait(lock, [this] { return impl_->stopped; });
}

void HttpServer::Stop() {
  Impl& s = *impl_;
  {
    std::lock_guard lock(s.mutex);
    if (s.stopping) return;
    s.stopping = true;
  }
  s.stopped_cv.notify_all();
  if (s.sweeper.joinable()) s.sweeper.join();
  if (s.mhd != nullptr) MHD_quiesce_daemon(s.mhd);
  // Streams see `stopping` and end; handlers under way finish and resume their connections, so
  // none is left suspended when the library closes them.
  WakeStreams();
  if (s.quick) s.quick->Stop();
  if (s.slow) s.slow->Stop();
  if (s.mhd != nullptr) {
    MHD_stop_daemon(s.mhd);
    s.mhd = nullptr;
  }
  if (s.listen_fd >= 0) close(s.listen_fd);
  s.listen_fd = -1;
  {
    std::lock_guard lock(s.mutex);
    s.stopped = true;
  }
  s.stopped_cv.notify_all();
}

void HttpServer::WakeStreams() {
  std::lock_guard lock(impl_->mutex);
  impl_->WakeLocked();
}

HttpServer::Stats HttpServer::GetStats() const {
  std::lock_guard lock(impl_->mutex);
  return {static_cast<int>(impl_->connections.size()), static_cast<int>(impl_->streams.size()),
          impl_->timed_out};
}

}  // namespace gs360
