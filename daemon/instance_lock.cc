#include "daemon/instance_lock.h"

#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <system_error>
#include <utility>

namespace gs360 {
namespace {

std::string ReadHolder(int fd) {
  char buf[512];
  const ssize_t n = pread(fd, buf, sizeof(buf) - 1, 0);
  if (n <= 0) return "";
  std::string s(buf, static_cast<std::size_t>(n));
  while (!s.empty() && (s.back() == '\n' || s.back() == '\0')) s.pop_back();
  return s;
}

}  // namespace

InstanceLock InstanceLock::Acquire(const std::filesystem::path& lock_file, const std::string& what,
                                   const std::string& holder) {
  std::error_code ec;
  if (lock_file.has_parent_path()) std::filesystem::create_directories(lock_file.parent_path(), ec);
  const int fd = ::open(lock_file.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
  if (fd < 0) {
    throw std::runtime_error("cannot create the lock file " + lock_file.string() + " for " + what +
                             ": " + std::strerror(errno));
  }
  if (::flock(fd, LOCK_EX | LOCK_NB) != 0) {
    const int err = errno;
    const std::string current = ReadHolder(fd);
    ::close(fd);
    if (err == EWOULDBLOCK) {
      throw LockHeldError(what + " is in use by " +
                              (current.empty() ? std::string("another process") : current) +
                              " (lock " + lock_file.string() + ")",
                          current);
    }
    throw std::runtime_error("cannot lock " + lock_file.string() + ": " + std::strerror(err));
  }
  InstanceLock lock;
  lock.fd_ = fd;
  lock.path_ = lock_file;
  lock.SetHolder(holder);
  return lock;
}

InstanceLock::InstanceLock(InstanceLock&& other) noexcept
    : fd_(std::exchange(other.fd_, -1)), path_(std::move(other.path_)) {}

InstanceLock& InstanceLock::operator=(InstanceLock&& other) noexcept {
  if (this != &other) {
    Release();
    fd_ = std::exchange(other.fd_, -1);
    path_ = std::move(other.path_);
  }
  return *this;
}

InstanceLock::~InstanceLock() {
  Release();
}

void InstanceLock::SetHolder(const std::string& holder) {
  if (fd_ < 0) return;
  const std::string line = holder + "\n";
  // Best effort: the description is for people, the flock is what counts.
  if (::ftruncate(fd_, 0) == 0) {
    [[maybe_unused]] const ssize_t n = ::pwrite(fd_, line.data(), line.size(), 0);
  }
}

void InstanceLock::Release() {
  if (fd_ < 0) return;
  // The file stays: removing it would race with a process that has just opened it.
  ::flock(fd_, LOCK_UN);
  ::close(fd_);
  fd_ = -1;
}

std::filesystem::path MachineLockPath(const std::string& uri, const std::filesystem::path& dir) {
  std::filesystem::path lock_dir = dir;
  if (lock_dir.empty()) {
    lock_dir = ::access("/run/lock", W_OK) == 0 ? std::filesystem::path("/run/lock")
                                                : std::filesystem::temp_directory_path();
  }
  std::string key = uri;
  if (!uri.empty() && uri[0] == '/') {
    std::error_code ec;
    const auto canonical = std::filesystem::canonical(uri, ec);
    if (!ec) key = canonical.string();
  }
  std::string name = "gs360d-port";
  for (char ch : key) {
    const bool plain = (ch >= 'a' && ch <= 'z') || (ch >= 'A' && ch <= 'Z') ||
                       (ch >= '0' && ch <= '9') || ch == '.' || ch == '-';
    name += plain ? ch : '_';
  }
  return lock_dir / (name + ".lock");
}

}  // namespace gs360
