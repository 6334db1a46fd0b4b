#include <catch2/catch.hpp>

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <poll.h>
#include <pty.h>
#include <sys/socket.h>
#include <termios.h>
#include <unistd.h>
#include <cerrno>

#include <atomic>
#include <chrono>
#include <string>
#include <thread>

#include "gcode/transport.h"

using namespace std::chrono_literals;
using gs360::OpenTransport;
using gs360::Transport;
using gs360::TransportClosed;
using gs360::TransportError;
using gs360::TransportOptions;

namespace {

struct PtyPair {
  int master = -1;
  int slave = -1;
  std::string path;
  PtyPair() {
    char name[256] = {};
    termios raw{};
    ::cfmakeraw(&raw);
    REQUIRE(::openpty(&master, &slave, name, &raw, nullptr) == 0);
    path = name;
  }
  ~PtyPair() {
    if (master >= 0) ::close(master);
    if (slave >= 0) ::close(slave);
  }
};

std::string ReadSome(int fd, std::size_t want, std::chrono::milliseconds timeout) {
  std::string got;
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (got.size() < want && std::chrono::steady_clock::now() < deadline) {
    pollfd p{fd, POLLIN, 0};
    if (::poll(&p, 1, 20) <= 0) continue;
    char buf[256];
    const ssize_t n = ::read(fd, buf, sizeof(buf));
    if (n > 0) got.append(buf, static_cast<std::size_t>(n));
  }
  return got;
}

std::string ReadTransport(Transport& t, std::size_t want, std::chrono::milliseconds timeout) {
  std::string got;
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  char buf[256];
  while (got.size() < want && std::chrono::steady_clock::now() < deadline) {
    const std::size_t n = t.Read(buf, sizeof(buf), 20ms);
    got.append(buf, n);
  }
  return got;
}

struct Listener {
  int fd = -1;
  int port = 0;
  Listener() {
    fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
    REQUIRE(fd >= 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    addr.sin_port = 0;  // ephemeral
    REQUIRE(::bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) == 0);
    REQUIRE(::listen(fd, 4) == 0);
    socklen_t len = sizeof(addr);
    REQUIRE(::getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len) == 0);
    port = ntohs(addr.sin_port);
  }
  ~Listener() { ::close(fd); }
};

}  // namespace

TEST_CASE("a pty path opens with termios and moves bytes both ways", "[transport]") {
  PtyPair pty;
  auto t = OpenTransport(pty.path, TransportOptions{});
  CHECK(t->Describe() == "termios " + pty.path);
  t->Write("G0 X1\n");
  CHECK(ReadSome(pty.master, 6, 2s) == "G0 X1\n");
  // Raw mode: no CR/LF translation, no echo, binary bytes pass.
  const std::string reply = std::string("ok\r\n\x18\xff", 6);
  REQUIRE(::write(pty.master, reply.data(), reply.size()) == 6);
  CHECK(ReadTransport(*t, 6, 2s) == reply);
  CHECK(ReadSome(pty.master, 1, 100ms).empty());  // nothing echoed back
  // Timeout returns 0.
  char c;
  CHECK(t->Read(&c, 1, 30ms) == 0);
}

TEST_CASE("closing the pty master is reported as TransportClosed", "[transport]") {
  PtyPair pty;
  auto t = gs360::OpenTermiosTransport(pty.path, TransportOptions{});
  ::close(pty.master);
  pty.master = -1;
  char buf[16];
  bool closed = false;
  for (int i = 0; i < 50 && !closed; ++i) {
    try {
      t->Read(buf, sizeof(buf), 20ms);
    } catch (const TransportClosed&) {
      closed = true;
    }
  }
  CHECK(closed);
  CHECK_THROWS_AS(t->Write("G0 X1\n"), TransportClosed);
}

TEST_CASE("a pty reached through a symlink still opens with termios", "[transport]") {
  PtyPair pty;
  const std::string link = std::string(GS360_BINARY_DIR) + "/gs360_test_pty_link";
  ::unlink(link.c_str());
  REQUIRE(::symlink(pty.path.c_str(), link.c_str()) == 0);
  auto t = OpenTransport(link, TransportOptions{});
  CHECK(t->Describe().rfind("termios ", 0) == 0);
  t->Write("x");
  CHECK(ReadSome(pty.master, 1, 1s) == "x");
  ::unlink(link.c_str());
}

