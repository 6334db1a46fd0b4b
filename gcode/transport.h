#pragma once
// Byte transports to a GRBL controller: real serial ports (libserialport), pseudo-terminals and
// other ttys (plain termios), and TCP sockets (grblHAL / FluidNC telnet).
//
// A Transport is a bidirectional byte pipe. It does no framing: the GRBL client above it splits
// lines. Thread safety: one thread may call Read() while another calls Write(); concurrent Write()
// calls must be serialised by the caller (GrblClient does).
//
// Errors: opening throws TransportError (a std::runtime_error) naming the port / address. Once
// open, a peer that vanished (USB unplugged, pty master closed, socket closed) makes Read() and
// Write() throw TransportClosed (a TransportError); other I/O failures throw TransportError.
// No libserialport, termios or socket header is included here.

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

namespace gs360 {

class TransportError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// The peer is gone (device unplugged, pty master closed, connection closed by the remote end).
class TransportClosed : public TransportError {
 public:
  using TransportError::TransportError;
};

struct TransportOptions {
  // Serial line rate (bit/s) for serial ports and ttys; ignored by TCP. 8N1, no flow control.
  int baud = 115200;
  // TCP connect timeout.
  std::chrono::milliseconds connect_timeout{3000};
  // A Write() that cannot hand all bytes to the OS within this time throws TransportError.
  std::chrono::milliseconds write_timeout{2000};

  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

class Transport {
 public:
  virtual ~Transport();

  // Writes all bytes. Throws TransportClosed if the peer vanished, TransportError on other
  // failures (including write_timeout).
  virtual void Write(std::string_view bytes) = 0;

  // Reads up to n bytes, waiting at most `timeout` for the first one. Returns the number of
  // bytes read, 0 on timeout. Throws TransportClosed when the peer vanished.
  virtual std::size_t Read(char* buf, std::size_t n, std::chrono::milliseconds timeout) = 0;

  // Human description for logs and errors, e.g. "termios /dev/pts/3" or "tcp 127.0.0.1:23".
  virtual std::string Describe() const = 0;
};

// Opens a transport from a URI:
//   "tcp://host:port"          TCP (grblHAL, FluidNC telnet; IPv4 or IPv6 host, [v6] in brackets)
//   "serial:VID:PID[:SERIAL]"  the USB serial port with that USB id (hex, e.g. "serial:1a86:7523"),
//                              found again by id each time, so a replugged device that came
//                              back under another name is reopened
//   "serial:/dev/ttyUSB0"      libserialport, forced
//   "termios:/dev/ttyX"        plain termios, forced
//   "/dev/..." (any path)      a pseudo-terminal (/dev/pts/N, or a tty that is not a real serial
//                              device, symlinks resolved) -> termios; otherwise libserialport.
// Throws TransportError naming the URI when the port cannot be opened or does not exist, and
// when libserialport is needed but gs360 was compiled without it. Throws std::invalid_argument
// for a malformed URI or invalid options.
std::unique_ptr<Transport> OpenTransport(const std::string& uri, const TransportOptions& options);

// Backends, for callers that know which one they want.
std::unique_ptr<Transport> OpenTermiosTransport(const std::string& path,
                                                const TransportOptions& options);
std::unique_ptr<Transport> OpenSerialPortTransport(const std::string& port_name,
                                                   const TransportOptions& options);
std::unique_ptr<Transport> OpenTcpTransport(const std::string& host, int port,
                                            const TransportOptions& options);

// True when gs360 was built with libserialport (real serial ports, USB enumeration).
bool HaveLibSerialPort();

struct PortInfo {
  std::string name;         // e.g. "/dev/ttyUSB0"
  std::string description;  // libserialport's description, e.g. "USB2.0-Serial"
  bool is_usb = false;
  std::uint16_t usb_vid = 0;  // valid when is_usb
  std::uint16_t usb_pid = 0;
  std::string serial_number;  // USB serial number, may be empty
  std::string manufacturer;
  std::string product;
};

// Serial ports known to the OS (via libserialport). Empty when there are none. Throws
// TransportError if libserialport fails or gs360 was compiled without it.
std::vector<PortInfo> ListSerialPorts();

// The current name of the USB serial port with this VID:PID (and serial number, when not empty),
// or nullopt when no such device is plugged in. Throws like ListSerialPorts().
std::optional<std::string> FindPortByUsbId(std::uint16_t vid, std::uint16_t pid,
                                           std::string_view serial_number = {});

// "1a86:7523" -> (0x1a86, 0x7523); nullopt when malformed.
struct UsbId {
  std::uint16_t vid = 0;
  std::uint16_t pid = 0;
  std::string serial_number;
};
std::optional<UsbId> ParseUsbId(std::string_view text);

}  // namespace gs360
