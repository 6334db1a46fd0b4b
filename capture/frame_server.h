#pragma once
// Frames over a Unix-domain socket, between processes on one machine.
//
// A FrameServer publishes frames produced by a callback (a camera owned by another process, or
// the virtual rig's camera, which must live beside the virtual CNC whose true position it
// renders); the "socket:/path/to.sock" frame source (OpenFrameSource) is its client.
//
// Protocol (version 1, native byte order, one request at a time per connection):
//   client -> server: one byte 'N' (next frame).
//   server -> client: FrameWireHeader, then `payload_bytes` bytes: the BGR pixels row by row
//                     when status == 0, a UTF-8 error message when status != 0.
// Timestamps are steady_clock (CLOCK_MONOTONIC) nanoseconds, shared by all processes of a boot.

#include <atomic>
#include <chrono>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

#include "capture/frame_source.h"

namespace gs360 {

struct FrameWireHeader {
  std::uint32_t magic = 0x52465347;  // "GSFR"
  std::uint32_t version = 1;
  std::int32_t status = 0;  // 0 ok, else error (payload = message)
  std::int32_t width = 0;
  std::int32_t height = 0;
  std::int32_t cv_type = 0;
  std::uint64_t sequence = 0;
  std::int64_t timestamp_ns = 0;  // steady_clock::time_point::time_since_epoch()
  std::int64_t exposure_us = 0;
  std::uint64_t payload_bytes = 0;
};

class FrameServer {
 public:
  // Produces the next frame; may block (e.g. until the next frame period). An exception from it
  // is sent to the client as an error reply and the server carries on.
  using Producer = std::function<Frame()>;

  // Binds and listens on `socket_path` (an existing socket file there is replaced; any other
  // existing file is an error) and serves on a background thread, one thread per client.
  // Throws std::runtime_error naming the path if the socket cannot be created.
  FrameServer(std::filesystem::path socket_path, Producer producer);
  // Stops serving, closes every connection and removes the socket file.
  ~FrameServer();
  FrameServer(const FrameServer&) = delete;
  FrameServer& operator=(const FrameServer&) = delete;

  const std::filesystem::path& path() const { return path_; }
  // Replies written completely (counted after the last byte is written, so a client may hold a
  // frame a moment before it is counted).
  std::uint64_t FramesServed() const { return served_.load(); }

 private:
  void AcceptLoop();
  void Serve(int fd);

  std::filesystem::path path_;
  Producer producer_;
  std::mutex producer_mutex_;  // one frame is produced at a time, whatever the client count
  int listen_fd_ = -1;
  int wake_pipe_[2] = {-1, -1};
  std::atomic<bool> stopping_{false};
  std::atomic<std::uint64_t> served_{0};
  std::thread accept_thread_;
  std::mutex clients_mutex_;
  std::vector<int> client_fds_;
  std::vector<std::thread> client_threads_;
};

// Client side, used by OpenFrameSource for "socket:<path>" (options: none). The connection is
// made at Start(); a server that vanishes gives FrameSourceError(kDisconnected).
std::unique_ptr<FrameSource> OpenSocketFrameSource(const FrameSourceUri& uri,
                                                   const CameraControls& controls);

}  // namespace gs360
