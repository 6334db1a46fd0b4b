#include "sim/grbl_gcode.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <sstream>

#include "sim/grbl_settings.h"

namespace gs360 {
namespace {

constexpr double kMmPerInch = 25.4;
constexpr int kMaxIntDigits = 8;             // GRBL read_float()
constexpr double kMaxLineNumber = 10000000;  // GRBL MAX_LINE_NUMBER
constexpr int kNCoordinateSystem = 6;

// Value words.
enum : unsigned {
  kWordF = 1u << 0,
  kWordI = 1u << 1,
  kWordJ = 1u << 2,
  kWordK = 1u << 3,
  kWordL = 1u << 4,
  kWordN = 1u << 5,
  kWordP = 1u << 6,
  kWordR = 1u << 7,
  kWordS = 1u << 8,
  kWordT = 1u << 9,
  kWordX = 1u << 10,
  kWordY = 1u << 11,
  kWordZ = 1u << 12,
};

// Modal groups (command words).
enum : unsigned {
  kGroupG0 = 1u << 0,    // non-modal
  kGroupG1 = 1u << 1,    // motion
  kGroupG2 = 1u << 2,    // plane
  kGroupG3 = 1u << 3,    // distance
  kGroupG4 = 1u << 4,    // arc IJK distance
  kGroupG5 = 1u << 5,    // feed rate mode
  kGroupG6 = 1u << 6,    // units
  kGroupG7 = 1u << 7,    // cutter compensation
  kGroupG8 = 1u << 8,    // tool length offset
  kGroupG12 = 1u << 9,   // coordinate system
  kGroupG13 = 1u << 10,  // path control
  kGroupM4 = 1u << 11,   // program flow
  kGroupM7 = 1u << 12,   // spindle
  kGroupM8 = 1u << 13,   // coolant
};

bool SamePosition(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return a[0] == b[0] && a[1] == b[1] && a[2] == b[2];
}

}  // namespace

Eigen::Vector3d GcodeState::Wco() const {
  Eigen::Vector3d wco = coord_system + coord_offset;
  wco[2] += tool_length_offset;
  return wco;
}

bool ReadGrblFloat(std::string_view line, std::size_t& pos, double& value) {
  std::size_t p = pos;
  bool negative = false;
  if (p < line.size() && line[p] == '-') {
    negative = true;
    ++p;
  } else if (p < line.size() && line[p] == '+') {
    ++p;
  }
  std::uint32_t intval = 0;
  int exp = 0;
  int ndigit = 0;
  bool decimal = false;
  while (p < line.size()) {
    const char c = line[p];
    if (c >= '0' && c <= '9') {
      ++ndigit;
      if (ndigit <= kMaxIntDigits) {
        if (decimal) --exp;
        intval = intval * 10u + static_cast<std::uint32_t>(c - '0');
      } else if (!decimal) {
        ++exp;  // drop overflow digits
      }
    } else if (c == '.' && !decimal) {
      decimal = true;
    } else {
      break;
    }
    ++p;
  }
  if (ndigit == 0) return false;
  double v = static_cast<double>(intval);
  if (exp < 0) {
    v /= std::pow(10.0, -exp);
  } else if (exp > 0) {
    v *= std::pow(10.0, exp);
  }
  value = negative ? -v : v;
  pos = p;
  return true;
}

namespace {

// GRBL's gc_execute_line, steps 2 and 3, for one line: the block being built (gc_block) and what
// the words seen so far set. Parse() runs the steps in GRBL's order; every step returns a
// GrblStatus, and the first error ends the parse.
class LineParser {
 public:
  LineParser(const GcodeState& gc, const CoordinateData& coords) : gc_(gc), coords_(coords) {
    blk_.modal = gc.modal;
  }