TEST_CASE("missing ports and malformed URIs are clear errors", "[transport]") {
  const std::string missing = "/dev/ttyUSB_gs360_does_not_exist";
  try {
    OpenTransport(missing, TransportOptions{});
    FAIL("expected TransportError");
  } catch (const TransportError& e) {
    CHECK(std::string(e.what()).find(missing) != std::string::npos);
  }
  if (gs360::HaveLibSerialPort()) {
    try {
      gs360::OpenSerialPortTransport(missing, TransportOptions{});
      FAIL("expected TransportError");
    } catch (const TransportError& e) {
      CHECK(std::string(e.what()).find(missing) != std::string::npos);
    }
  }
  CHECK_THROWS_AS(OpenTransport("", TransportOptions{}), std::invalid_argument);
  CHECK_THROWS_AS(OpenTransport("tcp://localhost", TransportOptions{}), std::invalid_argument);
  CHECK_THROWS_AS(OpenTransport("tcp://:23", TransportOptions{}), std::invalid_argument);
  CHECK_THROWS_AS(OpenTransport("tcp://host:99999", TransportOptions{}), std::invalid_argument);
  CHECK_THROWS_AS(OpenTransport("serial:zz:12", TransportOptions{}), std::invalid_argument);
  CHECK_THROWS_AS(OpenTransport("ftp://host:21", TransportOptions{}), std::invalid_argument);
  TransportOptions bad;
  bad.baud = 0;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("baud"));
  bad = TransportOptions{};
  bad.baud = 12345;  // not a termios rate
  PtyPair pty;
  CHECK_THROWS_AS(gs360::OpenTermiosTransport(pty.path, bad), std::invalid_argument);
}

TEST_CASE("USB ids parse and an unplugged USB id is a clear error", "[transport]") {
  const auto id = gs360::ParseUsbId("1a86:7523");
  REQUIRE(id);
  CHECK(id->vid == 0x1a86);
  CHECK(id->pid == 0x7523);
  CHECK(id->serial_number.empty());
  const auto with_serial = gs360::ParseUsbId("2341:0043:95735353");
  REQUIRE(with_serial);
  CHECK(with_serial->serial_number == "95735353");
  CHECK_FALSE(gs360::ParseUsbId("1a86"));
  CHECK_FALSE(gs360::ParseUsbId("1a86:"));
  CHECK_FALSE(gs360::ParseUsbId("12345:1"));
  CHECK_FALSE(gs360::ParseUsbId("1a86:7523:"));
  if (gs360::HaveLibSerialPort()) {
    // No device with this id exists on a test machine.
    CHECK_FALSE(gs360::FindPortByUsbId(0xfffe, 0xfffd));
    CHECK_THROWS_WITH(OpenTransport("serial:fffe:fffd", TransportOptions{}),
                      Catch::Contains("fffe:fffd"));
  } else {
    CHECK_THROWS_WITH(gs360::ListSerialPorts(), Catch::Contains("without libserialport"));
  }
}

TEST_CASE("ListSerialPorts enumerates without error", "[transport]") {
  if (!gs360::HaveLibSerialPort()) {
    CHECK_THROWS_AS(gs360::ListSerialPorts(), TransportError);
    return;
  }
  std::vector<gs360::PortInfo> ports;
  REQUIRE_NOTHROW(ports = gs360::ListSerialPorts());
  for (const auto& p : ports) {
    CHECK_FALSE(p.name.empty());
    if (!p.is_usb) CHECK(p.usb_vid == 0);
  }
}

TEST_CASE("tcp transport over loopback", "[transport]") {
  Listener listener;
  std::atomic<int> peer{-1};
  std::thread server([&] { peer = ::accept(listener.fd, nullptr, nullptr); });
  auto t = OpenTransport("tcp://127.0.0.1:" + std::to_string(listener.port), TransportOptions{});
  server.join();
  REQUIRE(peer >= 0);
  CHECK(t->Describe() == "tcp 127.0.0.1:" + std::to_string(listener.port));
  t->Write("$I\n");
  CHECK(ReadSome(peer, 3, 2s) == "$I\n");
  const std::string reply = "[VER:1.1h:]\r\nok\r\n";
  REQUIRE(::write(peer, reply.data(), reply.size()) == static_cast<ssize_t>(reply.size()));
  CHECK(ReadTransport(*t, reply.size(), 2s) == reply);
  char c;
  CHECK(t->Read(&c, 1, 20ms) == 0);
  ::close(peer);
  CHECK_THROWS_AS(ReadTransport(*t, 1, 2s), TransportClosed);
}

TEST_CASE("tcp connection refused names the address", "[transport]") {
  int port = 0;
  {
    Listener l;  // bound then closed: nothing listens on this port afterwards
    port = l.port;
  }
  const std::string uri = "tcp://127.0.0.1:" + std::to_string(port);
  CHECK_THROWS_WITH(OpenTransport(uri, TransportOptions{}),
                    Catch::Contains("127.0.0.1:" + std::to_string(port)));
}
