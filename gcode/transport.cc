#include "gcode/transport.h"

#include <fcntl.h>
#include <unistd.h>
#include <charconv>
#include <filesystem>

#include <spdlog/spdlog.h>

namespace gs360 {

Transport::~Transport() = default;

void TransportOptions::Check() const {
  if (baud <= 0) {
    throw std::invalid_argument("TransportOptions.baud must be > 0, got " + std::to_string(baud));
  }
  if (connect_timeout.count() <= 0) {
    throw std::invalid_argument("TransportOptions.connect_timeout must be > 0 ms, got " +
                                std::to_string(connect_timeout.count()));
  }
  if (write_timeout.count() <= 0) {
    throw std::invalid_argument("TransportOptions.write_timeout must be > 0 ms, got " +
                                std::to_string(write_timeout.count()));
  }
}

namespace {

bool StartsWith(std::string_view s, std::string_view prefix) {
  return s.substr(0, prefix.size()) == prefix;
}

std::optional<std::uint16_t> ParseHex16(std::string_view s) {
  if (s.empty() || s.size() > 4) return std::nullopt;
  unsigned value = 0;
  const auto [ptr, ec] = std::from_chars(s.data(), s.data() + s.size(), value, 16);
  if (ec != std::errc() || ptr != s.data() + s.size()) return std::nullopt;
  return static_cast<std::uint16_t>(value);
}

// A real serial device has a driver behind it: /sys/class/tty/NAME/device exists. Ptys and
// virtual consoles do not.
bool IsRealSerialDevice(const std::filesystem::path& resolved) {
  std::error_code ec;
  return std::filesystem::exists(
      std::filesystem::path("/sys/class/tty") / resolved.filename() / "device", ec);
}

bool IsTty(const std::string& path) {
  const int fd = ::open(path.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
  if (fd < 0) return false;
  const bool tty = ::isatty(fd) != 0;
  ::close(fd);
  return tty;
}

std::unique_ptr<Transport> OpenTcpUri(const std::string& uri, std::string_view rest,
                                      const TransportOptions& options) {
  std::string_view host;
  std::string_view port_text;
  if (StartsWith(rest, "[")) {  // [v6]:port
    const auto close = rest.find(']');
    if (close == std::string_view::npos || close + 1 >= rest.size() || rest[close + 1] != ':') {
      throw std::invalid_argument("malformed tcp URI '" + uri + "' (expected tcp://[v6]:port)");
    }
    host = rest.substr(1, close - 1);
    port_text = rest.substr(close + 2);
  } else {
    const auto colon = rest.rfind(':');
    if (colon == std::string_view::npos) {
      throw std::invalid_argument("malformed tcp URI '" + uri + "' (expected tcp://host:port)");
    }
    host = rest.substr(0, colon);
    port_text = rest.substr(colon + 1);
  }
  while (!port_text.empty() && port_text.back() == '/') port_text.remove_suffix(1);
  int port = 0;
  const auto [ptr, ec] =
      std::from_chars(port_text.data(), port_text.data() + port_text.size(), port);
  if (host.empty() || ec != std::errc() || ptr != port_text.data() + port_text.size() ||
      port <= 0 || port > 65535) {
    throw std::invalid_argument("malformed tcp URI '" + uri + "' (host or port 1..65535 missing)");
  }
  return OpenTcpTransport(std::string(host), port, options);
}

}  // namespace

std::optional<UsbId> ParseUsbId(std::string_view text) {
  const auto c1 = text.find(':');
  if (c1 == std::string_view::npos) return std::nullopt;
  const auto c2 = text.find(':', c1 + 1);
  const auto vid = ParseHex16(text.substr(0, c1));
  const auto pid =
      ParseHex16(text.substr(c1 + 1, c2 == std::string_view::npos ? text.npos : c2 - c1 - 1));
  if (!vid || !pid) return std::nullopt;
  UsbId id;
  id.vid = *vid;
  id.pid = *pid;
  if (c2 != std::string_view::npos) {
    id.serial_number = std::string(text.substr(c2 + 1));
    if (id.serial_number.empty()) return std::nullopt;
  }
  return id;
}

std::unique_ptr<Transport> OpenTransport(const std::string& uri, const TransportOptions& options) {
  options.Check();
  if (uri.empty()) throw std::invalid_argument("OpenTransport: empty URI");
  const std::string_view u(uri);
  if (StartsWith(u, "tcp://")) return OpenTcpUri(uri, u.substr(6), options);
  if (StartsWith(u, "termios:")) return OpenTermiosTransport(uri.substr(8), options);
  if (StartsWith(u, "serial:")) {
    const std::string rest = uri.substr(7);
    if (StartsWith(rest, "/")) return OpenSerialPortTransport(rest, options);
    const auto id = ParseUsbId(rest);
    if (!id) {
      throw std::invalid_argument("malformed serial URI '" + uri +
                                  "' (expected serial:VID:PID[:SERIAL] in hex, or serial:/path)");
    }
    const auto name = FindPortByUsbId(id->vid, id->pid, id->serial_number);
    if (!name) {
      throw TransportError("no serial port with USB id " + rest + " is plugged in (" + uri + ")");
    }
    spdlog::info("{} resolved to {}", uri, *name);
    return OpenSerialPortTransport(*name, options);
  }
  if (u.find("://") != std::string_view::npos) {
    throw std::invalid_argument("unsupported transport URI scheme in '" + uri +
                                "' (tcp://, serial:, termios: or a device path)");
  }
  // A device path.
  std::error_code ec;
  if (!std::filesystem::exists(uri, ec)) {
    throw TransportError("serial port '" + uri + "' does not exist");
  }
  const std::filesystem::path resolved = std::filesystem::canonical(uri, ec);
  const std::string resolved_text = ec ? uri : resolved.string();
  if (StartsWith(resolved_text, "/dev/pts/")) return OpenTermiosTransport(uri, options);
  if (!IsRealSerialDevice(resolved) && IsTty(uri)) return OpenTermiosTransport(uri, options);
  return OpenSerialPortTransport(uri, options);
}

}  // namespace gs360