  int Parse(std::string_view line, GcodeBlock* out) {
    std::size_t pos = 0;
    if (!line.empty() && line[0] == '$') {  // "$J=" jog: G1 G94 enforced
      blk_.jog = true;
      blk_.modal.motion = kMotionLinear;
      blk_.modal.inverse_time = false;
      pos = 3;
    }
    if (const int status = ImportWords(line, pos); status != kGrblOk) return status;
    if (const int status = CheckRatesAndDwell(); status != kGrblOk) return status;
    if (const int status = CheckModesAndOffsets(); status != kGrblOk) return status;
    if (const int status = CheckNonModal(); status != kGrblOk) return status;
    if (const int status = CheckMotion(); status != kGrblOk) return status;
    if (const int status = CheckUnusedWords(); status != kGrblOk) return status;
    Write(out);
    return kGrblOk;
  }

 private:
  // STEP 2: import the words.
  int ImportWords(std::string_view line, std::size_t pos);
  int ImportGWord(int int_value, int mantissa);
  int ImportNonModalGWord(int int_value, int* mantissa);
  int ImportMotionGWord(int int_value, int* mantissa);
  int ImportModalGWord(int int_value, int* mantissa, unsigned* word_bit);
  int ImportMWord(int int_value, int mantissa);
  int ImportValueWord(char letter, double value, int int_value);
  // STEP 3: error-check, in the order of GRBL's numbered checks.
  int CheckRatesAndDwell();    // [0.] line number, [2-3.] feed rate, [4.] spindle, [10.] dwell
  int CheckModesAndOffsets();  // [11.] plane, [12.] units, [14.] tool length, [15.] coordinates
  int CheckNonModal();         // [19.] non-modal actions
  int SetCoordinateData();     // [19.] G10
  int SetTarget();             // [19.] motion targets, G28 / G30, G53
  int CheckMotion();           // [20.] motion modes
  int CheckArc();              // [20.] G2 / G3
  int CheckUnusedWords();      // [0.] unused words, and the jog's limits
  void Write(GcodeBlock* out) const;

