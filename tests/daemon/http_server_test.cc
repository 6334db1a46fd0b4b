// gs360d's HTTP server under misuse and attack (issue 32): one daemon per port, bodies cut at
// their limits however they are sent, and clients that hold connections open (idle, slow to send
// their headers, event streams) never stop the API. Real sockets, a real client, the real gs360d.

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cstdlib>
#include <fstream>
#include <string>
#include <vector>

#include <catch2/catch.hpp>

#include "api_helpers.h"
#include "daemon/daemon_config.h"
#include "tests/wait.h"

namespace gs360 {
namespace {

using Json = nlohmann::json;

int PortOf(const std::string& url) {
  return std::stoi(url.substr(url.rfind(':') + 1));
}

// A raw TCP connection to the daemon, closed with the object.
class Socket {
 public:
  explicit Socket(int port) : fd_(::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0)) {
    REQUIRE(fd_ >= 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(static_cast<std::uint16_t>(port));
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    REQUIRE(::connect(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr) == 0);
  }
  ~Socket() { ::close(fd_); }
  Socket(const Socket&) = delete;
  Socket& operator=(const Socket&) = delete;

  bool Send(const std::string& data) {
    return ::send(fd_, data.data(), data.size(), MSG_NOSIGNAL) == static_cast<ssize_t>(data.size());
  }
  // What arrives within `wait` (up to `until` is seen, or the peer closes).
  std::string Read(std::chrono::milliseconds wait, const std::string& until = "\r\n\r\n") {
    std::string got;
    const auto deadline = std::chrono::steady_clock::now() + wait;
    while (got.find(until) == std::string::npos) {
      const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
          deadline - std::chrono::steady_clock::now());
      pollfd p{fd_, POLLIN, 0};
      if (::poll(&p, 1, static_cast<int>(std::max<std::int64_t>(left.count(), 0))) <= 0) break;
      char buf[4096];
      const ssize_t n = ::recv(fd_, buf, sizeof buf, 0);
      if (n <= 0) {
        closed_ = true;
        break;
      }
      got.append(buf, static_cast<std::size_t>(n));
    }
    return got;
  }
  // Whether the server has closed the connection (what it sent before is read and dropped).
  bool Closed() {
    if (!closed_) Read(std::chrono::milliseconds(0), "\x01never\x01");
    return closed_;
  }

 private:
  int fd_;
  bool closed_ = false;
};

std::string StatusLine(const std::string& response) {
  return response.substr(0, response.find("\r\n"));
}

std::filesystem::path TempDir(const std::string& name) {
  auto dir = std::filesystem::temp_directory_path() /
             ("gs360-http-" + name + "-" + std::to_string(::getpid()));
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  return dir;
}

// A daemon with no rig: it serves its API and data but starts no runs (enough for the server).
DaemonConfig ServerOnly(const std::filesystem::path& dir, const std::string& server = "") {
  return DaemonConfigFromToml("data_dir = \"data\"\n[server]\nport = 0\n" + server, "test.toml",
                              dir);
}

long RssKib() {
  std::ifstream in("/proc/self/status");
  for (std::string line; std::getline(in, line);) {
    if (line.rfind("VmRSS:", 0) == 0) return std::stol(line.substr(6));
  }
  return 0;
}

// Enough descriptors for the test's hundreds of sockets, both ends of each in this process.
void RoomForSockets(rlim_t n) {
  rlimit r{};
  getrlimit(RLIMIT_NOFILE, &r);
  if (r.rlim_cur < n) {
    r.rlim_cur = std::min(n, r.rlim_max);
    setrlimit(RLIMIT_NOFILE, &r);
  }
}

std::string ChunkedPost(const std::string& path, const std::string& type) {
  return "POST " + path + " HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: " + type +
         "\r\nTransfer-Encoding: chunked\r\n\r\n";
}

// Sends `bytes` of chunked body in 64 KiB chunks and the last chunk; false if the server cut the
// connection first.
bool SendChunks(Socket& s, std::size_t bytes, char fill) {
  const std::string data(64 << 10, fill);
  char size_line[32];
  std::snprintf(size_line, sizeof size_line, "%zx\r\n", data.size());
  for (std::size_t sent = 0; sent < bytes; sent += data.size()) {
    if (!s.Send(size_line + data + "\r\n")) return false;
  }
  return s.Send("0\r\n\r\n");
}

}  // namespace

