#include <catch2/catch.hpp>

#include <chrono>
#include <cmath>
#include <random>
#include <stdexcept>

#include "capture/capture_press.h"
#include "tests/capture/fake_frame_source.h"

using gs360::CapturePress;
using gs360::PressCaptureOptions;
using gs360::PressCaptureStatus;
using gs360::ReferenceSchedule;
using gs360::test::FakeFrameSource;
using Clock = std::chrono::steady_clock;
using std::chrono::microseconds;
using std::chrono::milliseconds;

namespace {

// A fixed, arbitrary point on the steady clock: the tests never depend on the real time.
const Clock::time_point kSyncOk = Clock::time_point(std::chrono::seconds(1000));

int Pixel(const cv::Mat& m, int row, int col, int channel) {
  return m.at<cv::Vec3b>(row, col)[channel];
}

}  // namespace

TEST_CASE("CapturePress drops frames exposed up to the sync ok and averages the next K",
          "[capture_press]") {
  FakeFrameSource source;
  source.Push(kSyncOk - milliseconds(20), 200);  // stale: still moving
  source.Push(kSyncOk - milliseconds(1), 201);   // stale
  source.Push(kSyncOk, 202);                     // stale: not strictly after the ok
  source.Push(kSyncOk + milliseconds(10), 10);
  source.Push(kSyncOk + milliseconds(20), 11);
  source.Push(kSyncOk + milliseconds(30), 13);
  source.Push(kSyncOk + milliseconds(40), 99);  // not needed

  PressCaptureOptions options;
  options.frames_to_average = 3;
  const auto result = CapturePress(source, kSyncOk, options);

  REQUIRE(result.ok());
  CHECK(result.stale_dropped == 3);
  CHECK(result.frames_used == 3);
  CHECK(result.first_timestamp == kSyncOk + milliseconds(10));
  CHECK(result.last_timestamp == kSyncOk + milliseconds(30));
  CHECK(result.first_sequence == 3);
  CHECK(result.last_sequence == 5);
  CHECK(source.remaining() == 1);
  REQUIRE(result.image.type() == CV_8UC3);
  REQUIRE(result.image.size() == cv::Size(8, 6));
  // (10 + 11 + 13) / 3 = 11.33 -> 11, in every pixel and channel.
  CHECK(cv::countNonZero(result.image.reshape(1) != 11) == 0);
}

TEST_CASE("CapturePress treats a frame whose exposure began before the ok as stale",
          "[capture_press]") {
  FakeFrameSource source;
  // Ends 2 ms after the ok but was exposing for 5 ms: it saw the machine before the ok.
  source.Push(kSyncOk + milliseconds(2), 50, {8, 6}, microseconds(5000));
  source.Push(kSyncOk + milliseconds(12), 60, {8, 6}, microseconds(5000));
  PressCaptureOptions options;
  options.frames_to_average = 1;
  const auto result = CapturePress(source, kSyncOk, options);
  REQUIRE(result.ok());
  CHECK(result.stale_dropped == 1);
  CHECK(Pixel(result.image, 0, 0, 0) == 60);
}

TEST_CASE("CapturePress averages per pixel and per channel with round-to-nearest",
          "[capture_press]") {
  std::mt19937 rng(7);
  std::uniform_int_distribution<int> value(0, 255);
  const cv::Size size(31, 17);
  FakeFrameSource source;
  std::vector<cv::Mat> frames;
  for (int k = 0; k < 3; ++k) {
    cv::Mat m(size, CV_8UC3);
    for (int r = 0; r < size.height; ++r) {
      for (int c = 0; c < size.width; ++c) {
        m.at<cv::Vec3b>(r, c) =
            cv::Vec3b(static_cast<uchar>(value(rng)), static_cast<uchar>(value(rng)),
                      static_cast<uchar>(value(rng)));
      }
    }
    frames.push_back(m);
    source.Push(kSyncOk + milliseconds(1 + k), m.clone());
  }
  PressCaptureOptions options;
  options.frames_to_average = 3;
  options.reject_outliers = false;  // random frames disagree everywhere
  const auto result = CapturePress(source, kSyncOk, options);
  REQUIRE(result.ok());
  int mismatches = 0;
  for (int r = 0; r < size.height; ++r) {
    for (int c = 0; c < size.width; ++c) {
      for (int ch = 0; ch < 3; ++ch) {
        double sum = 0;
        for (const auto& f : frames) sum += f.at<cv::Vec3b>(r, c)[ch];
        // With K = 3 the mean is never exactly halfway, so plain rounding is unambiguous.
        const int expected = static_cast<int>(std::lround(sum / 3.0));
        if (Pixel(result.image, r, c, ch) != expected) ++mismatches;
      }
    }
  }
  CHECK(mismatches == 0);
}

