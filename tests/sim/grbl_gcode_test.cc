#include <catch2/catch.hpp>

#include <string>

#include "sim/grbl_gcode.h"
#include "sim/grbl_settings.h"

using gs360::CoordinateData;
using gs360::GcodeBlock;
using gs360::GcodeState;
using gs360::ParseGcodeLine;

namespace {

int Parse(const std::string& line, const GcodeState& state = GcodeState(),
          GcodeBlock* out = nullptr) {
  GcodeBlock scratch;
  return ParseGcodeLine(line, state, CoordinateData(), out ? out : &scratch);
}

}  // namespace

TEST_CASE("ReadGrblFloat reads GRBL's number format", "[grbl_gcode]") {
  double v = 0;
  std::size_t pos = 0;
  CHECK(gs360::ReadGrblFloat("1.5X", pos, v));
  CHECK(v == 1.5);
  CHECK(pos == 3);
  pos = 0;
  CHECK(gs360::ReadGrblFloat("-.25", pos, v));
  CHECK(v == -0.25);
  pos = 0;
  CHECK(gs360::ReadGrblFloat("+3", pos, v));
  CHECK(v == 3.0);
  pos = 0;
  CHECK(gs360::ReadGrblFloat("1.2.3", pos, v));
  CHECK(v == Approx(1.2));
  CHECK(pos == 3);
  pos = 0;
  CHECK_FALSE(gs360::ReadGrblFloat("-", pos, v));
  pos = 0;
  CHECK_FALSE(gs360::ReadGrblFloat(".", pos, v));
  pos = 0;
  CHECK_FALSE(gs360::ReadGrblFloat("X1", pos, v));
}

TEST_CASE("Parser computes targets with modes and offsets", "[grbl_gcode]") {
  GcodeState gc;
  gc.position = Eigen::Vector3d(-10, -20, -5);
  gc.coord_system = Eigen::Vector3d(-100, -50, -10);
  GcodeBlock b;
  REQUIRE(Parse("G0X1Y2", gc, &b) == 0);
  CHECK(b.axis_command == gs360::kAxisCommandMotionMode);
  CHECK(b.xyz.isApprox(Eigen::Vector3d(-99, -48, -5)));  // Z keeps the current position
  REQUIRE(Parse("G91G1X1F100", gc, &b) == 0);
  CHECK(b.xyz.isApprox(Eigen::Vector3d(-9, -20, -5)));
  CHECK(b.feed_rate == 100);
  REQUIRE(Parse("G20G1X1F10", gc, &b) == 0);
  CHECK(b.xyz[0] == Approx(-100 + 25.4));
  CHECK(b.feed_rate == Approx(254));
  REQUIRE(Parse("G53G0X-3", gc, &b) == 0);
  CHECK(b.xyz[0] == -3.0);
  REQUIRE(Parse("G4P0.25", gc, &b) == 0);
  CHECK(b.non_modal == gs360::kNonModalDwell);
  CHECK(b.dwell_s == 0.25);
  // G10 L20 P1: make the current position read as X0 in G54.
  REQUIRE(Parse("G10L20P1X0", gc, &b) == 0);
  CHECK(b.coord_data_index == 0);
  CHECK(b.ijk[0] == -10.0);
  // Feed rate persists; a G1 without any feed rate is an error.
  gc.feed_rate = 300;
  REQUIRE(Parse("G1X0", gc, &b) == 0);
  CHECK(b.feed_rate == 300);
  CHECK(Parse("G1X0") == gs360::kGrblGcodeUndefinedFeedRate);
  // Jog: only distance, units and G53 allowed; F mandatory.
  REQUIRE(Parse("$J=G91X1F100", gc, &b) == 0);
  CHECK(b.jog);
  CHECK(b.xyz[0] == Approx(-9));
  CHECK(Parse("$J=G91X1", gc) == gs360::kGrblGcodeUndefinedFeedRate);
  CHECK(Parse("$J=G0X1F100", gc) == gs360::kGrblInvalidJogCommand);
}

