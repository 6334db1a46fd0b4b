#include <catch2/catch.hpp>

#include <string>
#include <vector>

#include "gcode/grbl_messages.h"

using gs360::GrblLineSplitter;
using gs360::GrblMachineState;
using gs360::GrblMessage;
using gs360::GrblMessageKind;
using gs360::ParseGrblLine;

TEST_CASE("ok, error and alarm replies", "[grbl_messages]") {
  CHECK(ParseGrblLine("ok").kind == GrblMessageKind::kOk);
  CHECK(ParseGrblLine("ok\r").kind == GrblMessageKind::kOk);

  const GrblMessage e = ParseGrblLine("error:20");
  CHECK(e.kind == GrblMessageKind::kError);
  CHECK(e.code == 20);
  CHECK(e.text.find("Unsupported or invalid g-code") != std::string::npos);

  const GrblMessage old_style = ParseGrblLine("error: Bad number format");
  CHECK(old_style.kind == GrblMessageKind::kError);  // still resolves a line
  CHECK(old_style.code == -1);
  CHECK(old_style.text == "Bad number format");

  const GrblMessage a = ParseGrblLine("ALARM:2");
  CHECK(a.kind == GrblMessageKind::kAlarm);
  CHECK(a.code == 2);
  CHECK(a.text.find("exceeds machine travel") != std::string::npos);

  CHECK(gs360::GrblErrorText(9).find("locked out") != std::string::npos);
  CHECK(gs360::GrblErrorText(99) == "unknown error 99 (not in the GRBL 1.1 or grblHAL tables)");
  CHECK(gs360::GrblAlarmText(1).find("Hard limit") != std::string::npos);
  CHECK(gs360::GrblAlarmText(42) == "unknown alarm 42 (not in the GRBL 1.1 or grblHAL tables)");
  CHECK(gs360::GrblAlarmLosesPosition(1));
  CHECK(gs360::GrblAlarmLosesPosition(3));
  CHECK(gs360::GrblAlarmLosesPosition(9));
  CHECK_FALSE(gs360::GrblAlarmLosesPosition(2));
  CHECK_FALSE(gs360::GrblAlarmLosesPosition(5));
}

TEST_CASE("welcome lines of GRBL, grblHAL and FluidNC", "[grbl_messages]") {
  const GrblMessage g = ParseGrblLine("Grbl 1.1h ['$' for help]");
  CHECK(g.kind == GrblMessageKind::kWelcome);
  CHECK(g.name == "Grbl");
  CHECK(g.version == "1.1h");

  const GrblMessage hal = ParseGrblLine("GrblHAL 1.1f ['$' or '$HELP' for help]");
  CHECK(hal.kind == GrblMessageKind::kWelcome);
  CHECK(hal.name == "GrblHAL");
  CHECK(hal.version == "1.1f");

  const GrblMessage fluid = ParseGrblLine("Grbl 3.7 [FluidNC v3.7.8 (wifi) '$' for help]");
  CHECK(fluid.kind == GrblMessageKind::kWelcome);
  CHECK(fluid.version == "3.7");

  // Noise before the welcome must not hide a reset.
  const GrblMessage noisy = ParseGrblLine("\xff\xfe\x01Grbl 1.1h ['$' for help]");
  CHECK(noisy.kind == GrblMessageKind::kWelcome);
  CHECK(noisy.version == "1.1h");

  CHECK(ParseGrblLine("Grbl is great").kind == GrblMessageKind::kUnknown);
}

