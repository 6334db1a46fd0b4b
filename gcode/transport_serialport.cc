// libserialport transport: real serial ports (USB CDC/FTDI/CH340 GRBL boards) and enumeration of
// ports with their USB VID:PID. libserialport opens and configures the port (8N1, no flow
// control, exclusive open); the I/O itself runs on the port's descriptor with poll(2), as
// libserialport's documentation recommends for custom blocking, so that an unplugged device is
// reported as TransportClosed instead of an endless timeout.
// Compiled without libserialport (GS360_HAVE_LIBSERIALPORT unset), every entry point throws a
// "compiled without libserialport" TransportError.

#include <fcntl.h>
#include <unistd.h>
#include <cerrno>

#include <spdlog/spdlog.h>

#include "gcode/transport.h"
#include "gcode/transport_fd.h"

#ifdef GS360_HAVE_LIBSERIALPORT
#include <libserialport.h>
#endif

namespace gs360 {

#ifdef GS360_HAVE_LIBSERIALPORT
namespace {

std::string LastSpError() {
  char* msg = sp_last_error_message();
  std::string text = msg != nullptr ? msg : "unknown libserialport error";
  if (msg != nullptr) sp_free_error_message(msg);
  // libserialport keeps trailing newlines from strerror on some platforms.
  while (!text.empty() && (text.back() == '\n' || text.back() == '\r')) text.pop_back();
  return text;
}

std::string SpResultText(sp_return r) {
  switch (r) {
    case SP_ERR_ARG:
      return "invalid argument";
    case SP_ERR_FAIL:
      return LastSpError();
    case SP_ERR_MEM:
      return "out of memory";
    case SP_ERR_SUPP:
      return "operation not supported";
    default:
      return "libserialport error " + std::to_string(static_cast<int>(r));
  }
}

class SerialPortTransport final : public Transport {
 public:
  SerialPortTransport(sp_port* port, int fd, std::string name, TransportOptions options)
      : port_(port), fd_(fd), what_("serial " + name), options_(options) {}
  ~SerialPortTransport() override {
    sp_close(port_);
    sp_free_port(port_);
  }
  SerialPortTransport(const SerialPortTransport&) = delete;
  SerialPortTransport& operator=(const SerialPortTransport&) = delete;

  void Write(std::string_view bytes) override {
    internal::FdWrite(fd_, bytes, options_.write_timeout, what_, /*is_socket=*/false);
  }
  std::size_t Read(char* buf, std::size_t n, std::chrono::milliseconds timeout) override {
    return internal::FdRead(fd_, buf, n, timeout, what_);
  }
  std::string Describe() const override { return what_; }

 private:
  sp_port* port_;
  int fd_;
  std::string what_;
  TransportOptions options_;
};

std::string Str(const char* s) {
  return s != nullptr ? std::string(s) : std::string();
}

}  // namespace

bool HaveLibSerialPort() {
  return true;
}

std::unique_ptr<Transport> OpenSerialPortTransport(const std::string& port_name,
                                                   const TransportOptions& options) {
  options.Check();
  sp_port* port = nullptr;
  sp_return r = sp_get_port_by_name(port_name.c_str(), &port);
  if (r != SP_OK) {
    throw TransportError("serial port '" + port_name + "' not found: " + SpResultText(r));
  }
  r = sp_open(port, SP_MODE_READ_WRITE);
  if (r != SP_OK) {
    const std::string why = SpResultText(r);
    sp_free_port(port);
    throw TransportError("cannot open serial port '" + port_name + "': " + why);
  }
  auto fail = [&](const std::string& step, sp_return code) {
    const std::string why = SpResultText(code);
    sp_close(port);
    sp_free_port(port);
    throw TransportError("cannot configure serial port '" + port_name + "' (" + step + "): " + why);
  };
  if ((r = sp_set_baudrate(port, options.baud)) != SP_OK) {
    fail("baud " + std::to_string(options.baud), r);
  }
  if ((r = sp_set_bits(port, 8)) != SP_OK) fail("8 data bits", r);
  if ((r = sp_set_parity(port, SP_PARITY_NONE)) != SP_OK) fail("no parity", r);
  if ((r = sp_set_stopbits(port, 1)) != SP_OK) fail("1 stop bit", r);
  if ((r = sp_set_flowcontrol(port, SP_FLOWCONTROL_NONE)) != SP_OK) fail("no flow control", r);
  int fd = -1;
  if ((r = sp_get_port_handle(port, &fd)) != SP_OK || fd < 0) fail("port handle", r);
  const int flags = ::fcntl(fd, F_GETFL);
  if (flags < 0 || ::fcntl(fd, F_SETFL, flags | O_NONBLOCK) != 0) {
    spdlog::warn("serial port {}: cannot set O_NONBLOCK: {}", port_name,
                 internal::ErrnoText(errno));
  }
  spdlog::debug("opened serial port {} at {} baud", port_name, options.baud);
  return std::make_unique<SerialPortTransport>(port, fd, port_name, options);
}

std::vector<PortInfo> ListSerialPorts() {
  sp_port** list = nullptr;
  const sp_return r = sp_list_ports(&list);
  if (r != SP_OK) throw TransportError("cannot list serial ports: " + SpResultText(r));
  std::vector<PortInfo> ports;
  for (sp_port** p = list; p != nullptr && *p != nullptr; ++p) {
    PortInfo info;
    info.name = Str(sp_get_port_name(*p));
    info.description = Str(sp_get_port_description(*p));
    if (sp_get_port_transport(*p) == SP_TRANSPORT_USB) {
      int vid = 0;
      int pid = 0;
      if (sp_get_port_usb_vid_pid(*p, &vid, &pid) == SP_OK) {
        info.is_usb = true;
        info.usb_vid = static_cast<std::uint16_t>(vid);
        info.usb_pid = static_cast<std::uint16_t>(pid);
      }
      info.serial_number = Str(sp_get_port_usb_serial(*p));
      info.manufacturer = Str(sp_get_port_usb_manufacturer(*p));
      info.product = Str(sp_get_port_usb_product(*p));
    }
    ports.push_back(std::move(info));
  }
  sp_free_port_list(list);
  return ports;
}

#else  // !GS360_HAVE_LIBSERIALPORT

namespace {
[[noreturn]] void NoLibSerialPort(const std::string& what) {
  throw TransportError(what +
                       ": gs360 was compiled without libserialport (install libserialport-dev "
                       "and reconfigure); ptys ('termios:' or /dev/pts/N) and tcp:// still work");
}
}  // namespace

bool HaveLibSerialPort() {
  return false;
}

std::unique_ptr<Transport> OpenSerialPortTransport(const std::string& port_name,
                                                   const TransportOptions& options) {
  options.Check();
  NoLibSerialPort("cannot open serial port '" + port_name + "'");
}

std::vector<PortInfo> ListSerialPorts() {
  NoLibSerialPort("cannot list serial ports");
}

#endif  // GS360_HAVE_LIBSERIALPORT

std::optional<std::string> FindPortByUsbId(std::uint16_t vid, std::uint16_t pid,
                                           std::string_view serial_number) {
  for (const PortInfo& p : ListSerialPorts()) {
    if (!p.is_usb || p.usb_vid != vid || p.usb_pid != pid) continue;
    if (!serial_number.empty() && p.serial_number != serial_number) continue;
    return p.name;
  }
  return std::nullopt;
}

}  // namespace gs360