TEST_CASE("CapturePress rounds exact halves to even", "[capture_press]") {
  FakeFrameSource source;
  // Two frames per pixel column: (1, 2) -> 1.5 -> 2, (2, 3) -> 2.5 -> 2, (10, 10) -> 10.
  cv::Mat a(1, 3, CV_8UC3), b(1, 3, CV_8UC3);
  a.at<cv::Vec3b>(0, 0) = cv::Vec3b(1, 1, 1);
  b.at<cv::Vec3b>(0, 0) = cv::Vec3b(2, 2, 2);
  a.at<cv::Vec3b>(0, 1) = cv::Vec3b(2, 2, 2);
  b.at<cv::Vec3b>(0, 1) = cv::Vec3b(3, 3, 3);
  a.at<cv::Vec3b>(0, 2) = cv::Vec3b(10, 10, 10);
  b.at<cv::Vec3b>(0, 2) = cv::Vec3b(10, 10, 10);
  source.Push(kSyncOk + milliseconds(1), a);
  source.Push(kSyncOk + milliseconds(2), b);
  PressCaptureOptions options;
  options.frames_to_average = 2;
  const auto result = CapturePress(source, kSyncOk, options);
  REQUIRE(result.ok());
  CHECK(Pixel(result.image, 0, 0, 1) == 2);
  CHECK(Pixel(result.image, 0, 1, 1) == 2);
  CHECK(Pixel(result.image, 0, 2, 1) == 10);
}

TEST_CASE("CapturePress reports a timeout when the source runs dry", "[capture_press]") {
  FakeFrameSource source;
  source.Push(kSyncOk - milliseconds(5), 1);
  source.Push(kSyncOk + milliseconds(5), 2);
  source.Push(kSyncOk + milliseconds(6), 3);
  PressCaptureOptions options;
  options.frames_to_average = 3;
  options.timeout = milliseconds(500);
  const auto result = CapturePress(source, kSyncOk, options);
  CHECK(result.status == PressCaptureStatus::kTimeout);
  CHECK_FALSE(result.ok());
  CHECK(result.image.empty());
  CHECK(result.frames_used == 2);
  CHECK(result.stale_dropped == 1);
  // Four Next() calls, each bounded by what is left of the 500 ms deadline.
  REQUIRE(source.next_timeouts.size() == 4);
  for (auto t : source.next_timeouts) {
    CHECK(t.count() > 0);
    CHECK(t <= milliseconds(500));
  }
}

TEST_CASE("CapturePress gives up after max_stale_frames stale frames", "[capture_press]") {
  FakeFrameSource source;
  for (int i = 0; i < 10; ++i) source.Push(kSyncOk - milliseconds(100 - i), i);
  source.Push(kSyncOk + milliseconds(1), 42);
  PressCaptureOptions options;
  options.frames_to_average = 1;
  options.max_stale_frames = 3;
  const auto result = CapturePress(source, kSyncOk, options);
  CHECK(result.status == PressCaptureStatus::kTooManyStale);
  CHECK(result.stale_dropped == 4);
  CHECK(result.image.empty());
  CHECK(source.remaining() == 7);
  CHECK(gs360::ToString(result.status) == "too many stale frames");
}