TEST_CASE("status reports with every field", "[grbl_messages]") {
  const GrblMessage m = ParseGrblLine(
      "<Hold:1|MPos:1.500,-2.250,3.000|Bf:12,100|Ln:99|FS:500,8000|WCO:0.000,1.551,5.664|"
      "Ov:100,50,120|Pn:XPZ|A:SF|H:1>");
  REQUIRE(m.kind == GrblMessageKind::kStatus);
  const gs360::GrblStatusReport& s = m.status;
  CHECK(s.state == GrblMachineState::kHold);
  CHECK(s.state_text == "Hold");
  CHECK(s.substate == 1);
  REQUIRE(s.mpos);
  CHECK(s.mpos->isApprox(Eigen::Vector3d(1.5, -2.25, 3.0)));
  CHECK(s.axis_count == 3);
  CHECK(s.planner_blocks_free == 12);
  CHECK(s.rx_bytes_free == 100);
  CHECK(s.line_number == 99);
  CHECK(s.feed == 500.0);
  CHECK(s.spindle == 8000.0);
  REQUIRE(s.wco);
  CHECK(s.wco->isApprox(Eigen::Vector3d(0.0, 1.551, 5.664)));
  REQUIRE(s.overrides);
  CHECK((*s.overrides)[1] == 50);
  CHECK(s.pins == "XPZ");
  CHECK(s.accessories == "SF");
  REQUIRE(s.other_fields.size() == 1);
  CHECK(s.other_fields[0].first == "H");

  // WPos + WCO gives the machine position; F without spindle; four axes.
  const GrblMessage w = ParseGrblLine("<Run|WPos:1.000,2.000,3.000,4.000|F:250>");
  REQUIRE(w.kind == GrblMessageKind::kStatus);
  CHECK(w.status.state == GrblMachineState::kRun);
  CHECK(w.status.substate == -1);
  CHECK(w.status.axis_count == 4);
  CHECK(w.status.feed == 250.0);
  CHECK_FALSE(w.status.spindle);
  CHECK_FALSE(w.status.MachinePosition());
  const auto mp = w.status.MachinePosition(Eigen::Vector3d(10, 20, 30));
  REQUIRE(mp);
  CHECK(mp->isApprox(Eigen::Vector3d(11, 22, 33)));

  for (const char* s_text :
       {"<Idle|MPos:0.000,0.000,0.000|FS:0,0>", "<Alarm|MPos:0,0,0>", "<Home|MPos:0,0,0>",
        "<Door:2|MPos:0,0,0>", "<Jog|MPos:0,0,0>", "<Check|MPos:0,0,0>", "<Sleep|MPos:0,0,0>"}) {
    CHECK(ParseGrblLine(s_text).kind == GrblMessageKind::kStatus);
  }
  CHECK(ParseGrblLine("<Door:2|MPos:0,0,0>").status.substate == 2);
}

TEST_CASE("malformed status reports are unknown, never half-parsed", "[grbl_messages]") {
  for (const char* bad : {"<Idle|MPos:1.0,abc,2.0|FS:0,0>", "<Idle|MPos:1,2>", "<Idle|FS:0,0>",
                          "<Idle|MPos:0,0,0|Bf:15>", "<Idle|MPos:0,0,0", "<>", "<Idle|MPos>",
                          "<Hold:x|MPos:0,0,0>", "<Idle|MPos:0,0,0|Ov:100,100>"}) {
    const GrblMessage m = ParseGrblLine(bad);
    CHECK(m.kind == GrblMessageKind::kUnknown);
    CHECK_FALSE(m.status.mpos);
  }
}

