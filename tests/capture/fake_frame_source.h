#pragma once
// A scripted FrameSource for tests: delivers the frames it was given, in order, then reports
// timeouts; records every call.

#include <chrono>
#include <deque>
#include <optional>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "capture/frame_source.h"

namespace gs360::test {

class FakeFrameSource : public FrameSource {
 public:
  // A uniform frame of `value` (all channels) at `timestamp`.
  void Push(std::chrono::steady_clock::time_point timestamp, int value, cv::Size size = {8, 6},
            std::chrono::microseconds exposure = std::chrono::microseconds(0)) {
    Push(timestamp, cv::Mat(size, CV_8UC3, cv::Scalar::all(value)), exposure);
  }
  void Push(std::chrono::steady_clock::time_point timestamp, cv::Mat image,
            std::chrono::microseconds exposure = std::chrono::microseconds(0)) {
    Frame frame;
    frame.image = std::move(image);
    frame.timestamp = timestamp;
    frame.exposure = exposure;
    frame.sequence = next_sequence_++;
    script_.push_back(std::move(frame));
  }

  void Start() override {
    ++start_calls;
    started = true;
  }
  void Stop() override {
    ++stop_calls;
    started = false;
  }
  std::optional<Frame> Next(std::chrono::milliseconds timeout) override {
    next_timeouts.push_back(timeout);
    if (script_.empty()) return std::nullopt;
    Frame frame = std::move(script_.front());
    script_.pop_front();
    return frame;
  }
  std::string Describe() const override { return "fake source"; }
  bool IsLive() const override { return true; }

  std::size_t remaining() const { return script_.size(); }

  int start_calls = 0;
  int stop_calls = 0;
  bool started = false;
  std::vector<std::chrono::milliseconds> next_timeouts;

 private:
  std::deque<Frame> script_;
  std::uint64_t next_sequence_ = 0;
};

}  // namespace gs360::test