TEST_CASE("Parser returns GRBL's error codes", "[grbl_gcode]") {
  using namespace gs360;
  GcodeState fed;
  fed.feed_rate = 100;
  CHECK(Parse("1G0") == kGrblExpectedCommandLetter);
  CHECK(Parse("G0X") == kGrblBadNumberFormat);
  CHECK(Parse("G0X-") == kGrblBadNumberFormat);
  CHECK(Parse("F-1") == kGrblNegativeValue);
  CHECK(Parse("G4P-1") == kGrblNegativeValue);
  CHECK(Parse("G5X1") == kGrblGcodeUnsupportedCommand);
  CHECK(Parse("M7") == kGrblGcodeUnsupportedCommand);  // mist coolant not compiled in
  CHECK(Parse("Q1") == kGrblGcodeUnsupportedCommand);
  CHECK(Parse("G38.1X1") == kGrblGcodeUnsupportedCommand);
  CHECK(Parse("G90G91") == kGrblGcodeModalGroupViolation);
  CHECK(Parse("G0G1X1") == kGrblGcodeAxisCommandConflict);  // GRBL checks this first
  CHECK(Parse("M3M5") == kGrblGcodeModalGroupViolation);
  CHECK(Parse("G1X1") == kGrblGcodeUndefinedFeedRate);
  CHECK(Parse("G1.5X1") == kGrblGcodeCommandValueNotInteger);
  CHECK(Parse("M3.5") == kGrblGcodeCommandValueNotInteger);
  CHECK(Parse("G0G10L20P1X0") == kGrblGcodeAxisCommandConflict);
  CHECK(Parse("G0X1X2") == kGrblGcodeWordRepeated);
  CHECK(Parse("G10L20P1") == kGrblGcodeNoAxisWords);
  CHECK(Parse("G92") == kGrblGcodeNoAxisWords);
  CHECK(Parse("N99999999G0X1") == kGrblGcodeInvalidLineNumber);
  CHECK(Parse("G4") == kGrblGcodeValueWordMissing);
  CHECK(Parse("G10X0") == kGrblGcodeValueWordMissing);
  CHECK(Parse("G10L2P7X0") == kGrblGcodeUnsupportedCoordSys);
  CHECK(Parse("G53G2X1Y1R5F100") == kGrblGcodeG53InvalidMotionMode);
  CHECK(Parse("G80X1") == kGrblGcodeAxisWordsExist);
  CHECK(Parse("G2Z5", fed) == kGrblGcodeNoAxisWordsInPlane);
  CHECK(Parse("G2X0Y0R5", fed) == kGrblGcodeInvalidTarget);
  CHECK(Parse("G2X10Y0R1", fed) == kGrblGcodeArcRadiusError);
  CHECK(Parse("G2X10", fed) == kGrblGcodeNoOffsetsInPlane);
  CHECK(Parse("G0X1P5") == kGrblGcodeUnusedWords);
  CHECK(Parse("G43.1X1") == kGrblGcodeG43DynamicAxisError);
  CHECK(Parse("T300") == kGrblGcodeMaxValueExceeded);
  CHECK(Parse("") == kGrblOk);
  CHECK(Parse("G21G90G94G17G54M5M9T0S0") == kGrblOk);
}

// Found by tests/fuzz (gcode_line): a command number past a long's range was cast to long, which
// is undefined (UBSan stopped there). GRBL keeps the low byte of the number, which for doubles
// that large is 0: the line reads as G0 and M0.
TEST_CASE("Parser takes command numbers past a long's range", "[grbl_gcode]") {
  using namespace gs360;
  CHECK(Parse("G4444444444444444444499") == kGrblOk);
  CHECK(Parse("G-4444444444444444444499") == kGrblOk);
  CHECK(Parse("M1" + std::string(40, '9')) == kGrblOk);
  CHECK(Parse("X1" + std::string(30, '7')) == kGrblOk);  // an axis value may be that large
  CHECK(Parse("P3" + std::string(95, '3') + "G10L2Y0") == kGrblGcodeUnsupportedCoordSys);
}

