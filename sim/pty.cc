#include "sim/pty.h"

#include <fcntl.h>
#include <pty.h>
#include <sys/inotify.h>
#include <termios.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstring>
#include <stdexcept>
#include <utility>
#include <vector>

namespace gs360 {
namespace {

std::string ErrnoText(const std::string& what) {
  return what + ": " + std::strerror(errno);
}

}  // namespace

Pty::Pty(Pty&& other) noexcept
    : master_fd_(std::exchange(other.master_fd_, -1)),
      watch_fd_(std::exchange(other.watch_fd_, -1)),
      slave_path_(std::move(other.slave_path_)) {}

Pty& Pty::operator=(Pty&& other) noexcept {
  if (this != &other) {
    Close();
    master_fd_ = std::exchange(other.master_fd_, -1);
    watch_fd_ = std::exchange(other.watch_fd_, -1);
    slave_path_ = std::move(other.slave_path_);
  }
  return *this;
}

Pty::~Pty() {
  Close();
}

void Pty::Close() {
  if (master_fd_ >= 0) {
    ::close(master_fd_);
    master_fd_ = -1;
  }
  if (watch_fd_ >= 0) {
    ::close(watch_fd_);
    watch_fd_ = -1;
  }
}

int Pty::TakeOpens() {
  if (watch_fd_ < 0) return 0;
  int opens = 0;
  alignas(inotify_event) char buf[4096];
  ssize_t n;
  while ((n = ::read(watch_fd_, buf, sizeof(buf))) > 0) {
    for (ssize_t off = 0; off < n;) {
      const auto* e = reinterpret_cast<const inotify_event*>(buf + off);
      if (e->mask & IN_OPEN) ++opens;
      off += static_cast<ssize_t>(sizeof(inotify_event) + e->len);
    }
  }
  return opens;
}

Pty Pty::Open(const std::string& avoid_path, bool watch_opens) {
  // Keep rejected pairs open until a different path comes up, so the kernel cannot hand the
  // same number back.
  std::vector<int> rejected;
  Pty pty;
  for (int attempt = 0; attempt < 16; ++attempt) {
    int master = -1;
    int slave = -1;
    char name[256] = {};
    struct termios raw;
    std::memset(&raw, 0, sizeof(raw));
    cfmakeraw(&raw);
    raw.c_cflag |= CLOCAL | CREAD;
    cfsetispeed(&raw, B115200);
    cfsetospeed(&raw, B115200);
    if (::openpty(&master, &slave, name, &raw, nullptr) != 0) {
      const std::string msg = ErrnoText("openpty failed");
      for (int fd : rejected) ::close(fd);
      throw std::runtime_error(msg);
    }
    ::close(slave);
    if (!avoid_path.empty() && avoid_path == name) {
      rejected.push_back(master);
      continue;
    }
    const int flags = ::fcntl(master, F_GETFL);
    if (flags < 0 || ::fcntl(master, F_SETFL, flags | O_NONBLOCK) < 0 ||
        ::fcntl(master, F_SETFD, FD_CLOEXEC) < 0) {
      const std::string msg = ErrnoText("fcntl on pty master failed");
      ::close(master);
      for (int fd : rejected) ::close(fd);
      throw std::runtime_error(msg);
    }
    pty.master_fd_ = master;
    pty.slave_path_ = name;
    break;
  }
  for (int fd : rejected) ::close(fd);
  if (!pty.IsOpen()) throw std::runtime_error("openpty kept returning " + avoid_path);
  if (watch_opens) {
    // Best effort: without a watch (inotify's per-user limits), POLLHUP still tells most opens.
    pty.watch_fd_ = ::inotify_init1(IN_NONBLOCK | IN_CLOEXEC);
    if (pty.watch_fd_ >= 0 &&
        ::inotify_add_watch(pty.watch_fd_, pty.slave_path_.c_str(), IN_OPEN) < 0) {
      ::close(pty.watch_fd_);
      pty.watch_fd_ = -1;
    }
  }
  return pty;
}

void ReplaceSymlink(const std::string& target, const std::string& link_path) {
  const std::string tmp = link_path + ".tmp" + std::to_string(::getpid());
  ::unlink(tmp.c_str());
  if (::symlink(target.c_str(), tmp.c_str()) != 0) {
    throw std::runtime_error(ErrnoText("cannot create symlink " + tmp + " -> " + target));
  }
  if (::rename(tmp.c_str(), link_path.c_str()) != 0) {
    const std::string msg = ErrnoText("cannot rename symlink " + tmp + " to " + link_path);
    ::unlink(tmp.c_str());
    throw std::runtime_error(msg);
  }
}

}  // namespace gs360
