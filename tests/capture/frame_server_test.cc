#include <catch2/catch.hpp>

#include <unistd.h>

#include <atomic>
#include <chrono>
#include <filesystem>
#include <stdexcept>
#include <thread>

#include "capture/frame_server.h"
#include "capture/frame_source.h"
#include "tests/wait.h"

namespace {

std::filesystem::path SocketPath(const char* name) {
  return std::filesystem::temp_directory_path() /
         ("gs360_" + std::string(name) + "_" + std::to_string(::getpid()) + ".sock");
}

gs360::Frame MakeFrame(std::uint64_t seq) {
  gs360::Frame f;
  f.image = cv::Mat(48, 64, CV_8UC3);
  for (int y = 0; y < f.image.rows; ++y)
    for (int x = 0; x < f.image.cols; ++x)
      f.image.at<cv::Vec3b>(y, x) =
          cv::Vec3b(static_cast<uchar>(x + seq), static_cast<uchar>(y), static_cast<uchar>(seq));
  f.sequence = seq;
  f.timestamp = std::chrono::steady_clock::now();
  f.exposure = std::chrono::microseconds(1234);
  return f;
}

}  // namespace

TEST_CASE("socket frame source receives the server's frames intact", "[capture][socket]") {
  const auto path = SocketPath("intact");
  std::atomic<std::uint64_t> seq{0};
  std::vector<gs360::Frame> produced;
  std::mutex m;
  gs360::FrameServer server(path, [&] {
    auto f = MakeFrame(++seq);
    std::lock_guard lock(m);
    produced.push_back(gs360::Frame{f.image.clone(), f.timestamp, f.exposure, f.sequence});
    return f;
  });
  auto source = gs360::OpenFrameSource("socket:" + path.string(), {});
  CHECK(source->IsLive());
  source->Start();
  for (int i = 0; i < 5; ++i) {
    auto frame = source->Next(std::chrono::milliseconds(2000));
    REQUIRE(frame);
    std::lock_guard lock(m);
    const auto& want = produced.at(static_cast<std::size_t>(i));
    CHECK(frame->sequence == want.sequence);
    CHECK(frame->timestamp == want.timestamp);
    CHECK(frame->exposure == want.exposure);
    CHECK(cv::norm(frame->image, want.image, cv::NORM_INF) == 0);
  }
  // The server counts a reply once its last byte is written, which can be just after the client
  // has read it: wait for the count (bounded), then it must be exactly the five requested.
  gs360::test::WaitUntil([&] { return server.FramesServed() >= 5; }, std::chrono::seconds(2));
  CHECK(server.FramesServed() == 5);
}

TEST_CASE("socket frame source: a timeout keeps requests and replies in step",
          "[capture][socket]") {
  const auto path = SocketPath("timeout");
  std::atomic<std::uint64_t> seq{0};
  gs360::FrameServer server(path, [&] {
    std::this_thread::sleep_for(std::chrono::milliseconds(150));
    return MakeFrame(++seq);
  });
  auto source = gs360::OpenFrameSource("socket:" + path.string(), {});
  source->Start();
  CHECK_FALSE(source->Next(std::chrono::milliseconds(10)));  // reply still being produced
  auto first = source->Next(std::chrono::milliseconds(2000));
  REQUIRE(first);
  CHECK(first->sequence == 1);  // the owed reply, not a second request's
  auto second = source->Next(std::chrono::milliseconds(2000));
  REQUIRE(second);
  CHECK(second->sequence == 2);
}

TEST_CASE("socket frame source: producer errors and a vanished server are clear errors",
          "[capture][socket]") {
  const auto path = SocketPath("errors");
  auto server = std::make_unique<gs360::FrameServer>(
      path, []() -> gs360::Frame { throw std::runtime_error("camera on fire"); });
  auto source = gs360::OpenFrameSource("socket:" + path.string(), {});
  source->Start();
  try {
    source->Next(std::chrono::milliseconds(2000));
    FAIL("expected an error");
  } catch (const gs360::FrameSourceError& e) {
    CHECK(std::string(e.what()).find("camera on fire") != std::string::npos);
  }
  server.reset();
  CHECK_FALSE(std::filesystem::exists(path));
  CHECK_THROWS_AS(source->Next(std::chrono::milliseconds(500)), gs360::FrameSourceError);

  auto missing = gs360::OpenFrameSource("socket:" + path.string(), {});
  try {
    missing->Start();
    FAIL("expected an error");
  } catch (const gs360::FrameSourceError& e) {
    CHECK(e.code() == gs360::FrameSourceErrc::kNoDevice);
    CHECK(std::string(e.what()).find(path.string()) != std::string::npos);
  }
}
