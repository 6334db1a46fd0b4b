#pragma once
// Internal to gcode/: poll(2)-based blocking I/O with timeouts on a POSIX file descriptor, shared
// by the termios, libserialport and TCP transports. Not part of the public API.

#include <chrono>
#include <cstddef>
#include <string>
#include <string_view>

namespace gs360::internal {

// Reads up to n bytes, waiting at most `timeout` for the first. Returns 0 on timeout. Throws
// TransportClosed on end of file / hang-up / EIO (the peer vanished), TransportError otherwise.
// `what` names the port in messages.
std::size_t FdRead(int fd, char* buf, std::size_t n, std::chrono::milliseconds timeout,
                   const std::string& what);

// Writes all bytes, waiting for the descriptor to become writable for at most `timeout` in total.
// `is_socket` selects send(MSG_NOSIGNAL) so a closed socket raises no SIGPIPE.
void FdWrite(int fd, std::string_view bytes, std::chrono::milliseconds timeout,
             const std::string& what, bool is_socket);

// True for errno values meaning the device or peer is gone (EIO, ENXIO, ENODEV, EPIPE, ...).
bool ErrnoMeansClosed(int err);

// strerror(err) as a std::string.
std::string ErrnoText(int err);

}  // namespace gs360::internal