namespace {

// A settled press as a camera gives it: a scene plus a few DN of noise per frame.
// (cv::theRNG(): seed it for a repeatable test.)
cv::Mat NoisyFrame(const cv::Mat& scene) {
  cv::Mat noise(scene.size(), CV_16SC3);
  cv::randn(noise, 0, 3);
  cv::Mat out;
  cv::add(scene, noise, out, cv::noArray(), CV_8UC3);
  return out;
}

cv::Mat Scene() {
  cv::Mat scene(48, 64, CV_8UC3);
  for (int r = 0; r < scene.rows; ++r) {
    for (int c = 0; c < scene.cols; ++c) {
      scene.at<cv::Vec3b>(r, c) = cv::Vec3b(static_cast<uchar>(60 + c), static_cast<uchar>(90 + r),
                                            static_cast<uchar>(120 + (r + c) % 50));
    }
  }
  return scene;
}

// A transfer error: `rows` rows of random bytes from row `from`.
cv::Mat Garbled(cv::Mat frame, int from, int rows) {
  cv::randu(frame.rowRange(from, from + rows), cv::Scalar::all(0), cv::Scalar::all(256));
  return frame;
}

double MeanAbsDiff(const cv::Mat& a, const cv::Mat& b) {
  cv::Mat d;
  cv::absdiff(a, b, d);
  return cv::mean(d.reshape(1))[0];
}

}  // namespace

TEST_CASE("CapturePress leaves a garbled frame out of the average and reads another",
          "[capture_press]") {
  cv::theRNG().state = 11;
  const cv::Mat scene = Scene();
  PressCaptureOptions options;
  options.frames_to_average = 3;
  for (int bad = 0; bad < 3; ++bad) {
    INFO("garbled frame " << bad);
    FakeFrameSource source;
    for (int k = 0; k < 4; ++k) {
      cv::Mat f = NoisyFrame(scene);
      source.Push(kSyncOk + milliseconds(1 + k), k == bad ? Garbled(f, 10, 3) : f);
    }
    const auto result = CapturePress(source, kSyncOk, options);
    REQUIRE(result.ok());
    CHECK(result.outliers_rejected == 1);
    CHECK(result.frames_used == 3);
    CHECK(source.remaining() == 0);
    CHECK(MeanAbsDiff(result.image, scene) < 2.5);  // noise averaged, no garbage in it
    CHECK(result.last_sequence == 3);
    CHECK(result.first_sequence == (bad == 0 ? 1u : 0u));
  }
  SECTION("without the check, the garbage is averaged in") {
    options.reject_outliers = false;
    FakeFrameSource source;
    for (int k = 0; k < 3; ++k) {
      cv::Mat f = NoisyFrame(scene);
      source.Push(kSyncOk + milliseconds(1 + k), k == 1 ? Garbled(f, 10, 3) : f);
    }
    const auto result = CapturePress(source, kSyncOk, options);
    REQUIRE(result.ok());
    CHECK(result.outliers_rejected == 0);
    CHECK(MeanAbsDiff(result.image.rowRange(10, 13), scene.rowRange(10, 13)) > 10.0);
  }
}

TEST_CASE(
    "CapturePress with two frames that disagree reads a third to decide, and gives up "
    "when none agree",
    "[capture_press]") {
  cv::theRNG().state = 12;
  const cv::Mat scene = Scene();
  PressCaptureOptions options;
  options.frames_to_average = 2;
  {
    FakeFrameSource source;
    source.Push(kSyncOk + milliseconds(1), Garbled(NoisyFrame(scene), 0, 48));
    source.Push(kSyncOk + milliseconds(2), NoisyFrame(scene));
    source.Push(kSyncOk + milliseconds(3), NoisyFrame(scene));
    const auto result = CapturePress(source, kSyncOk, options);
    REQUIRE(result.ok());
    CHECK(result.outliers_rejected == 1);
    CHECK(result.first_sequence == 1);
    CHECK(MeanAbsDiff(result.image, scene) < 3.0);
  }
  {
    // Every frame torn differently: K + max_outlier_frames frames read, then a status.
    options.max_outlier_frames = 2;
    FakeFrameSource source;
    for (int k = 0; k < 6; ++k) {
      source.Push(kSyncOk + milliseconds(1 + k), Garbled(NoisyFrame(scene), 8 * k, 8));
    }
    const auto result = CapturePress(source, kSyncOk, options);
    CHECK(result.status == PressCaptureStatus::kInconsistent);
    CHECK(gs360::ToString(result.status) == "frames disagree");
    CHECK(result.image.empty());
    CHECK(source.remaining() == 2);
  }
  {
    // K = 1 has nothing to compare with: the first fresh frame is the capture.
    options.frames_to_average = 1;
    FakeFrameSource source;
    source.Push(kSyncOk + milliseconds(1), 7);
    const auto result = CapturePress(source, kSyncOk, options);
    REQUIRE(result.ok());
    CHECK(result.outliers_rejected == 0);
  }
}