TEST_CASE("gs360d: a second daemon on a port that is taken exits 4, the first keeps it",
          "[daemon][http][security]") {
  const auto dir = TempDir("port");
  test::InProcessDaemon first(ServerOnly(dir / "a"));
  const int port = PortOf(first.url);
  std::filesystem::create_directories(dir / "b");
  std::ofstream(dir / "b" / "gs360d.toml")
      << "data_dir = \"data\"\n[server]\nport = " << port << "\n";
  // `timeout`: a daemon that shares the port serves on and would never return.
  const std::string command = "timeout 60 " + std::string(GS360_BINARY_DIR) +
                              "/daemon/gs360d --config " + (dir / "b" / "gs360d.toml").string() +
                              " > " + (dir / "b.log").string() + " 2>&1";
  const int status = std::system(command.c_str());
  std::ifstream in(dir / "b.log");
  const std::string log((std::istreambuf_iterator<char>(in)), {});
  INFO(log);
  REQUIRE(WIFEXITED(status));
  CHECK(WEXITSTATUS(status) == 4);
  CHECK_THAT(log, Catch::Contains(std::to_string(port)) && Catch::Contains("in use"));
  // Every connection still reaches the first daemon.
  httplib::Client c = first.Client();
  for (int i = 0; i < 20; ++i) {
    c.set_keep_alive(false);
    const auto r = c.Get("/api/v1/info");
    REQUIRE(r);
    CHECK(r->status == 200);
  }
}

TEST_CASE("api: chunked bodies are cut at their limits with 413, their bytes never kept",
          "[daemon][http][security]") {
  const auto dir = TempDir("chunked");
  DaemonConfig config = ServerOnly(dir);
  config.server.max_upload_bytes = 2 << 20;
  test::InProcessDaemon d(config);
  const int port = PortOf(d.url);
  {
    // A 2 MB JSON body (limit 1 MiB), chunked: 413, not 400 after reading it whole.
    Socket s(port);
    REQUIRE(s.Send(ChunkedPost("/api/v1/runs", "application/json")));
    SendChunks(s, 2 << 20, ' ');
    const std::string r = s.Read(std::chrono::seconds(30));
    CHECK(StatusLine(r).rfind("HTTP/1.1 413 ", 0) == 0);
    CHECK_THAT(r, Catch::Contains("\"too_large\""));
  }
  {
    // A 40 MB mesh upload (limit 2 MiB), chunked: 413, and the daemon's memory does not grow
    // with the body.
    const long before = RssKib();
    Socket s(port);
    REQUIRE(s.Send(ChunkedPost("/api/v1/meshes?format=stl", "application/octet-stream")));
    SendChunks(s, 40 << 20, 'x');
    CHECK(StatusLine(s.Read(std::chrono::seconds(60))).rfind("HTTP/1.1 413 ", 0) == 0);
    CHECK(RssKib() - before < 24 * 1024);
  }
  {
    // One that goes on past the limit by more than the server drops: cut off, memory bounded.
    const long before = RssKib();
    Socket s(port);
    REQUIRE(s.Send(ChunkedPost("/api/v1/meshes?format=stl", "application/octet-stream")));
    const std::size_t huge = (2u << 20) + HttpServer::kMaxDiscardBytes + (16u << 20);
    CHECK_FALSE(SendChunks(s, huge, 'y'));
    CHECK(RssKib() - before < 24 * 1024);
  }
  httplib::Client c = d.Client();
  CHECK(test::Body(c.Get("/api/v1/meshes"))["meshes"].empty());
  CHECK(c.Get("/api/v1/info")->status == 200);
}

