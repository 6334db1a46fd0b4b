#pragma once
// A pseudo-terminal pair for the virtual CNC: the master side stays in this process, the slave
// path (/dev/pts/N) is what a host opens exactly as it would open /dev/ttyUSB0. The line
// discipline is put in raw mode at creation (no echo, no CR/LF translation), so bytes pass
// unchanged in both directions whatever the host does before configuring its end.

#include <string>

namespace gs360 {

class Pty {
 public:
  Pty() = default;
  Pty(const Pty&) = delete;
  Pty& operator=(const Pty&) = delete;
  Pty(Pty&& other) noexcept;
  Pty& operator=(Pty&& other) noexcept;
  ~Pty();

  // Opens a raw pty pair with a non-blocking master. The slave is not kept open here (so a
  // host closing it is visible as POLLHUP on the master). With `avoid_path`, the new slave path
  // differs from it (a device coming back under a new name). Throws std::runtime_error with the
  // errno text on failure. With `watch_opens`, every open of the slave by a host is counted
  // (inotify), so a close and a reopen between two looks at POLLHUP is not missed; if the
  // kernel refuses a watch, open_watch_fd() is -1 and only POLLHUP tells.
  static Pty Open(const std::string& avoid_path = "", bool watch_opens = false);

  bool IsOpen() const { return master_fd_ >= 0; }
  int master_fd() const { return master_fd_; }
  const std::string& slave_path() const { return slave_path_; }
  // Readable when a host has opened the slave since the last TakeOpens(); -1 without a watch.
  int open_watch_fd() const { return watch_fd_; }
  // The number of opens of the slave since the last call (0 without a watch). Never blocks.
  int TakeOpens();
  // Closes the master: a host holding the slave sees EOF / EIO, as after a USB unplug.
  void Close();

 private:
  int master_fd_ = -1;
  int watch_fd_ = -1;
  std::string slave_path_;
};

// Points `link_path` at `target` atomically (a temporary link renamed over it). Throws
// std::runtime_error naming the path on failure.
void ReplaceSymlink(const std::string& target, const std::string& link_path);

}  // namespace gs360