  const GcodeState& gc_;
  const CoordinateData& coords_;
  GcodeBlock blk_;
  int axis_command_ = kAxisCommandNone;
  unsigned axis_words_ = 0, ijk_words_ = 0, command_words_ = 0, value_words_ = 0;
  struct {  // GRBL gc_values_t
    double f = 0, p = 0, r = 0, s = 0, n = 0;
    int l = 0, t = 0;
    Eigen::Vector3d xyz = Eigen::Vector3d::Zero();
    Eigen::Vector3d ijk = Eigen::Vector3d::Zero();
  } v_;
};

int LineParser::ImportWords(std::string_view line, std::size_t pos) {
  while (pos < line.size()) {
    const char letter = line[pos];
    if (letter < 'A' || letter > 'Z') return kGrblExpectedCommandLetter;
    ++pos;
    double value = 0.0;
    if (!ReadGrblFloat(line, pos, value)) return kGrblBadNumberFormat;
    // GRBL: uint8_t int_value = trunc(value); uint16_t mantissa = round(100*(value - int_value)),
    // both keeping the low bits. A value past a long's range cannot be cast (undefined, found by
    // tests/fuzz): such doubles are multiples of 2^11, whose low byte is 0 anyway.
    constexpr double kLongRange = 9.0e18;
    const double whole = std::trunc(value);
    const int int_value =
        std::abs(whole) < kLongRange
            ? static_cast<int>(static_cast<std::uint8_t>(static_cast<long>(whole) & 0xFF))
            : 0;
    const double hundredths = std::round(100.0 * (value - int_value));
    const int mantissa =
        std::abs(hundredths) < kLongRange
            ? static_cast<int>(static_cast<std::uint16_t>(static_cast<long>(hundredths) & 0xFFFF))
            : 0;
    int status;
    switch (letter) {
      case 'G':
        status = ImportGWord(int_value, mantissa);
        break;
      case 'M':
        status = ImportMWord(int_value, mantissa);
        break;
      default:
        status = ImportValueWord(letter, value, int_value);
        break;
    }
    if (status != kGrblOk) return status;
  }
  return kGrblOk;
}

int LineParser::ImportGWord(int int_value, int mantissa) {
  unsigned word_bit = 0;
  int status;
  switch (int_value) {
    case 4:
    case 10:
    case 28:
    case 30:
    case 53:
    case 92:
      word_bit = kGroupG0;
      status = ImportNonModalGWord(int_value, &mantissa);
      break;
    case 0:
    case 1:
    case 2:
    case 3:
    case 38:
    case 80:
      word_bit = kGroupG1;
      status = ImportMotionGWord(int_value, &mantissa);
      break;
    default:
      status = ImportModalGWord(int_value, &mantissa, &word_bit);
      break;
  }
  if (status != kGrblOk) return status;
  if (mantissa > 0) return kGrblGcodeCommandValueNotInteger;
  if (command_words_ & word_bit) return kGrblGcodeModalGroupViolation;
  command_words_ |= word_bit;
  return kGrblOk;
}

// Group 0: G4, G10, G28, G30, G53, G92 (and G28.1, G30.1, G92.1).
int LineParser::ImportNonModalGWord(int int_value, int* mantissa) {
  if (int_value != 4 && int_value != 53 && *mantissa == 0) {
    if (axis_command_) return kGrblGcodeAxisCommandConflict;
    axis_command_ = kAxisCommandNonModal;
  }
  blk_.non_modal = int_value;
  if (int_value == 28 || int_value == 30 || int_value == 92) {
    if (!(*mantissa == 0 || *mantissa == 10)) return kGrblGcodeUnsupportedCommand;
    blk_.non_modal += *mantissa;
    *mantissa = 0;
  }
  return kGrblOk;
}

// Group 1: G0, G1, G2, G3, G38.2-G38.5, G80.
int LineParser::ImportMotionGWord(int int_value, int* mantissa) {
  if (int_value != 80) {
    if (axis_command_) return kGrblGcodeAxisCommandConflict;
    axis_command_ = kAxisCommandMotionMode;
  }
  blk_.modal.motion = int_value;
  if (int_value == 38) {
    if (!(*mantissa == 20 || *mantissa == 30 || *mantissa == 40 || *mantissa == 50)) {
      return kGrblGcodeUnsupportedCommand;
    }
    blk_.modal.motion += *mantissa / 10 + 100;
    *mantissa = 0;
  }
  return kGrblOk;
}

// The other modal groups: plane, distance, feed rate mode, units, cutter compensation, tool
// length offset, coordinate system, path control.
int LineParser::ImportModalGWord(int int_value, int* mantissa, unsigned* word_bit) {
  switch (int_value) {
    case 17:
    case 18:
    case 19:
      *word_bit = kGroupG2;
      blk_.modal.plane = int_value - 17;
      break;
    case 90:
    case 91:
      if (*mantissa == 0) {
        *word_bit = kGroupG3;
        blk_.modal.incremental = int_value == 91;
      } else {
        *word_bit = kGroupG4;
        if (*mantissa != 10 || int_value == 90) return kGrblGcodeUnsupportedCommand;
        *mantissa = 0;  // G91.1: arc IJK incremental, the default; does nothing
      }
      break;
    case 93:
    case 94:
      *word_bit = kGroupG5;
      blk_.modal.inverse_time = int_value == 93;
      break;
    case 20:
    case 21:
      *word_bit = kGroupG6;
      blk_.modal.inches = int_value == 20;
      break;
    case 40:
      *word_bit = kGroupG7;
      break;
    case 43:
    case 49:
      *word_bit = kGroupG8;
      if (axis_command_) return kGrblGcodeAxisCommandConflict;
      axis_command_ = kAxisCommandToolLengthOffset;
      if (int_value == 49) {
        blk_.modal.tool_length_dynamic = false;
      } else if (*mantissa == 10) {
        blk_.modal.tool_length_dynamic = true;
      } else {
        return kGrblGcodeUnsupportedCommand;
      }
      *mantissa = 0;
      break;
    case 54:
    case 55:
    case 56:
    case 57:
    case 58:
    case 59:
      *word_bit = kGroupG12;
      blk_.modal.coord_select = int_value - 54;
      break;
    case 61:
      *word_bit = kGroupG13;
      if (*mantissa != 0) return kGrblGcodeUnsupportedCommand;
      break;
    default:
      return kGrblGcodeUnsupportedCommand;
  }
  return kGrblOk;
}

int LineParser::ImportMWord(int int_value, int mantissa) {
  if (mantissa > 0) return kGrblGcodeCommandValueNotInteger;
  unsigned word_bit = 0;
  switch (int_value) {
    case 0:
    case 1:
    case 2:
    case 30:
      word_bit = kGroupM4;
      if (int_value == 0) {
        blk_.modal.program_flow = 3;  // PROGRAM_FLOW_PAUSED
      } else if (int_value != 1) {    // M1 optional stop: ignored
        blk_.modal.program_flow = int_value;
      }
      break;
    case 3:
    case 4:
    case 5:
      word_bit = kGroupM7;
      blk_.modal.spindle = int_value == 3 ? 1 : (int_value == 4 ? 2 : 0);
      break;
    case 8:
    case 9:
      word_bit = kGroupM8;
      if (int_value == 8) {
        blk_.modal.coolant |= 1;
      } else {
        blk_.modal.coolant = 0;
      }
      break;
    default:
      return kGrblGcodeUnsupportedCommand;
  }
  if (command_words_ & word_bit) return kGrblGcodeModalGroupViolation;
  command_words_ |= word_bit;
  return kGrblOk;
}

int LineParser::ImportValueWord(char letter, double value, int int_value) {
  unsigned word_bit = 0;
  switch (letter) {
    case 'F':
      word_bit = kWordF;
      v_.f = value;
      break;
    case 'I':
      word_bit = kWordI;
      v_.ijk[0] = value;
      ijk_words_ |= 1u;
      break;
    case 'J':
      word_bit = kWordJ;
      v_.ijk[1] = value;
      ijk_words_ |= 2u;
      break;
    case 'K':
      word_bit = kWordK;
      v_.ijk[2] = value;
      ijk_words_ |= 4u;
      break;
    case 'L':
      word_bit = kWordL;
      v_.l = int_value;
      break;
    case 'N':
      word_bit = kWordN;
      v_.n = std::trunc(value);
      break;
    case 'P':
      word_bit = kWordP;
      v_.p = value;
      break;
    case 'R':
      word_bit = kWordR;
      v_.r = value;
      break;
    case 'S':
      word_bit = kWordS;
      v_.s = value;
      break;
    case 'T':
      word_bit = kWordT;
      if (value > 255) return kGrblGcodeMaxValueExceeded;
      v_.t = int_value;
      break;
    case 'X':
      word_bit = kWordX;
      v_.xyz[0] = value;
      axis_words_ |= 1u;
      break;
    case 'Y':
      word_bit = kWordY;
      v_.xyz[1] = value;
      axis_words_ |= 2u;
      break;
    case 'Z':
      word_bit = kWordZ;
      v_.xyz[2] = value;
      axis_words_ |= 4u;
      break;
    default:
      return kGrblGcodeUnsupportedCommand;
  }
  if (value_words_ & word_bit) return kGrblGcodeWordRepeated;
  if ((word_bit & (kWordF | kWordN | kWordP | kWordT | kWordS)) && value < 0.0) {
    return kGrblNegativeValue;
  }
  value_words_ |= word_bit;
  return kGrblOk;
}

int LineParser::CheckRatesAndDwell() {
  if (axis_words_ && !axis_command_) axis_command_ = kAxisCommandMotionMode;
  if ((value_words_ & kWordN) && v_.n > kMaxLineNumber) return kGrblGcodeInvalidLineNumber;

  // [2-3. Feed rate mode and feed rate]
  if (blk_.jog) {
    if (!(value_words_ & kWordF)) return kGrblGcodeUndefinedFeedRate;
    if (blk_.modal.inches) v_.f *= kMmPerInch;
  } else if (blk_.modal.inverse_time) {
    if (axis_command_ == kAxisCommandMotionMode && blk_.modal.motion != kMotionNone &&
        blk_.modal.motion != kMotionSeek && !(value_words_ & kWordF)) {
      return kGrblGcodeUndefinedFeedRate;
    }
  } else if (!gc_.modal.inverse_time) {
    if (value_words_ & kWordF) {
      if (blk_.modal.inches) v_.f *= kMmPerInch;
    } else {
      v_.f = gc_.feed_rate;
    }
  }
  // [4. Spindle speed]
  if (!(value_words_ & kWordS)) v_.s = gc_.spindle_speed;
  // [10. Dwell]
  if (blk_.non_modal == kNonModalDwell) {
    if (!(value_words_ & kWordP)) return kGrblGcodeValueWordMissing;
    value_words_ &= ~kWordP;
  }
  return kGrblOk;
}

int LineParser::CheckModesAndOffsets() {
  // [11. Plane]
  switch (blk_.modal.plane) {
    case 0:
      blk_.axis_0 = 0;
      blk_.axis_1 = 1;
      blk_.axis_linear = 2;
      break;
    case 1:
      blk_.axis_0 = 2;
      blk_.axis_1 = 0;
      blk_.axis_linear = 1;
      break;
    default:
      blk_.axis_0 = 1;
      blk_.axis_1 = 2;
      blk_.axis_linear = 0;
      break;
  }
  // [12. Units]
  if (blk_.modal.inches) {
    for (int i = 0; i < 3; ++i) {
      if (axis_words_ & (1u << i)) v_.xyz[i] *= kMmPerInch;
    }
  }
  // [14. Tool length offset]
  if (axis_command_ == kAxisCommandToolLengthOffset && blk_.modal.tool_length_dynamic) {
    if (axis_words_ ^ (1u << 2)) return kGrblGcodeG43DynamicAxisError;
  }
  // [15. Coordinate system]
  blk_.block_coord_system = gc_.coord_system;
  if (command_words_ & kGroupG12) {
    if (blk_.modal.coord_select > kNCoordinateSystem) return kGrblGcodeUnsupportedCoordSys;
    if (gc_.modal.coord_select != blk_.modal.coord_select) {
      blk_.block_coord_system = coords_.wcs[static_cast<std::size_t>(blk_.modal.coord_select)];
    }
  }
  return kGrblOk;
}

int LineParser::CheckNonModal() {
  switch (blk_.non_modal) {
    case kNonModalSetCoordinateData:
      return SetCoordinateData();
    case kNonModalSetCoordinateOffset:
      if (!axis_words_) return kGrblGcodeNoAxisWords;
      for (int i = 0; i < 3; ++i) {
        if (axis_words_ & (1u << i)) {
          v_.xyz[i] = gc_.position[i] - blk_.block_coord_system[i] - v_.xyz[i];
          if (i == 2) v_.xyz[i] -= gc_.tool_length_offset;
        } else {
          v_.xyz[i] = gc_.coord_offset[i];
        }
      }
      return kGrblOk;
    default:
      return SetTarget();
  }
}

int LineParser::SetCoordinateData() {
  if (!axis_words_) return kGrblGcodeNoAxisWords;
  if (!(value_words_ & (kWordP | kWordL))) return kGrblGcodeValueWordMissing;
  // Compared as a double first: a P past int's range cannot be cast (found by tests/fuzz).
  if (!(std::trunc(v_.p) <= kNCoordinateSystem)) return kGrblGcodeUnsupportedCoordSys;
  int coord_select = static_cast<int>(std::trunc(v_.p));
  if (v_.l != 20) {
    if (v_.l == 2) {
      if (value_words_ & kWordR) return kGrblGcodeUnsupportedCommand;
    } else {
      return kGrblGcodeUnsupportedCommand;
    }
  }
  value_words_ &= ~(kWordL | kWordP);
  coord_select = coord_select > 0 ? coord_select - 1 : blk_.modal.coord_select;
  v_.ijk = coords_.wcs[static_cast<std::size_t>(coord_select)];
  for (int i = 0; i < 3; ++i) {
    if (!(axis_words_ & (1u << i))) continue;
    if (v_.l == 20) {
      v_.ijk[i] = gc_.position[i] - gc_.coord_offset[i] - v_.xyz[i];
      if (i == 2) v_.ijk[i] -= gc_.tool_length_offset;
    } else {
      v_.ijk[i] = v_.xyz[i];
    }
  }
  blk_.coord_data_index = coord_select;
  return kGrblOk;
}

int LineParser::SetTarget() {
  if (axis_command_ != kAxisCommandToolLengthOffset && axis_words_) {
    for (int i = 0; i < 3; ++i) {
      if (!(axis_words_ & (1u << i))) {
        v_.xyz[i] = gc_.position[i];
      } else if (blk_.non_modal != kNonModalAbsoluteOverride) {
        if (!blk_.modal.incremental) {
          v_.xyz[i] += blk_.block_coord_system[i] + gc_.coord_offset[i];
          if (i == 2) v_.xyz[i] += gc_.tool_length_offset;
        } else {
          v_.xyz[i] += gc_.position[i];
        }
      }
    }
  }
  switch (blk_.non_modal) {
    case kNonModalGoHome0:
    case kNonModalGoHome1:
      v_.ijk = blk_.non_modal == kNonModalGoHome0 ? coords_.g28 : coords_.g30;
      if (axis_words_) {
        for (int i = 0; i < 3; ++i) {
          if (!(axis_words_ & (1u << i))) v_.ijk[i] = gc_.position[i];
        }
      } else {
        axis_command_ = kAxisCommandNone;
      }
      break;
    case kNonModalAbsoluteOverride:
      if (!(blk_.modal.motion == kMotionSeek || blk_.modal.motion == kMotionLinear)) {
        return kGrblGcodeG53InvalidMotionMode;
      }
      break;
    default:
      break;
  }
  return kGrblOk;
}

int LineParser::CheckMotion() {
  if (blk_.modal.motion == kMotionNone) {
    if (axis_words_) return kGrblGcodeAxisWordsExist;
    return kGrblOk;
  }
  if (axis_command_ != kAxisCommandMotionMode) return kGrblOk;
  if (blk_.modal.motion == kMotionSeek) {
    if (!axis_words_) axis_command_ = kAxisCommandNone;
    return kGrblOk;
  }
  if (v_.f == 0.0) return kGrblGcodeUndefinedFeedRate;
  switch (blk_.modal.motion) {
    case kMotionLinear:
      if (!axis_words_) axis_command_ = kAxisCommandNone;
      break;
    case kMotionCwArc:
    case kMotionCcwArc:
      return CheckArc();
    case kMotionProbeToward:
    case kMotionProbeTowardNoError:
    case kMotionProbeAway:
    case kMotionProbeAwayNoError:
      if (!axis_words_) return kGrblGcodeNoAxisWords;
      if (SamePosition(gc_.position, v_.xyz)) return kGrblGcodeInvalidTarget;
      break;
    default:
      break;
  }
  return kGrblOk;
}

int LineParser::CheckArc() {
  blk_.arc_clockwise = blk_.modal.motion == kMotionCwArc;
  const int a0 = blk_.axis_0, a1 = blk_.axis_1;
  if (!axis_words_) return kGrblGcodeNoAxisWords;
  if (!(axis_words_ & ((1u << a0) | (1u << a1)))) return kGrblGcodeNoAxisWordsInPlane;
  double x = v_.xyz[a0] - gc_.position[a0];
  double y = v_.xyz[a1] - gc_.position[a1];
  if (value_words_ & kWordR) {  // radius mode
    value_words_ &= ~kWordR;
    if (SamePosition(gc_.position, v_.xyz)) return kGrblGcodeInvalidTarget;
    if (blk_.modal.inches) v_.r *= kMmPerInch;
    double h_x2_div_d = 4.0 * v_.r * v_.r - x * x - y * y;
    if (h_x2_div_d < 0) return kGrblGcodeArcRadiusError;
    h_x2_div_d = -std::sqrt(h_x2_div_d) / std::hypot(x, y);
    if (blk_.modal.motion == kMotionCcwArc) h_x2_div_d = -h_x2_div_d;
    if (v_.r < 0) {
      h_x2_div_d = -h_x2_div_d;
      v_.r = -v_.r;
    }
    v_.ijk[a0] = 0.5 * (x - (y * h_x2_div_d));
    v_.ijk[a1] = 0.5 * (y + (x * h_x2_div_d));
    return kGrblOk;
  }
  // Centre offset mode.
  if (!(ijk_words_ & ((1u << a0) | (1u << a1)))) return kGrblGcodeNoOffsetsInPlane;
  value_words_ &= ~(kWordI | kWordJ | kWordK);
  if (blk_.modal.inches) {
    for (int i = 0; i < 3; ++i) {
      if (ijk_words_ & (1u << i)) v_.ijk[i] *= kMmPerInch;
    }
  }
  x -= v_.ijk[a0];
  y -= v_.ijk[a1];
  const double target_r = std::hypot(x, y);
  v_.r = std::hypot(v_.ijk[a0], v_.ijk[a1]);
  const double delta_r = std::abs(target_r - v_.r);
  if (delta_r > 0.005) {
    if (delta_r > 0.5) return kGrblGcodeInvalidTarget;
    if (delta_r > 0.001 * v_.r) return kGrblGcodeInvalidTarget;
  }
  return kGrblOk;
}

int LineParser::CheckUnusedWords() {
  if (blk_.jog) {
    value_words_ &= ~(kWordN | kWordF);
  } else {
    value_words_ &= ~(kWordN | kWordF | kWordS | kWordT);
  }
  if (axis_command_) value_words_ &= ~(kWordX | kWordY | kWordZ);
  if (value_words_) return kGrblGcodeUnusedWords;

  if (blk_.jog) {
    if (command_words_ & ~(kGroupG3 | kGroupG6 | kGroupG0)) return kGrblInvalidJogCommand;
    if (!(blk_.non_modal == kNonModalAbsoluteOverride || blk_.non_modal == kNonModalNone)) {
      return kGrblInvalidJogCommand;
    }
  }
  return kGrblOk;
}

void LineParser::Write(GcodeBlock* out) const {
  GcodeBlock blk = blk_;
  blk.axis_command = axis_command_;
  blk.axis_words = axis_words_;
  blk.feed_rate = v_.f;
  blk.spindle_speed = v_.s;
  blk.tool = v_.t;  // GRBL: gc_state.tool = gc_block.values.t (0 when no T word)
  blk.line_number = static_cast<int>(v_.n);
  blk.dwell_s = v_.p;
  blk.xyz = v_.xyz;
  blk.ijk = v_.ijk;
  blk.radius = v_.r;
  *out = blk;
}

}  // namespace

int ParseGcodeLine(std::string_view line, const GcodeState& gc, const CoordinateData& coords,
                   GcodeBlock* out) {
  return LineParser(gc, coords).Parse(line, out);
}

std::string FormatParserState(const GcodeState& gc, bool report_inches) {
  std::ostringstream os;
  os << "[GC:G";
  if (gc.modal.motion >= kMotionProbeToward) {
    os << "38." << (gc.modal.motion - (kMotionProbeToward - 2));
  } else {
    os << gc.modal.motion;
  }
  os << " G" << gc.modal.coord_select + 54;
  os << " G" << gc.modal.plane + 17;
  os << " G" << (gc.modal.inches ? 20 : 21);
  os << " G" << (gc.modal.incremental ? 91 : 90);
  os << " G" << (gc.modal.inverse_time ? 93 : 94);
  if (gc.modal.program_flow) {
    os << " M" << (gc.modal.program_flow == 3 ? 0 : gc.modal.program_flow);
  }
  os << " M" << (gc.modal.spindle == 1 ? 3 : (gc.modal.spindle == 2 ? 4 : 5));
  os << " M" << ((gc.modal.coolant & 1) ? 8 : 9);
  os << " T" << gc.tool;
  os << " F"
     << (report_inches ? FormatGrblFloat(gc.feed_rate / kMmPerInch, 1)
                       : FormatGrblFloat(gc.feed_rate, 0));
  os << " S" << FormatGrblFloat(gc.spindle_speed, 0);
  os << "]";
  return os.str();
}

std::vector<Eigen::Vector3d> ArcSegmentTargets(const Eigen::Vector3d& position_in,
                                               const Eigen::Vector3d& target,
                                               const Eigen::Vector3d& offset, double radius,
                                               int axis_0, int axis_1, int axis_linear,
                                               bool clockwise, double arc_tolerance_mm) {
  constexpr double kArcAngularTravelEpsilon = 5e-7;
  Eigen::Vector3d position = position_in;
  const double center_axis0 = position[axis_0] + offset[axis_0];
  const double center_axis1 = position[axis_1] + offset[axis_1];
  const double r_axis0 = -offset[axis_0];
  const double r_axis1 = -offset[axis_1];
  const double rt_axis0 = target[axis_0] - center_axis0;
  const double rt_axis1 = target[axis_1] - center_axis1;
  double angular_travel =
      std::atan2(r_axis0 * rt_axis1 - r_axis1 * rt_axis0, r_axis0 * rt_axis0 + r_axis1 * rt_axis1);
  if (clockwise) {
    if (angular_travel >= -kArcAngularTravelEpsilon) angular_travel -= 2 * M_PI;
  } else {
    if (angular_travel <= kArcAngularTravelEpsilon) angular_travel += 2 * M_PI;
  }
  const double chord = std::sqrt(arc_tolerance_mm * (2 * radius - arc_tolerance_mm));
  // GRBL counts segments in a uint16_t; more than that many from an absurd radius would be an
  // undefined cast here, and a useless allocation.
  constexpr double kMaxSegments = 65535.0;
  const double count = chord > 0 ? std::floor(std::abs(0.5 * angular_travel * radius) / chord) : 0;
  const int segments = static_cast<int>(std::min(count, kMaxSegments));
  std::vector<Eigen::Vector3d> out;
  if (segments > 0) {
    const double theta_per_segment = angular_travel / segments;
    const double linear_per_segment = (target[axis_linear] - position[axis_linear]) / segments;
    out.reserve(static_cast<std::size_t>(segments));
    for (int i = 1; i < segments; ++i) {
      const double c = std::cos(i * theta_per_segment);
      const double s = std::sin(i * theta_per_segment);
      position[axis_0] = center_axis0 + (r_axis0 * c - r_axis1 * s);
      position[axis_1] = center_axis1 + (r_axis0 * s + r_axis1 * c);
      position[axis_linear] += linear_per_segment;
      out.push_back(position);
    }
  }
  out.push_back(target);
  return out;
}

}  // namespace gs360
