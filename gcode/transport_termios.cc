// Plain termios transport: pseudo-terminals (which libserialport cannot open) and any other tty.
// Raw mode, 8N1, no hardware or software flow control, non-blocking descriptor driven by poll.

#include <fcntl.h>
#include <sys/ioctl.h>
#include <termios.h>
#include <unistd.h>
#include <cerrno>

#include <spdlog/spdlog.h>

#include "gcode/transport.h"
#include "gcode/transport_fd.h"

namespace gs360 {
namespace {

speed_t BaudToSpeed(int baud) {
  switch (baud) {
    case 9600:
      return B9600;
    case 19200:
      return B19200;
    case 38400:
      return B38400;
    case 57600:
      return B57600;
    case 115200:
      return B115200;
    case 230400:
      return B230400;
    case 460800:
      return B460800;
    case 500000:
      return B500000;
    case 921600:
      return B921600;
    case 1000000:
      return B1000000;
    case 2000000:
      return B2000000;
    default:
      break;
  }
  throw std::invalid_argument("TransportOptions.baud = " + std::to_string(baud) +
                              " is not a baud rate termios supports");
}

class TermiosTransport final : public Transport {
 public:
  TermiosTransport(int fd, std::string path, TransportOptions options)
      : fd_(fd), path_(std::move(path)), what_("termios " + path_), options_(options) {}
  ~TermiosTransport() override {
    // Clear the exclusive flag set at open: the tty may outlive us (another holder of the pty),
    // and a later reopen of the same path must not fail with EBUSY.
    ::ioctl(fd_, TIOCNXCL);
    ::close(fd_);
  }
  TermiosTransport(const TermiosTransport&) = delete;
  TermiosTransport& operator=(const TermiosTransport&) = delete;

  void Write(std::string_view bytes) override {
    internal::FdWrite(fd_, bytes, options_.write_timeout, what_, /*is_socket=*/false);
  }
  std::size_t Read(char* buf, std::size_t n, std::chrono::milliseconds timeout) override {
    return internal::FdRead(fd_, buf, n, timeout, what_);
  }
  std::string Describe() const override { return what_; }

 private:
  int fd_;
  std::string path_;
  std::string what_;
  TransportOptions options_;
};

}  // namespace

std::unique_ptr<Transport> OpenTermiosTransport(const std::string& path,
                                                const TransportOptions& options) {
  options.Check();
  const speed_t speed = BaudToSpeed(options.baud);
  const int fd = ::open(path.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
  if (fd < 0) {
    const int err = errno;
    throw TransportError("cannot open tty '" + path + "': " + internal::ErrnoText(err));
  }
  auto fail = [&](const std::string& what) {
    const int err = errno;
    ::close(fd);
    throw TransportError("cannot configure tty '" + path + "': " + what + ": " +
                         internal::ErrnoText(err));
  };
  if (!::isatty(fd)) {
    ::close(fd);
    throw TransportError("'" + path + "' is not a tty");
  }
  termios tio{};
  if (::tcgetattr(fd, &tio) != 0) fail("tcgetattr");
  ::cfmakeraw(&tio);
  tio.c_cflag |= (CLOCAL | CREAD);
  tio.c_cflag &= ~(CSTOPB | PARENB | CRTSCTS | CSIZE);
  tio.c_cflag |= CS8;
  tio.c_iflag &= ~(IXON | IXOFF | IXANY);
  tio.c_cc[VMIN] = 0;
  tio.c_cc[VTIME] = 0;
  if (::cfsetispeed(&tio, speed) != 0 || ::cfsetospeed(&tio, speed) != 0) fail("cfsetspeed");
  if (::tcsetattr(fd, TCSANOW, &tio) != 0) fail("tcsetattr");
  // Exclusive use: a second opener (another sender) gets EBUSY. Best effort.
  if (::ioctl(fd, TIOCEXCL) != 0) spdlog::debug("TIOCEXCL on {} failed", path);
  spdlog::debug("opened termios transport {} at {} baud", path, options.baud);
  return std::make_unique<TermiosTransport>(fd, path, options);
}

}  // namespace gs360