TEST_CASE("feedback messages in brackets", "[grbl_messages]") {
  const GrblMessage msg = ParseGrblLine("[MSG:'$H'|'$X' to unlock]");
  CHECK(msg.kind == GrblMessageKind::kMessage);
  CHECK(msg.text == "'$H'|'$X' to unlock");

  const GrblMessage gc = ParseGrblLine("[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]");
  CHECK(gc.kind == GrblMessageKind::kGcState);
  CHECK(gc.text == "G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0");

  const GrblMessage hlp =
      ParseGrblLine("[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $C $X $H ~ ! ? ctrl-x]");
  CHECK(hlp.kind == GrblMessageKind::kHelp);

  const GrblMessage ver = ParseGrblLine("[VER:1.1h.20190830:my rig]");
  CHECK(ver.kind == GrblMessageKind::kVersion);
  CHECK(ver.version == "1.1h.20190830");
  CHECK(ver.text == "my rig");

  const GrblMessage opt = ParseGrblLine("[OPT:V,15,128]");
  CHECK(opt.kind == GrblMessageKind::kOptions);
  CHECK(opt.option_codes == "V");
  CHECK(opt.planner_blocks == 15);
  CHECK(opt.rx_buffer_bytes == 128);

  const GrblMessage hal_opt = ParseGrblLine("[OPT:VNMSL,35,1024,3,0]");
  CHECK(hal_opt.planner_blocks == 35);
  CHECK(hal_opt.rx_buffer_bytes == 1024);

  const GrblMessage old_opt = ParseGrblLine("[OPT:VL]");  // GRBL 1.1d: no sizes
  CHECK(old_opt.kind == GrblMessageKind::kOptions);
  CHECK_FALSE(old_opt.rx_buffer_bytes);

  const GrblMessage echo = ParseGrblLine("[echo:G1X0.540Y10.4F100]");
  CHECK(echo.kind == GrblMessageKind::kEcho);
  CHECK(echo.text == "G1X0.540Y10.4F100");

  const GrblMessage g54 = ParseGrblLine("[G54:1.000,-2.000,3.500]");
  CHECK(g54.kind == GrblMessageKind::kParameter);
  CHECK(g54.name == "G54");
  CHECK(g54.values == std::vector<double>{1.0, -2.0, 3.5});
  CHECK(ParseGrblLine("[G28:0.000,0.000,0.000]").kind == GrblMessageKind::kParameter);
  CHECK(ParseGrblLine("[G92:0.000,0.000,0.000]").kind == GrblMessageKind::kParameter);
  const GrblMessage tlo = ParseGrblLine("[TLO:0.250]");
  CHECK(tlo.kind == GrblMessageKind::kParameter);
  CHECK(tlo.values == std::vector<double>{0.25});
  const GrblMessage prb = ParseGrblLine("[PRB:1.000,2.000,-3.000:1]");
  CHECK(prb.kind == GrblMessageKind::kParameter);
  CHECK(prb.values.size() == 3);
  CHECK(prb.probe_success == true);
  CHECK(ParseGrblLine("[PRB:0.000,0.000,0.000:0]").probe_success == false);

  const GrblMessage other = ParseGrblLine("[AXS:3:XYZ]");
  CHECK(other.kind == GrblMessageKind::kFeedback);
  CHECK(other.name == "AXS");
  CHECK(ParseGrblLine("[MSG:unterminated").kind == GrblMessageKind::kUnknown);
}

TEST_CASE("settings and startup lines", "[grbl_messages]") {
  const GrblMessage s = ParseGrblLine("$110=500.000");
  CHECK(s.kind == GrblMessageKind::kSetting);
  CHECK(s.setting == 110);
  CHECK(s.setting_value == 500.0);
  const GrblMessage old = ParseGrblLine("$0=10 (step pulse, usec)");  // GRBL 0.9
  CHECK(old.kind == GrblMessageKind::kSetting);
  CHECK(old.setting_value == 10.0);
  const GrblMessage text_setting = ParseGrblLine("$300=gs360-rig");  // grblHAL string setting
  CHECK(text_setting.kind == GrblMessageKind::kSetting);
  CHECK_FALSE(text_setting.setting_value);
  CHECK(text_setting.text == "gs360-rig");

  const GrblMessage n0 = ParseGrblLine("$N0=G54");
  CHECK(n0.kind == GrblMessageKind::kStartupLineSetting);
  CHECK(n0.setting == 0);
  CHECK(n0.text == "G54");
  CHECK(ParseGrblLine("$N1=").kind == GrblMessageKind::kStartupLineSetting);

  const GrblMessage ran = ParseGrblLine(">G54G20:ok");
  CHECK(ran.kind == GrblMessageKind::kStartupLineResult);
  CHECK(ran.text == "G54G20");
  CHECK(ran.code == 0);
  const GrblMessage failed = ParseGrblLine(">G54G20:error:20");
  CHECK(failed.kind == GrblMessageKind::kStartupLineResult);
  CHECK(failed.code == 20);
  CHECK(ParseGrblLine(">:error:7").code == 7);

  CHECK(ParseGrblLine("$abc=1").kind == GrblMessageKind::kUnknown);
  CHECK(ParseGrblLine("$").kind == GrblMessageKind::kUnknown);
}