TEST_CASE("CapturePress rejects frames that change size or are not 8-bit BGR", "[capture_press]") {
  PressCaptureOptions options;
  options.frames_to_average = 2;
  {
    FakeFrameSource source;
    source.Push(kSyncOk + milliseconds(1), 5, cv::Size(8, 6));
    source.Push(kSyncOk + milliseconds(2), 5, cv::Size(6, 8));
    CHECK_THROWS_AS(CapturePress(source, kSyncOk, options), std::runtime_error);
  }
  {
    FakeFrameSource source;
    source.Push(kSyncOk + milliseconds(1), cv::Mat(6, 8, CV_8UC1, cv::Scalar(5)));
    CHECK_THROWS_WITH(CapturePress(source, kSyncOk, options),
                      Catch::Contains("fake source") && Catch::Contains("CV_8UC3"));
  }
}

TEST_CASE("PressCaptureOptions::Check names the bad field", "[capture_press]") {
  PressCaptureOptions options;
  CHECK_NOTHROW(options.Check());
  options.frames_to_average = 0;
  CHECK_THROWS_WITH(options.Check(), Catch::Contains("frames_to_average") && Catch::Contains("0"));
  options = {};
  options.timeout = milliseconds(0);
  CHECK_THROWS_WITH(options.Check(), Catch::Contains("timeout"));
  options = {};
  options.max_stale_frames = -1;
  CHECK_THROWS_WITH(options.Check(), Catch::Contains("max_stale_frames") && Catch::Contains("-1"));
  options = {};
  options.outlier_dn = 0;
  CHECK_THROWS_WITH(options.Check(), Catch::Contains("outlier_dn") && Catch::Contains("0"));
  options = {};
  options.outlier_fraction = 1.5;
  CHECK_THROWS_WITH(options.Check(), Catch::Contains("outlier_fraction") && Catch::Contains("1.5"));
  options = {};
  options.frames_to_average = 51;
  CHECK_THROWS_WITH(options.Check(), Catch::Contains("<= 50 with reject_outliers"));
  options.reject_outliers = false;
  CHECK_NOTHROW(options.Check());
  options = {};
  options.max_outlier_frames = -2;
  CHECK_THROWS_WITH(options.Check(),
                    Catch::Contains("max_outlier_frames") && Catch::Contains("-2"));
  options.max_stale_frames = -1;
  FakeFrameSource source;
  source.Push(kSyncOk + milliseconds(1), 1);
  CHECK_THROWS_AS(CapturePress(source, kSyncOk, options), std::invalid_argument);
  CHECK(source.next_timeouts.empty());
}

TEST_CASE("ReferenceSchedule: a reference at the start, then every M probes", "[capture_press]") {
  ReferenceSchedule schedule{25};
  CHECK(schedule.NeedsReference(0, std::nullopt));
  CHECK(schedule.NeedsReference(40, std::nullopt));  // resumed run without any reference
  CHECK_FALSE(schedule.NeedsReference(0, 0));
  CHECK_FALSE(schedule.NeedsReference(24, 0));
  CHECK(schedule.NeedsReference(25, 0));
  CHECK(schedule.NeedsReference(30, 0));
  CHECK_FALSE(schedule.NeedsReference(49, 25));
  CHECK(schedule.NeedsReference(50, 25));

  ReferenceSchedule only_start{0};
  CHECK(only_start.NeedsReference(0, std::nullopt));
  CHECK_FALSE(only_start.NeedsReference(100000, 0));

  CHECK_THROWS_AS(schedule.NeedsReference(10, 11), std::invalid_argument);
  CHECK_THROWS_AS(schedule.NeedsReference(-1, std::nullopt), std::invalid_argument);
  CHECK_THROWS_WITH(ReferenceSchedule{-3}.Check(),
                    Catch::Contains("every_m_probes") && Catch::Contains("-3"));
}
