#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <limits>
#include <optional>
#include <stdexcept>
#include <string>

#include "capture/frame_source.h"
#include "tests/capture/fake_frame_source.h"

using gs360::CameraControls;
using gs360::FrameSourceErrc;
using gs360::FrameSourceError;
using gs360::OpenFrameSource;

namespace {

// Opens `uri` expecting a FrameSourceError; checks that the message names the URI and returns it.
FrameSourceError OpenError(const std::string& uri, const CameraControls& controls = {}) {
  try {
    OpenFrameSource(uri, controls);
  } catch (const FrameSourceError& e) {
    CHECK(e.uri() == uri);
    CHECK_THAT(e.what(), Catch::Contains("'" + uri + "'"));
    return e;
  }
  FAIL("expected FrameSourceError opening " << uri);
  throw std::logic_error("unreachable");
}

}  // namespace

TEST_CASE("CameraControls::Check names the bad field and value", "[frame_source]") {
  CameraControls c;
  CHECK_NOTHROW(c.Check());
  c.exposure_us = 0;
  CHECK_THROWS_WITH(c.Check(), Catch::Contains("exposure_us") && Catch::Contains("0"));
  c = {};
  c.exposure_us = std::numeric_limits<double>::quiet_NaN();
  CHECK_THROWS_AS(c.Check(), std::invalid_argument);
  c = {};
  c.analogue_gain = -1;
  CHECK_THROWS_WITH(c.Check(), Catch::Contains("analogue_gain") && Catch::Contains("-1"));
  c = {};
  c.colour_gains = {1.5, 0.0};
  CHECK_THROWS_WITH(c.Check(), Catch::Contains("colour_gains[1]"));
  c = {};
  c.width = 4;
  CHECK_THROWS_WITH(c.Check(), Catch::Contains("width") && Catch::Contains("4"));
  c = {};
  c.height = 100000;
  CHECK_THROWS_WITH(c.Check(), Catch::Contains("height") && Catch::Contains("100000"));
  // OpenFrameSource checks the controls before anything else.
  CHECK_THROWS_AS(OpenFrameSource("nosuchscheme:x", c), std::invalid_argument);
}

TEST_CASE("ParseFrameSourceUri splits scheme, target and options", "[frame_source]") {
  auto u = gs360::ParseFrameSourceUri("replay:/data/run 1?fps=30&loop=1");
  CHECK(u.scheme == "replay");
  CHECK(u.target == "/data/run 1");
  CHECK(u.options.size() == 2);
  CHECK(u.DoubleOption("fps") == 30.0);
  CHECK(u.BoolOption("loop") == true);
  CHECK_FALSE(u.Option("missing"));
  CHECK_NOTHROW(u.RequireKnownOptions({"fps", "loop"}));
  CHECK_THROWS_WITH(u.RequireKnownOptions({"fps"}), Catch::Contains("unknown option 'loop'"));

  auto v = gs360::ParseFrameSourceUri("libcamera:/base/soc/i2c0mux/i2c@1/imx477@1a");
  CHECK(v.scheme == "libcamera");
  CHECK(v.target == "/base/soc/i2c0mux/i2c@1/imx477@1a");  // ':' and '@' in the target are fine
  CHECK(v.options.empty());

  auto w = gs360::ParseFrameSourceUri("sim:rig?x=");
  CHECK(w.Option("x") == std::string());
  CHECK_THROWS_AS(w.DoubleOption("x"), FrameSourceError);

  for (const char* bad : {"/dev/video0", "Video:0", "1cam:0", ":x", "v4l2:0?fps", "v4l2:0?=3",
                          "v4l2:0?fps=1&fps=2"}) {
    INFO(bad);
    try {
      gs360::ParseFrameSourceUri(bad);
      FAIL("expected kBadUri");
    } catch (const FrameSourceError& e) {
      CHECK(e.code() == FrameSourceErrc::kBadUri);
      CHECK_THAT(e.what(), Catch::Contains(bad));
    }
  }
  auto x = gs360::ParseFrameSourceUri("replay:/x?loop=maybe");
  CHECK_THROWS_WITH(x.BoolOption("loop"), Catch::Contains("loop") && Catch::Contains("maybe"));
}

TEST_CASE("an unknown scheme is an error listing the known ones", "[frame_source]") {
  const auto e = OpenError("gopro:0");
  CHECK(e.code() == FrameSourceErrc::kUnknownScheme);
  CHECK_THAT(e.what(), Catch::Contains("gopro") && Catch::Contains("libcamera") &&
                           Catch::Contains("replay") && Catch::Contains("v4l2"));
}

