#include "gcode/transport_fd.h"

#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>
#include <cerrno>
#include <cstring>

#include "gcode/transport.h"

namespace gs360::internal {

bool ErrnoMeansClosed(int err) {
  switch (err) {
    case EIO:
    case ENXIO:
    case ENODEV:
    case EPIPE:
    case ECONNRESET:
    case ECONNABORTED:
    case ENOTCONN:
    case EBADF:
    case ESHUTDOWN:
    case ETIMEDOUT:
    case EHOSTUNREACH:
    case ENETDOWN:
    case ENETUNREACH:
      return true;
    default:
      return false;
  }
}

std::string ErrnoText(int err) {
  char buf[256];
  // GNU strerror_r returns a char* that may or may not point into buf.
  const char* text = strerror_r(err, buf, sizeof(buf));
  return std::string(text);
}

namespace {
int PollOne(int fd, short events, std::chrono::milliseconds timeout, short* revents) {
  pollfd p{};
  p.fd = fd;
  p.events = events;
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (true) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
        deadline - std::chrono::steady_clock::now());
    const int ms = left.count() < 0 ? 0 : static_cast<int>(left.count());
    const int r = ::poll(&p, 1, ms);
    if (r < 0 && errno == EINTR) continue;
    if (r > 0) *revents = p.revents;
    return r;
  }
}
}  // namespace

std::size_t FdRead(int fd, char* buf, std::size_t n, std::chrono::milliseconds timeout,
                   const std::string& what) {
  if (n == 0) return 0;
  short revents = 0;
  const int r = PollOne(fd, POLLIN, timeout, &revents);
  if (r < 0) {
    const int err = errno;
    throw TransportError("poll on " + what + " failed: " + ErrnoText(err));
  }
  if (r == 0) return 0;
  if (revents & POLLNVAL) throw TransportClosed(what + " is closed (invalid descriptor)");
  // POLLHUP may come with POLLIN while buffered bytes remain: read those first; the next read
  // returns 0 or EIO and reports the hang-up.
  while (true) {
    const ssize_t got = ::read(fd, buf, n);
    if (got > 0) return static_cast<std::size_t>(got);
    if (got == 0) throw TransportClosed(what + " closed by the peer (end of file)");
    const int err = errno;
    if (err == EINTR) continue;
    if (err == EAGAIN || err == EWOULDBLOCK) {
      if (revents & (POLLHUP | POLLERR)) throw TransportClosed(what + " hung up");
      return 0;
    }
    if (ErrnoMeansClosed(err)) throw TransportClosed(what + " vanished: " + ErrnoText(err));
    throw TransportError("read from " + what + " failed: " + ErrnoText(err));
  }
}

void FdWrite(int fd, std::string_view bytes, std::chrono::milliseconds timeout,
             const std::string& what, bool is_socket) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  std::size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t put = is_socket
                            ? ::send(fd, bytes.data() + done, bytes.size() - done, MSG_NOSIGNAL)
                            : ::write(fd, bytes.data() + done, bytes.size() - done);
    if (put > 0) {
      done += static_cast<std::size_t>(put);
      continue;
    }
    const int err = put < 0 ? errno : EAGAIN;
    if (err == EINTR) continue;
    if (err == EAGAIN || err == EWOULDBLOCK) {
      const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
          deadline - std::chrono::steady_clock::now());
      if (left.count() <= 0) {
        throw TransportError("write to " + what + " timed out after " +
                             std::to_string(timeout.count()) + " ms (" + std::to_string(done) +
                             " of " + std::to_string(bytes.size()) + " bytes written)");
      }
      short revents = 0;
      const int r = PollOne(fd, POLLOUT, left, &revents);
      if (r < 0) {
        const int perr = errno;
        throw TransportError("poll on " + what + " failed: " + ErrnoText(perr));
      }
      if (r > 0 && (revents & (POLLHUP | POLLERR | POLLNVAL)) && !(revents & POLLOUT)) {
        throw TransportClosed(what + " hung up during a write");
      }
      continue;
    }
    if (ErrnoMeansClosed(err)) throw TransportClosed(what + " vanished: " + ErrnoText(err));
    throw TransportError("write to " + what + " failed: " + ErrnoText(err));
  }
}

}  // namespace gs360::internal
