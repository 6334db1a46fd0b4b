#include "capture/frame_server.h"

#include <fcntl.h>
#include <poll.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <stdexcept>
#include <string>

#include <spdlog/spdlog.h>

namespace gs360 {
namespace {

sockaddr_un MakeAddress(const std::filesystem::path& path) {
  sockaddr_un addr{};
  addr.sun_family = AF_UNIX;
  const std::string s = path.string();
  if (s.size() >= sizeof(addr.sun_path)) {
    throw std::runtime_error("frame socket path too long (" + std::to_string(s.size()) +
                             " bytes, at most " + std::to_string(sizeof(addr.sun_path) - 1) +
                             "): " + s);
  }
  std::memcpy(addr.sun_path, s.c_str(), s.size() + 1);
  return addr;
}

// Writes everything or returns false (peer gone). MSG_NOSIGNAL: a vanished client must not kill
// the serving process with SIGPIPE.
bool WriteAll(int fd, const void* data, std::size_t size) {
  const auto* p = static_cast<const char*>(data);
  while (size > 0) {
    const ssize_t n = ::send(fd, p, size, MSG_NOSIGNAL);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return false;
    p += n;
    size -= static_cast<std::size_t>(n);
  }
  return true;
}

// Reads exactly `size` bytes before `deadline`. Returns 1 done, 0 timeout, -1 peer closed/error.
int ReadAll(int fd, void* data, std::size_t size, std::chrono::steady_clock::time_point deadline) {
  auto* p = static_cast<char*>(data);
  while (size > 0) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
        deadline - std::chrono::steady_clock::now());
    pollfd pfd{fd, POLLIN, 0};
    const int r = ::poll(&pfd, 1, static_cast<int>(std::max<long long>(0, left.count())));
    if (r < 0 && errno == EINTR) continue;
    if (r < 0) return -1;
    if (r == 0) return 0;
    const ssize_t n = ::recv(fd, p, size, 0);
    if (n < 0 && (errno == EINTR || errno == EAGAIN)) continue;
    if (n <= 0) return -1;
    p += n;
    size -= static_cast<std::size_t>(n);
  }
  return 1;
}

}  // namespace

FrameServer::FrameServer(std::filesystem::path socket_path, Producer producer)
    : path_(std::move(socket_path)), producer_(std::move(producer)) {
  if (!producer_) throw std::invalid_argument("FrameServer: empty producer");
  const sockaddr_un addr = MakeAddress(path_);
  struct stat st {};
  if (::lstat(path_.c_str(), &st) == 0) {
    if (!S_ISSOCK(st.st_mode)) {
      throw std::runtime_error("frame socket path exists and is not a socket: " + path_.string());
    }
    ::unlink(path_.c_str());
  }
  listen_fd_ = ::socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (listen_fd_ < 0) throw std::runtime_error("socket(): " + std::string(std::strerror(errno)));
  if (::bind(listen_fd_, reinterpret_cast<const sockaddr*>(&addr), sizeof(addr)) != 0 ||
      ::listen(listen_fd_, 8) != 0) {
    const std::string err = std::strerror(errno);
    ::close(listen_fd_);
    throw std::runtime_error("cannot listen on frame socket " + path_.string() + ": " + err);
  }
  if (::pipe2(wake_pipe_, O_CLOEXEC) != 0) {
    ::close(listen_fd_);
    throw std::runtime_error("pipe2(): " + std::string(std::strerror(errno)));
  }
  accept_thread_ = std::thread([this] { AcceptLoop(); });
}

FrameServer::~FrameServer() {
  stopping_ = true;
  const char b = 'x';
  [[maybe_unused]] const ssize_t w = ::write(wake_pipe_[1], &b, 1);
  accept_thread_.join();
  {
    std::lock_guard lock(clients_mutex_);
    for (int fd : client_fds_) ::shutdown(fd, SHUT_RDWR);
  }
  for (auto& t : client_threads_) t.join();
  ::close(listen_fd_);
  ::close(wake_pipe_[0]);
  ::close(wake_pipe_[1]);
  ::unlink(path_.c_str());
}

void FrameServer::AcceptLoop() {
  while (!stopping_) {
    pollfd pfds[2] = {{listen_fd_, POLLIN, 0}, {wake_pipe_[0], POLLIN, 0}};
    const int r = ::poll(pfds, 2, -1);
    if (r < 0) {
      if (errno == EINTR) continue;
      spdlog::error("frame server {}: poll: {}", path_.string(), std::strerror(errno));
      return;
    }
    if (pfds[1].revents) return;
    if (!(pfds[0].revents & POLLIN)) continue;
    const int fd = ::accept4(listen_fd_, nullptr, nullptr, SOCK_CLOEXEC);
    if (fd < 0) continue;
    std::lock_guard lock(clients_mutex_);
    client_fds_.push_back(fd);
    client_threads_.emplace_back([this, fd] { Serve(fd); });
  }
}