TEST_CASE("a registered scheme opens through OpenFrameSource", "[frame_source]") {
  int calls = 0;
  gs360::FrameSourceUri seen;
  CameraControls seen_controls;
  auto factory = [&](const gs360::FrameSourceUri& uri, const CameraControls& controls) {
    ++calls;
    seen = uri;
    seen_controls = controls;
    return std::make_unique<gs360::test::FakeFrameSource>();
  };
  CHECK_FALSE(gs360::RegisterFrameSourceFactory("testcam", factory));
  const auto schemes = gs360::FrameSourceSchemes();
  CHECK(std::find(schemes.begin(), schemes.end(), "testcam") != schemes.end());
  CHECK(std::is_sorted(schemes.begin(), schemes.end()));

  CameraControls controls;
  controls.exposure_us = 1234;
  controls.width = 320;
  auto source = OpenFrameSource("testcam:rig-1?noise=0.5", controls);
  REQUIRE(source);
  CHECK(source->Describe() == "fake source");
  CHECK(calls == 1);
  CHECK(seen.scheme == "testcam");
  CHECK(seen.target == "rig-1");
  CHECK(seen.DoubleOption("noise") == 0.5);
  CHECK(seen_controls.exposure_us == 1234);
  CHECK(seen_controls.width == 320);

  // Registering again replaces the factory.
  int second_calls = 0;
  CHECK(gs360::RegisterFrameSourceFactory("testcam",
                                          [&](const gs360::FrameSourceUri&, const CameraControls&) {
                                            ++second_calls;
                                            return std::make_unique<gs360::test::FakeFrameSource>();
                                          }));
  OpenFrameSource("testcam:x", {});
  CHECK(calls == 1);
  CHECK(second_calls == 1);

  CHECK(gs360::UnregisterFrameSourceFactory("testcam"));
  CHECK_FALSE(gs360::UnregisterFrameSourceFactory("testcam"));
  CHECK(OpenError("testcam:x").code() == FrameSourceErrc::kUnknownScheme);

  CHECK_THROWS_AS(gs360::RegisterFrameSourceFactory("Bad Scheme", factory), std::invalid_argument);
  CHECK_THROWS_AS(gs360::RegisterFrameSourceFactory("ok", gs360::FrameSourceFactory()),
                  std::invalid_argument);
  gs360::RegisterFrameSourceFactory("nullcam",
                                    [](const gs360::FrameSourceUri&, const CameraControls&) {
                                      return std::unique_ptr<gs360::FrameSource>();
                                    });
  CHECK(OpenError("nullcam:0").code() == FrameSourceErrc::kIo);
  gs360::UnregisterFrameSourceFactory("nullcam");
}

TEST_CASE("v4l2: a missing device is a clear error naming it", "[frame_source][v4l2]") {
  const auto e = OpenError("v4l2:/dev/video_gs360_missing");
  if (!gs360::HaveV4l2Support()) {
    CHECK(e.code() == FrameSourceErrc::kNotCompiled);
    CHECK_THAT(e.what(), Catch::Contains("compiled without V4L2 support"));
    return;
  }
  CHECK(e.code() == FrameSourceErrc::kNoDevice);
  CHECK_THAT(e.what(), Catch::Contains("no such V4L2 device /dev/video_gs360_missing"));
  // A bare index means /dev/video<index>.
  const auto f = OpenError("v4l2:987");
  CHECK(f.code() == FrameSourceErrc::kNoDevice);
  CHECK_THAT(f.what(), Catch::Contains("/dev/video987"));
  CHECK(OpenError("v4l2:").code() == FrameSourceErrc::kBadUri);
  CHECK(OpenError("v4l2:0?exposure=3").code() == FrameSourceErrc::kBadUri);
}

TEST_CASE("v4l2: a path that is not a camera is refused", "[frame_source][v4l2]") {
  if (!gs360::HaveV4l2Support()) return;
  // A regular file.
  const auto e = OpenError("v4l2:/proc/self/status");
  CHECK(e.code() == FrameSourceErrc::kNoDevice);
  CHECK_THAT(e.what(), Catch::Contains("not a character device"));
  // A character device that is not a V4L2 capture device.
  const auto f = OpenError("v4l2:/dev/null");
  CHECK(f.code() == FrameSourceErrc::kIo);
  CHECK_THAT(f.what(), Catch::Contains("/dev/null"));
}

TEST_CASE("libcamera: no camera (or no libcamera) is a clear error, not a crash or hang",
          "[frame_source][libcamera]") {
  if (!gs360::HaveLibcameraSupport()) {
    const auto e = OpenError("libcamera:0");
    CHECK(e.code() == FrameSourceErrc::kNotCompiled);
    CHECK_THAT(e.what(), Catch::Contains("gs360 was compiled without libcamera support"));
    return;
  }
  // This test machine has no camera; on a machine with one, index 0 may open (and is closed
  // again), and only the out-of-range and unknown-id errors below are checked.
  for (int attempt = 0; attempt < 2; ++attempt) {  // the shared CameraManager is re-created
    try {
      auto source = OpenFrameSource("libcamera:0", {});
      WARN("a libcamera camera is present: " << source->Describe());
    } catch (const FrameSourceError& e) {
      CHECK(e.uri() == "libcamera:0");
      CHECK(e.code() == FrameSourceErrc::kNoDevice);
      CHECK_THAT(e.what(), Catch::Contains("no camera") && Catch::Contains("'libcamera:0'"));
    }
  }
  const auto f = OpenError("libcamera:57");
  CHECK(f.code() == FrameSourceErrc::kNoDevice);
  CHECK_THAT(f.what(), Catch::Contains("no camera"));
  const auto g = OpenError("libcamera:/base/no/such/sensor@10");
  CHECK(g.code() == FrameSourceErrc::kNoDevice);
  CHECK(OpenError("libcamera:0?buffers=1").code() == FrameSourceErrc::kBadUri);
  CHECK(OpenError("libcamera:0?fps=30").code() == FrameSourceErrc::kBadUri);
  CHECK(OpenError("libcamera:").code() == FrameSourceErrc::kBadUri);
}