TEST_CASE("Parser state line and arcs", "[grbl_gcode]") {
  GcodeState gc;
  CHECK(gs360::FormatParserState(gc, false) == "[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]");
  gc.modal.motion = 1;
  gc.modal.coord_select = 1;
  gc.modal.incremental = true;
  gc.feed_rate = 254;
  CHECK(gs360::FormatParserState(gc, false) == "[GC:G1 G55 G17 G21 G91 G94 M5 M9 T0 F254 S0]");
  CHECK(gs360::FormatParserState(gc, true) == "[GC:G1 G55 G17 G21 G91 G94 M5 M9 T0 F10.0 S0]");

  // A half circle of radius 10 in XY, counter-clockwise from (0,0) to (20,0) around (10,0).
  GcodeBlock b;
  gc = GcodeState();
  gc.feed_rate = 100;
  REQUIRE(Parse("G3X20Y0I10J0", gc, &b) == 0);
  const auto pts = gs360::ArcSegmentTargets(gc.position, b.xyz, b.ijk, b.radius, b.axis_0, b.axis_1,
                                            b.axis_linear, b.arc_clockwise, 0.002);
  REQUIRE(pts.size() > 50);
  CHECK(pts.back().isApprox(Eigen::Vector3d(20, 0, 0)));
  for (const auto& p : pts) CHECK(std::hypot(p[0] - 10, p[1]) == Approx(10).margin(1e-9));
  // Counter-clockwise from (0,0) around (10,0) goes through negative y.
  CHECK(pts[pts.size() / 2][1] < -9.9);
}

TEST_CASE("Settings print and store like GRBL", "[grbl_settings]") {
  using namespace gs360;
  GrblSettings s = GrblSettings::GrblFirmwareDefaults();
  const std::string r = s.Report();
  CHECK(r.rfind("$0=10\r\n$1=25\r\n$2=0\r\n", 0) == 0);
  CHECK(r.find("$10=1\r\n$11=0.010\r\n$12=0.002\r\n$13=0\r\n") != std::string::npos);
  CHECK(r.find("$30=1000\r\n$31=0\r\n$32=0\r\n") != std::string::npos);
  CHECK(r.find("$110=500.000\r\n") != std::string::npos);
  CHECK(r.find("$120=10.000\r\n") != std::string::npos);
  CHECK(r.substr(r.size() - 14) == "$132=200.000\r\n");
  CHECK(s.Store(20, 1) == kGrblSoftLimitError);  // homing is off in the firmware defaults
  CHECK(s.Store(22, 1) == kGrblOk);
  CHECK(s.Store(20, 1) == kGrblOk);
  CHECK(s.soft_limits);
  CHECK(s.Store(22, 0) == kGrblOk);
  CHECK_FALSE(s.soft_limits);  // $22=0 forces soft limits off
  CHECK(s.Store(0, 2) == kGrblSettingStepPulseMin);
  CHECK(s.Store(1, -1) == kGrblNegativeValue);
  CHECK(s.Store(7, 1) == kGrblInvalidStatement);
  CHECK(s.Store(133, 1) == kGrblInvalidStatement);
  CHECK(s.Store(111, 1234.5) == kGrblOk);
  CHECK(s.max_rate_mm_per_min[1] == 1234.5);
  CHECK(s.Limits().max_rate_mm_per_min[1] == 1234.5);
  CHECK_NOTHROW(GrblSettings().Check());
  GrblSettings bad;
  bad.acceleration_mm_per_s2[2] = 0;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("acceleration_mm_per_s2.z"));

  CHECK(FormatGrblFloat(-0.0001, 3) == "-0.000");
  CHECK(FormatGrblFloat(1.23456, 3) == "1.235");
  CHECK(FormatGrblFloat(-1.5, 0) == "-2");
  CHECK(FormatGrblFloat(12, 3) == "12.000");
  CHECK(FormatGrblFloat(0.05, 1) == "0.1");
}
