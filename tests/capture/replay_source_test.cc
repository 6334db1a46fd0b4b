#include <catch2/catch.hpp>

#include <unistd.h>

#include <atomic>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <stdexcept>
#include <string>

#include <opencv2/imgcodecs.hpp>

#include "capture/capture_press.h"
#include "capture/frame_source.h"
#include "capture/replay_source.h"

namespace fs = std::filesystem;
using gs360::FrameSourceErrc;
using gs360::FrameSourceError;
using std::chrono::milliseconds;

namespace {

// A fresh folder under the system temp dir, removed with its contents at scope exit.
class TempDir {
 public:
  TempDir() {
    static std::atomic<int> counter{0};
    path_ = fs::temp_directory_path() /
            ("gs360_capture_test_" + std::to_string(::getpid()) + "_" + std::to_string(counter++));
    fs::remove_all(path_);
    fs::create_directories(path_);
  }
  ~TempDir() {
    std::error_code ec;
    fs::remove_all(path_, ec);
  }
  const fs::path& path() const { return path_; }

 private:
  fs::path path_;
};

// An image whose pixel (0,0) encodes `id` (B = id, G = 2*id, R = 255 - id), so the test can tell
// frames apart after decoding.
cv::Mat Tagged(int id, cv::Size size = {32, 24}) {
  cv::Mat m(size, CV_8UC3, cv::Scalar(id, 2 * id, 255 - id));
  m.at<cv::Vec3b>(size.height - 1, size.width - 1) = cv::Vec3b(7, 8, 9);
  return m;
}

void WritePng(const fs::path& file, const cv::Mat& image) {
  REQUIRE(cv::imwrite(file.string(), image));
}

// "f<i>.png" (built with a stream: GCC 12 warns falsely on "f" + std::to_string(i)).
std::string FrameName(int i) {
  std::ostringstream name;
  name << "f" << i << ".png";
  return name.str();
}

int Tag(const gs360::Frame& frame) {
  return frame.image.at<cv::Vec3b>(0, 0)[0];
}

}  // namespace

TEST_CASE("replay delivers the folder's images in name order, decoded losslessly", "[replay]") {
  TempDir dir;
  // Written out of order; non-images and sub-folders are ignored.
  WritePng(dir.path() / "frame_0002.png", Tagged(2));
  WritePng(dir.path() / "frame_0000.png", Tagged(0));
  WritePng(dir.path() / "frame_0001.PNG", Tagged(1));
  std::ofstream(dir.path() / "notes.txt") << "not an image";
  fs::create_directory(dir.path() / "sub.png");

  auto source = gs360::OpenFrameSource("replay:" + dir.path().string(), {});
  CHECK_FALSE(source->IsLive());
  CHECK_THROWS_AS(source->Next(milliseconds(10)), std::logic_error);  // not started
  source->Start();
  for (int i = 0; i < 3; ++i) {
    auto frame = source->Next(milliseconds(100));
    REQUIRE(frame);
    CHECK(Tag(*frame) == i);
    CHECK(frame->sequence == static_cast<std::uint64_t>(i));
    CHECK(frame->image.type() == CV_8UC3);
    CHECK(frame->image.size() == cv::Size(32, 24));
    CHECK(cv::norm(frame->image, Tagged(i), cv::NORM_INF) == 0);
  }
  CHECK_FALSE(source->Next(milliseconds(10)));  // end of the folder, no loop
  CHECK(source->Describe().find("3 images") != std::string::npos);
}

TEST_CASE("replay keeps the recorded size and converts grey images to BGR", "[replay]") {
  TempDir dir;
  cv::Mat grey(50, 70, CV_8UC1, cv::Scalar(123));
  WritePng(dir.path() / "a.png", grey);
  gs360::CameraControls controls;  // 640x480, ignored by replay
  auto source = gs360::OpenFrameSource("replay:" + dir.path().string(), controls);
  source->Start();
  auto frame = source->Next(milliseconds(100));
  REQUIRE(frame);
  CHECK(frame->image.size() == cv::Size(70, 50));
  CHECK(frame->image.type() == CV_8UC3);
  CHECK(frame->image.at<cv::Vec3b>(10, 10) == cv::Vec3b(123, 123, 123));
}

TEST_CASE("replay on demand stamps frames at delivery, so they pass the sync check", "[replay]") {
  TempDir dir;
  for (int i = 0; i < 4; ++i) {
    WritePng(dir.path() / FrameName(i), Tagged(10 * (i + 1)));
  }
  gs360::ReplayFrameSource source(dir.path(), {});
  source.Start();
  const auto sync_ok = std::chrono::steady_clock::now();
  gs360::PressCaptureOptions options;
  options.frames_to_average = 3;
  const auto result = gs360::CapturePress(source, sync_ok, options);
  REQUIRE(result.ok());
  CHECK(result.stale_dropped == 0);
  CHECK(result.first_timestamp > sync_ok);
  CHECK(result.last_timestamp > result.first_timestamp);
  // B channel: (10 + 20 + 30) / 3 = 20.
  CHECK(result.image.at<cv::Vec3b>(0, 0)[0] == 20);
  CHECK(source.position() == 3);
}

