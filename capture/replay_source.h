#pragma once
// Replay: a folder of images played back as a frame source, for tests and for re-running a
// calibration on recorded data.
//
// URI: "replay:/path/to/folder[?fps=<rate>&loop=<0|1>]".
// - Images are the folder's regular files ending in .png, .jpg, .jpeg, .bmp, .tif, .tiff, .ppm,
//   .pgm (case-insensitive), in lexicographic file-name order (zero-pad numbered names); other
//   files are ignored. Store PNG: JPEG is lossy and corrupts the photometric data calibration
//   needs.
// - Every image is decoded to 8-bit BGR; all must have the size of the first one delivered.
// - Timestamps: without fps, frames are produced on demand and stamped with the steady_clock time
//   of delivery (strictly increasing), so a frame requested after a sync `ok` is never stale.
//   With fps, playback is paced like a camera: after Start(), frame i is due at start + i/fps,
//   Next() waits until it is due (nullopt if that is beyond the timeout) and stamps it with its due
//   time (exactly 1/fps apart). Nothing is dropped when the consumer is slow.
// - At the end of the folder Next() returns nullopt at once, or starts over with loop=1.
// - Stop() keeps the position; Start() continues from it (paced timing restarts at Start()).
// The camera controls are ignored: recorded images are what they are.

#include <cstddef>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "capture/frame_source.h"

namespace gs360 {

struct ReplayOptions {
  // Paced playback rate in frames per second (> 0 and <= 10000); unset: on demand.
  std::optional<double> fps;
  // Start over after the last image.
  bool loop = false;

  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

class ReplayFrameSource : public FrameSource {
 public:
  // Lists the folder (images are decoded lazily, one per Next()). Throws FrameSourceError naming
  // `uri` and the folder: kNoDevice if it does not exist, is not a folder or holds no image.
  // `uri` is used in messages; empty: "replay:<folder>".
  ReplayFrameSource(const std::filesystem::path& folder, const ReplayOptions& options,
                    std::string uri = "");

  void Start() override;
  void Stop() override;
  // Throws FrameSourceError(kBadImage) naming the file if it cannot be decoded or its size differs
  // from the first frame's.
  std::optional<Frame> Next(std::chrono::milliseconds timeout) override;
  std::string Describe() const override;
  bool IsLive() const override { return false; }

  // The images, in playback order.
  const std::vector<std::filesystem::path>& files() const { return files_; }
  // Index into files() of the image the next Next() delivers.
  std::size_t position() const { return position_; }

 private:
  std::filesystem::path folder_;
  ReplayOptions options_;
  std::string uri_;
  std::vector<std::filesystem::path> files_;
  std::size_t position_ = 0;
  bool started_ = false;
  std::uint64_t sequence_ = 0;
  std::chrono::steady_clock::time_point pace_start_{};
  std::uint64_t paced_count_ = 0;  // frames delivered since Start() (paced mode)
  std::optional<std::chrono::steady_clock::time_point> last_timestamp_;
  cv::Size size_;  // of the first frame delivered; empty before
};

// Factory for the "replay" scheme: parses the fps / loop options and the folder from the URI.
std::unique_ptr<FrameSource> OpenReplayFrameSource(const FrameSourceUri& uri,
                                                   const CameraControls& controls);

}  // namespace gs360