TEST_CASE("api: idle sockets, slow senders and many event streams do not stop the API",
          "[daemon][http][security]") {
  RoomForSockets(4096);
  const auto dir = TempDir("crowd");
  test::InProcessDaemon d(
      ServerOnly(dir, "max_event_streams = 120\nrequest_timeout_s = 2\nidle_timeout_s = 30\n"));
  const int port = PortOf(d.url);
  httplib::Client c = d.Client();
  c.set_read_timeout(static_cast<time_t>(10 * test::TimeScale()), 0);
  // 120 event streams: more than the old server's 64 threads, each of which a stream held.
  std::vector<std::unique_ptr<Socket>> streams;
  for (int i = 0; i < 120; ++i) {
    streams.push_back(std::make_unique<Socket>(port));
    REQUIRE(streams.back()->Send("GET /api/v1/events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"));
    REQUIRE(StatusLine(streams.back()->Read(std::chrono::seconds(10))) == "HTTP/1.1 200 OK");
  }
  // One more is refused (503), and says why.
  {
    Socket extra(port);
    REQUIRE(extra.Send("GET /api/v1/events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"));
    const std::string r = extra.Read(std::chrono::seconds(10), "}");
    CHECK(StatusLine(r) == "HTTP/1.1 503 Service Unavailable");
    CHECK_THAT(r, Catch::Contains("max_event_streams"));
  }
  // 300 idle sockets and 100 that send their headers slowly.
  std::vector<std::unique_ptr<Socket>> idle;
  for (int i = 0; i < 300; ++i) idle.push_back(std::make_unique<Socket>(port));
  std::vector<std::unique_ptr<Socket>> slow;
  for (int i = 0; i < 100; ++i) {
    slow.push_back(std::make_unique<Socket>(port));
    REQUIRE(slow.back()->Send("GET /api/v1/info HTTP/1.1\r\nHost: 127.0.0.1\r\n"));
  }
  // The API answers through all of it, and the streams carry what is published.
  const auto r = c.Get("/api/v1/info");
  REQUIRE(r);
  CHECK(r->status == 200);
  d.daemon->events().Publish("log", {{"message", "to every stream"}});
  for (auto& s : streams)
    CHECK_THAT(s->Read(std::chrono::seconds(10), "\n\n"), Catch::Contains("to every stream"));
  // The slow senders keep sending, a header line at a time, and are cut off at the request's
  // time limit; idle sockets too (a request that never arrives is a slow one).
  const bool all_cut = test::WaitUntil(
      [&] {
        for (auto& s : slow) s->Send("X-Slow: 1\r\n");
        for (auto& s : slow) {
          if (!s->Closed()) return false;
        }
        for (auto& s : idle) {
          if (!s->Closed()) return false;
        }
        return true;
      },
      std::chrono::seconds(30));
  CHECK(all_cut);
  // Event streams are not requests being received: they stay open.
  for (auto& s : streams) CHECK_FALSE(s->Closed());
  CHECK(c.Get("/api/v1/info")->status == 200);
}

TEST_CASE("api: content types, bearer schemes and query numbers are read as the RFCs say",
          "[daemon][http][security]") {
  const auto dir = TempDir("strict");
  DaemonConfig config = ServerOnly(dir);
  const std::string token = "a-token-of-the-test-0123456789";
  config.server.token = token;
  test::InProcessDaemon d(config);
  httplib::Client c = d.Client();
  const httplib::Headers auth = {{"Authorization", "Bearer " + token}};
  // The scheme is case-insensitive (RFC 7235).
  CHECK(c.Get("/api/v1/info", {{"Authorization", "bearer " + token}})->status == 200);
  CHECK(c.Get("/api/v1/info", {{"Authorization", "BEARER " + token}})->status == 200);
  CHECK(c.Get("/api/v1/info", {{"Authorization", "Bearer" + token}})->status == 401);
  // The media type exactly, in any case, with parameters.
  CHECK(c.Post("/api/v1/runs", auth, "{}", "application/jsonx")->status == 415);
  CHECK(c.Post("/api/v1/runs", auth, "{}", "application/json-seq")->status == 415);
  CHECK(c.Post("/api/v1/runs", auth, "{\"name\": 5}", "Application/JSON; charset=utf-8")->status !=
        415);
  // A number in the query that is not one is a 400 naming it, not 0.
  auto r = c.Get("/api/v1/runs/1/log?after=abc", auth);
  CHECK(r->status == 400);
  CHECK(test::Body(r)["error"]["field"] == "after");
  r = c.Get("/api/v1/events?after=-2", auth);
  CHECK(r->status == 400);
  r = c.Get("/api/v1/events?run=x", auth);
  CHECK(r->status == 400);
  // A path that exists with another method: 405.
  CHECK(c.Put("/api/v1/info", auth, "{}", "application/json")->status == 405);
  CHECK(c.Get("/api/v1/nothing", auth)->status == 404);
}

}  // namespace gs360