void FrameServer::Serve(int fd) {
  for (;;) {
    char request = 0;
    const ssize_t n = ::recv(fd, &request, 1, 0);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0 || stopping_) break;
    if (request != 'N') {
      spdlog::warn("frame server {}: unknown request byte 0x{:02x}, closing the connection",
                   path_.string(), static_cast<unsigned char>(request));
      break;
    }
    FrameWireHeader header;
    std::string error;
    Frame frame;
    try {
      std::lock_guard lock(producer_mutex_);
      frame = producer_();
      if (frame.image.empty() || !frame.image.isContinuous()) frame.image = frame.image.clone();
      if (frame.image.empty()) throw std::runtime_error("producer returned an empty frame");
    } catch (const std::exception& e) {
      error = e.what();
    }
    bool ok;
    if (!error.empty()) {
      header.status = 1;
      header.payload_bytes = error.size();
      ok = WriteAll(fd, &header, sizeof(header)) && WriteAll(fd, error.data(), error.size());
    } else {
      header.width = frame.image.cols;
      header.height = frame.image.rows;
      header.cv_type = frame.image.type();
      header.sequence = frame.sequence;
      header.timestamp_ns =
          std::chrono::duration_cast<std::chrono::nanoseconds>(frame.timestamp.time_since_epoch())
              .count();
      header.exposure_us = frame.exposure.count();
      header.payload_bytes = frame.image.total() * frame.image.elemSize();
      ok = WriteAll(fd, &header, sizeof(header)) &&
           WriteAll(fd, frame.image.data, header.payload_bytes);
      if (ok) ++served_;
    }
    if (!ok) break;
  }
  std::lock_guard lock(clients_mutex_);
  std::erase(client_fds_, fd);
  ::close(fd);
}

namespace {

class SocketFrameSource final : public FrameSource {
 public:
  SocketFrameSource(std::string uri, std::filesystem::path path)
      : uri_(std::move(uri)), path_(std::move(path)) {}
  ~SocketFrameSource() override { Stop(); }

  void Start() override {
    if (fd_ >= 0) return;
    const sockaddr_un addr = MakeAddress(path_);
    fd_ = ::socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
    if (fd_ < 0) throw FrameSourceError(FrameSourceErrc::kIo, uri_, std::strerror(errno));
    if (::connect(fd_, reinterpret_cast<const sockaddr*>(&addr), sizeof(addr)) != 0) {
      const std::string err = std::strerror(errno);
      ::close(fd_);
      fd_ = -1;
      throw FrameSourceError(FrameSourceErrc::kNoDevice, uri_,
                             "cannot connect to frame server " + path_.string() + ": " + err);
    }
    request_pending_ = false;
  }

  void Stop() override {
    if (fd_ >= 0) ::close(fd_);
    fd_ = -1;
    request_pending_ = false;
  }

  std::optional<Frame> Next(std::chrono::milliseconds timeout) override {
    if (fd_ < 0) throw std::logic_error("frame source " + uri_ + ": Next() before Start()");
    const auto deadline = std::chrono::steady_clock::now() + timeout;
    // A reply still owed from a request that timed out is the next frame: never ask twice, or
    // replies would pile up out of step with requests.
    if (!request_pending_) {
      const char req = 'N';
      if (!WriteAll(fd_, &req, 1)) Disconnected("the frame server closed the connection");
      request_pending_ = true;
    }
    // Wait for the reply's first byte within the caller's timeout; a timeout consumes nothing,
    // so the stream stays in step. Once it starts, header and payload follow at once.
    pollfd pfd{fd_, POLLIN, 0};
    int r;
    do {
      const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
          deadline - std::chrono::steady_clock::now());
      r = ::poll(&pfd, 1, static_cast<int>(std::max<long long>(0, left.count())));
    } while (r < 0 && errno == EINTR);
    if (r == 0) return std::nullopt;
    const auto read_deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
    FrameWireHeader header;
    if (r < 0 || ReadAll(fd_, &header, sizeof(header), read_deadline) != 1) {
      Disconnected("the frame server closed the connection");
    }
    request_pending_ = false;
    if (header.magic != FrameWireHeader{}.magic || header.version != 1) {
      Disconnected("bad frame header (wrong magic or version)");
    }
    std::string payload(header.payload_bytes, '\0');
    if (ReadAll(fd_, payload.data(), payload.size(), read_deadline) != 1) {
      Disconnected("truncated frame payload");
    }
    if (header.status != 0) {
      throw FrameSourceError(FrameSourceErrc::kIo, uri_, "frame server error: " + payload);
    }
    cv::Mat image(header.height, header.width, header.cv_type);
    if (image.total() * image.elemSize() != payload.size()) {
      Disconnected("payload size does not match the frame size");
    }
    std::memcpy(image.data, payload.data(), payload.size());
    Frame frame;
    frame.image = image;
    frame.sequence = header.sequence;
    frame.timestamp = std::chrono::steady_clock::time_point(
        std::chrono::duration_cast<std::chrono::steady_clock::duration>(
            std::chrono::nanoseconds(header.timestamp_ns)));
    frame.exposure = std::chrono::microseconds(header.exposure_us);
    return frame;
  }

  std::string Describe() const override { return "socket frame source " + path_.string(); }
  bool IsLive() const override { return true; }

 private:
  [[noreturn]] void Disconnected(const std::string& why) {
    Stop();
    throw FrameSourceError(FrameSourceErrc::kDisconnected, uri_, why);
  }

  std::string uri_;
  std::filesystem::path path_;
  int fd_ = -1;
  bool request_pending_ = false;
};

}  // namespace

std::unique_ptr<FrameSource> OpenSocketFrameSource(const FrameSourceUri& uri,
                                                   const CameraControls&) {
  uri.RequireKnownOptions({});
  if (uri.target.empty()) {
    throw FrameSourceError(FrameSourceErrc::kBadUri, uri.uri, "expected socket:<path>");
  }
  return std::make_unique<SocketFrameSource>(uri.uri, uri.target);
}

}  // namespace gs360
