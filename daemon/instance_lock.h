#pragma once
// Exclusive ownership between processes: one daemon per data folder, one per machine port.
//
// An InstanceLock is flock(LOCK_EX) on a lock file, held for the object's life and released by
// the kernel when the process ends in any way (SIGKILL and power cuts included: nothing stale to
// clean up). The file holds one line describing the holder ("gs360d pid 4242, data /var/lib/gs360,
// http://127.0.0.1:7360"), read back to tell a second process who is in the way.

#include <filesystem>
#include <stdexcept>
#include <string>

namespace gs360 {

// Another process holds the lock; holder() is its description (may be empty if it has not
// written one yet).
class LockHeldError : public std::runtime_error {
 public:
  LockHeldError(const std::string& message, std::string holder)
      : std::runtime_error(message), holder_(std::move(holder)) {}
  const std::string& holder() const { return holder_; }

 private:
  std::string holder_;
};

class InstanceLock {
 public:
  // Creates the lock file (and its folder) if needed and takes the lock without waiting. `what`
  // names the resource in the error ("the data folder /var/lib/gs360"). Throws LockHeldError,
  // std::runtime_error when the file cannot be created.
  static InstanceLock Acquire(const std::filesystem::path& lock_file, const std::string& what,
                              const std::string& holder);
  InstanceLock() = default;
  InstanceLock(InstanceLock&& other) noexcept;
  InstanceLock& operator=(InstanceLock&& other) noexcept;
  InstanceLock(const InstanceLock&) = delete;
  InstanceLock& operator=(const InstanceLock&) = delete;
  ~InstanceLock();

  bool Held() const { return fd_ >= 0; }
  const std::filesystem::path& path() const { return path_; }
  // Rewrites the holder's description (e.g. once the listening port is known).
  void SetHolder(const std::string& holder);
  void Release();

 private:
  int fd_ = -1;
  std::filesystem::path path_;
};

// Where the lock of a machine connection lives: one file per port in `lock_dir` (default
// /run/lock when writable, else the temp folder), named after the port's canonical path (a
// symlink and its target share one lock) or, for serial:VID:PID and tcp:// URIs, the URI.
std::filesystem::path MachineLockPath(const std::string& machine_uri,
                                      const std::filesystem::path& lock_dir = {});

}  // namespace gs360