TEST_CASE("garbage lines are unknown or empty and never throw", "[grbl_messages]") {
  CHECK(ParseGrblLine("").kind == GrblMessageKind::kEmpty);
  CHECK(ParseGrblLine("\x01\x02\xff").kind == GrblMessageKind::kEmpty);
  CHECK(ParseGrblLine("okay").kind == GrblMessageKind::kUnknown);
  CHECK(ParseGrblLine("oko").kind == GrblMessageKind::kUnknown);
  // Noise bytes around a reply are dropped, the reply survives.
  CHECK(ParseGrblLine("\xffok\x00").kind == GrblMessageKind::kOk);
  CHECK(ParseGrblLine("  ok  ").kind == GrblMessageKind::kOk);
  // Every byte value, alone and in combination with message prefixes: no throw, no crash.
  std::string all;
  for (int b = 0; b < 256; ++b) all.push_back(static_cast<char>(b));
  for (const std::string prefix : {"", "<", "[", "$", ">", "error:", "ALARM:", "Grbl "}) {
    for (std::size_t cut = 0; cut < all.size(); cut += 17) {
      const std::string line = prefix + all.substr(cut, 40);
      CHECK_NOTHROW(ParseGrblLine(line));
    }
  }
}

TEST_CASE("line splitter handles CRLF, split chunks and overlong garbage", "[grbl_messages]") {
  GrblLineSplitter splitter;
  std::vector<std::string> lines;
  const std::string stream = "ok\r\n<Idle|MPos:0.000,0.000,0.000|FS:0,0>\r\nerr";
  splitter.Feed(stream.data(), stream.size(), &lines);
  REQUIRE(lines.size() == 2);
  CHECK(lines[0] == "ok");
  CHECK(lines[1] == "<Idle|MPos:0.000,0.000,0.000|FS:0,0>");
  const std::string rest = "or:9\r\n\r\n\n";
  splitter.Feed(rest.data(), rest.size(), &lines);
  REQUIRE(lines.size() == 3);
  CHECK(lines[2] == "error:9");

  // 5000 bytes without a newline: cut once, the rest discarded up to the newline, then normal.
  lines.clear();
  const std::string flood(5000, 'x');
  splitter.Feed(flood.data(), flood.size(), &lines);
  const std::string after = "\r\nok\r\n";
  splitter.Feed(after.data(), after.size(), &lines);
  REQUIRE(lines.size() == 2);
  CHECK(lines[0].size() == GrblLineSplitter::kMaxLine);
  CHECK(lines[1] == "ok");
  CHECK(splitter.OverlongLines() == 1);
}

namespace {

// The codes of the source tables, listed independently of gcode/grbl_messages.cc.
// GRBL 1.1: gnea/grbl doc/csv/error_codes_en_US.csv and alarm_codes_en_US.csv.
// grblHAL: grblHAL/core errors.h (status_code_t) with errors.c, alarms.h (alarm_code_t) with
// alarms.c; 60-66 and 70 are described by grblHAL plugins.
std::vector<int> Range(int first, int last) {
  std::vector<int> v;
  for (int c = first; c <= last; ++c) v.push_back(c);
  return v;
}

std::vector<int> Grbl11ErrorCodes() {
  std::vector<int> v = Range(1, 17);
  for (int c : Range(20, 38)) v.push_back(c);
  return v;
}

std::vector<int> GrblHalErrorCodes() {
  std::vector<int> v = Range(1, 58);
  for (int c : Range(60, 66)) v.push_back(c);
  for (int c : Range(70, 84)) v.push_back(c);
  v.push_back(253);
  return v;
}

bool IsUnknownText(const std::string& text) {
  return text.rfind("unknown ", 0) == 0;
}

}  // namespace

TEST_CASE("every GRBL 1.1 and grblHAL error code has its text", "[gcode][messages]") {
  for (const std::vector<int>& codes : {Grbl11ErrorCodes(), GrblHalErrorCodes()}) {
    for (int code : codes) {
      INFO("error " << code);
      const std::string text = gs360::GrblErrorText(code);
      CHECK_FALSE(text.empty());
      CHECK_FALSE(IsUnknownText(text));
    }
  }
}

TEST_CASE("every GRBL 1.1 and grblHAL alarm code has its text", "[gcode][messages]") {
  for (int code : Range(1, 18)) {  // GRBL 1.1: 1-10; grblHAL: 1-18
    INFO("alarm " << code);
    const std::string text = gs360::GrblAlarmText(code);
    CHECK_FALSE(text.empty());
    CHECK_FALSE(IsUnknownText(text));
  }
}

