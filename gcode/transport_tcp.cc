// TCP transport for network GRBL controllers (grblHAL, FluidNC telnet): "tcp://host:port".

#include <fcntl.h>
#include <netdb.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>
#include <cerrno>
#include <cstring>

#include <spdlog/spdlog.h>

#include "gcode/transport.h"
#include "gcode/transport_fd.h"

namespace gs360 {
namespace {

class TcpTransport final : public Transport {
 public:
  TcpTransport(int fd, std::string what, TransportOptions options)
      : fd_(fd), what_(std::move(what)), options_(options) {}
  ~TcpTransport() override { ::close(fd_); }
  TcpTransport(const TcpTransport&) = delete;
  TcpTransport& operator=(const TcpTransport&) = delete;

  void Write(std::string_view bytes) override {
    internal::FdWrite(fd_, bytes, options_.write_timeout, what_, /*is_socket=*/true);
  }
  std::size_t Read(char* buf, std::size_t n, std::chrono::milliseconds timeout) override {
    return internal::FdRead(fd_, buf, n, timeout, what_);
  }
  std::string Describe() const override { return what_; }

 private:
  int fd_;
  std::string what_;
  TransportOptions options_;
};

// Connects a non-blocking socket within the timeout; returns the fd or -1 with `error` set.
int ConnectWithTimeout(const addrinfo* ai, std::chrono::milliseconds timeout, std::string* error) {
  const int fd =
      ::socket(ai->ai_family, ai->ai_socktype | SOCK_NONBLOCK | SOCK_CLOEXEC, ai->ai_protocol);
  if (fd < 0) {
    *error = internal::ErrnoText(errno);
    return -1;
  }
  if (::connect(fd, ai->ai_addr, ai->ai_addrlen) != 0) {
    if (errno != EINPROGRESS) {
      *error = internal::ErrnoText(errno);
      ::close(fd);
      return -1;
    }
    pollfd p{};
    p.fd = fd;
    p.events = POLLOUT;
    int r;
    do {
      r = ::poll(&p, 1, static_cast<int>(timeout.count()));
    } while (r < 0 && errno == EINTR);
    if (r == 0) {
      *error = "connect timed out after " + std::to_string(timeout.count()) + " ms";
      ::close(fd);
      return -1;
    }
    int so_error = 0;
    socklen_t len = sizeof(so_error);
    if (r < 0 || ::getsockopt(fd, SOL_SOCKET, SO_ERROR, &so_error, &len) != 0 || so_error != 0) {
      *error = internal::ErrnoText(r < 0 ? errno : so_error);
      ::close(fd);
      return -1;
    }
  }
  const int one = 1;
  // Lines are small and latency matters (ok round trips): no Nagle delay.
  ::setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof(one));
  ::setsockopt(fd, SOL_SOCKET, SO_KEEPALIVE, &one, sizeof(one));
  return fd;
}

}  // namespace

std::unique_ptr<Transport> OpenTcpTransport(const std::string& host, int port,
                                            const TransportOptions& options) {
  options.Check();
  if (host.empty()) throw std::invalid_argument("OpenTcpTransport: empty host");
  if (port <= 0 || port > 65535) {
    throw std::invalid_argument("OpenTcpTransport: port = " + std::to_string(port) +
                                " is outside 1..65535");
  }
  const std::string what = "tcp " + host + ":" + std::to_string(port);
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  addrinfo* res = nullptr;
  const std::string port_text = std::to_string(port);
  const int gai = ::getaddrinfo(host.c_str(), port_text.c_str(), &hints, &res);
  if (gai != 0) {
    throw TransportError("cannot resolve " + what + ": " + ::gai_strerror(gai));
  }
  std::string last_error = "no address";
  int fd = -1;
  for (const addrinfo* ai = res; ai != nullptr && fd < 0; ai = ai->ai_next) {
    fd = ConnectWithTimeout(ai, options.connect_timeout, &last_error);
  }
  ::freeaddrinfo(res);
  if (fd < 0) throw TransportError("cannot connect to " + what + ": " + last_error);
  spdlog::debug("opened {}", what);
  return std::make_unique<TcpTransport>(fd, what, options);
}

}  // namespace gs360