TEST_CASE("replay paced by fps stamps frames exactly 1/fps apart and honours timeouts",
          "[replay]") {
  TempDir dir;
  for (int i = 0; i < 3; ++i) WritePng(dir.path() / FrameName(i), Tagged(i));
  {
    auto source = gs360::OpenFrameSource("replay:" + dir.path().string() + "?fps=200&loop=1", {});
    source->Start();
    std::vector<std::chrono::steady_clock::time_point> stamps;
    std::vector<int> tags;
    for (int i = 0; i < 5; ++i) {  // loops after the third image
      auto frame = source->Next(milliseconds(1000));
      REQUIRE(frame);
      stamps.push_back(frame->timestamp);
      tags.push_back(Tag(*frame));
    }
    CHECK(tags == std::vector<int>{0, 1, 2, 0, 1});
    for (std::size_t i = 1; i < stamps.size(); ++i) {
      CHECK(stamps[i] - stamps[0] == std::chrono::milliseconds(5) * static_cast<int>(i));
    }
  }
  {
    // 0.1 fps: the first frame is due at Start(), the second only 10 s later.
    auto source = gs360::OpenFrameSource("replay:" + dir.path().string() + "?fps=0.1", {});
    source->Start();
    REQUIRE(source->Next(milliseconds(100)));
    CHECK_FALSE(source->Next(milliseconds(20)));
  }
}

TEST_CASE("replay continues after Stop and Start with increasing timestamps", "[replay]") {
  TempDir dir;
  for (int i = 0; i < 3; ++i) WritePng(dir.path() / FrameName(i), Tagged(i));
  gs360::ReplayFrameSource source(dir.path(), {});
  source.Start();
  auto a = source.Next(milliseconds(10));
  source.Stop();
  CHECK_THROWS_AS(source.Next(milliseconds(10)), std::logic_error);
  source.Start();
  auto b = source.Next(milliseconds(10));
  REQUIRE(a);
  REQUIRE(b);
  CHECK(Tag(*b) == 1);
  CHECK(b->timestamp > a->timestamp);
  CHECK(b->sequence == a->sequence + 1);
}

TEST_CASE("replay reports a corrupt image by file name", "[replay]") {
  TempDir dir;
  WritePng(dir.path() / "f0.png", Tagged(0));
  std::ofstream(dir.path() / "f1.png", std::ios::binary) << "\x89PNG\r\n\x1a\n this is not a PNG";
  auto source = gs360::OpenFrameSource("replay:" + dir.path().string(), {});
  source->Start();
  REQUIRE(source->Next(milliseconds(10)));
  try {
    source->Next(milliseconds(10));
    FAIL("a corrupt PNG must throw");
  } catch (const FrameSourceError& e) {
    CHECK(e.code() == FrameSourceErrc::kBadImage);
    CHECK_THAT(e.what(), Catch::Contains((dir.path() / "f1.png").string()));
  }
}

TEST_CASE("replay rejects an image whose size differs from the first", "[replay]") {
  TempDir dir;
  WritePng(dir.path() / "f0.png", Tagged(0, {32, 24}));
  WritePng(dir.path() / "f1.png", Tagged(1, {24, 32}));
  gs360::ReplayFrameSource source(dir.path(), {});
  source.Start();
  REQUIRE(source.Next(milliseconds(10)));
  CHECK_THROWS_WITH(source.Next(milliseconds(10)), Catch::Contains("f1.png") &&
                                                       Catch::Contains("24x32") &&
                                                       Catch::Contains("32x24"));
}

TEST_CASE("replay of a missing, empty or non-folder path fails naming it", "[replay]") {
  TempDir dir;
  auto code_of = [](const std::string& uri) {
    try {
      gs360::OpenFrameSource(uri, {});
    } catch (const FrameSourceError& e) {
      CHECK_THAT(e.what(), Catch::Contains(uri));
      return e.code();
    }
    FAIL("expected FrameSourceError for " << uri);
    return FrameSourceErrc::kIo;
  };
  std::ofstream(dir.path() / "readme.txt") << "no images here";
  CHECK(code_of("replay:" + dir.path().string()) == FrameSourceErrc::kNoDevice);
  CHECK_THROWS_WITH(gs360::OpenFrameSource("replay:" + dir.path().string(), {}),
                    Catch::Contains("holds no image"));
  CHECK(code_of("replay:" + (dir.path() / "missing").string()) == FrameSourceErrc::kNoDevice);
  CHECK_THROWS_WITH(gs360::OpenFrameSource("replay:" + (dir.path() / "missing").string(), {}),
                    Catch::Contains("does not exist"));
  CHECK(code_of("replay:" + (dir.path() / "readme.txt").string()) == FrameSourceErrc::kNoDevice);
  CHECK(code_of("replay:") == FrameSourceErrc::kBadUri);
  CHECK(code_of("replay:" + dir.path().string() + "?fps=-3") == FrameSourceErrc::kBadUri);
  CHECK(code_of("replay:" + dir.path().string() + "?fps=fast") == FrameSourceErrc::kBadUri);
  CHECK(code_of("replay:" + dir.path().string() + "?speed=2") == FrameSourceErrc::kBadUri);
}