TEST_CASE("error and alarm texts are the sources' wording", "[gcode][messages]") {
  using gs360::GrblAlarmText;
  using gs360::GrblErrorText;
  // gnea/grbl doc/csv/error_codes_en_US.csv
  CHECK(GrblErrorText(1) == "G-code words consist of a letter and a value. Letter was not found.");
  CHECK(GrblErrorText(20) == "Unsupported or invalid g-code command found in block.");
  CHECK(GrblErrorText(38) == "Tool number greater than max supported value.");
  // grblHAL/core errors.c
  CHECK(GrblErrorText(46) == "Home machine to continue.");
  CHECK(GrblErrorText(45) == "Only homing is allowed when a limit switch is engaged.");
  CHECK(GrblErrorText(50) == "Emergency stop active.");
  CHECK(GrblErrorText(253) == "User defined error occured.");  // sic
  // gnea/grbl doc/csv/alarm_codes_en_US.csv
  CHECK(GrblAlarmText(1) ==
        "Hard limit has been triggered. Machine position is likely lost due to sudden halt. "
        "Re-homing is highly recommended.");
  // grblHAL/core alarms.c
  CHECK(GrblAlarmText(11) == "Homing required. Execute homing command ($H) to continue.");
  CHECK(GrblAlarmText(18) == "Homing fail. Bad configuration.");
  // Alarm 10 conflicts (grblHAL: "EStop asserted. Clear and reset"): GRBL 1.1's text is kept.
  CHECK(GrblAlarmText(10).rfind("Homing fail. Second dual axis limit switch", 0) == 0);
}

TEST_CASE("unknown error and alarm codes name the number", "[gcode][messages]") {
  for (int code : {0, 200, -1, 59, 85, 254}) {
    INFO("code " << code);
    const std::string n = std::to_string(code);
    CHECK(gs360::GrblErrorText(code) ==
          "unknown error " + n + " (not in the GRBL 1.1 or grblHAL tables)");
  }
  for (int code : {0, 200, -1, 19}) {
    INFO("code " << code);
    const std::string n = std::to_string(code);
    CHECK(gs360::GrblAlarmText(code) ==
          "unknown alarm " + n + " (not in the GRBL 1.1 or grblHAL tables)");
  }
}

TEST_CASE("grblHAL error 46 and alarm 11 lines parse to their real text", "[gcode][messages]") {
  const GrblMessage e = ParseGrblLine("error:46");
  CHECK(e.kind == GrblMessageKind::kError);
  CHECK(e.code == 46);
  CHECK(e.text == "Home machine to continue.");

  const GrblMessage a = ParseGrblLine("ALARM:11\r");
  CHECK(a.kind == GrblMessageKind::kAlarm);
  CHECK(a.code == 11);
  CHECK(a.text == "Homing required. Execute homing command ($H) to continue.");

  const GrblMessage unknown = ParseGrblLine("error:200");
  CHECK(unknown.kind == GrblMessageKind::kError);
  CHECK(unknown.text == "unknown error 200 (not in the GRBL 1.1 or grblHAL tables)");
}

TEST_CASE("alarms that lose the machine position", "[gcode][messages]") {
  // GRBL 1.1's texts: 1 and 3 say "Machine position is likely lost"; 2 says "retained".
  CHECK(gs360::GrblAlarmLosesPosition(1));
  CHECK(gs360::GrblAlarmLosesPosition(3));
  CHECK_FALSE(gs360::GrblAlarmLosesPosition(2));
  // Probe fails stop without a sudden halt.
  CHECK_FALSE(gs360::GrblAlarmLosesPosition(4));
  CHECK_FALSE(gs360::GrblAlarmLosesPosition(5));
  // Homing failures (GRBL 6-10, grblHAL 15 and 18), grblHAL E-stop (10), homing required (11),
  // limit engaged, probe protection, spindle, self test, motor fault: re-home.
  for (int code : {6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18}) {
    INFO("alarm " << code);
    CHECK(gs360::GrblAlarmLosesPosition(code));
  }
  // An alarm we do not know: assume the worst.
  CHECK(gs360::GrblAlarmLosesPosition(200));
}
