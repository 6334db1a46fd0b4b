#include "sim/grbl_gcode.h"

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

int ParseGcodeLine(std::string_view line, const GcodeState& gc, const CoordinateData& coords,
                   GcodeBlock* out) {
  GcodeBlock blk;
  blk.modal = gc.modal;
  int axis_command = kAxisCommandNone;
  unsigned axis_words = 0, ijk_words = 0, command_words = 0, value_words = 0;
  struct {
    double f = 0, p = 0, r = 0, s = 0, n = 0;
    int l = 0, t = 0;
    Eigen::Vector3d xyz = Eigen::Vector3d::Zero();
    Eigen::Vector3d ijk = Eigen::Vector3d::Zero();
  } v;

  std::size_t pos = 0;
  if (!line.empty() && line[0] == '$') {  // "$J=" jog: G1 G94 enforced
    blk.jog = true;
    blk.modal.motion = kMotionLinear;
    blk.modal.inverse_time = false;
    pos = 3;
  }

  // STEP 2: import the words.
  while (pos < line.size()) {
    const char letter = line[pos];
    if (letter < 'A' || letter > 'Z') return kGrblExpectedCommandLetter;
    ++pos;
    double value = 0.0;
    if (!ReadGrblFloat(line, pos, value)) return kGrblBadNumberFormat;
    // GRBL: uint8_t int_value = trunc(value); uint16_t mantissa = round(100*(value - int_value)).
    const int int_value =
        static_cast<int>(static_cast<std::uint8_t>(static_cast<long>(std::trunc(value)) & 0xFF));
    int mantissa = static_cast<int>(static_cast<std::uint16_t>(
        static_cast<long>(std::lround(100.0 * (value - int_value))) & 0xFFFF));

    switch (letter) {
      case 'G': {
        unsigned word_bit = 0;
        switch (int_value) {
          case 10:
          case 28:
          case 30:
          case 92:
            if (mantissa == 0) {
              if (axis_command) return kGrblGcodeAxisCommandConflict;
              axis_command = kAxisCommandNonModal;
            }
            [[fallthrough]];
          case 4:
          case 53:
            word_bit = kGroupG0;
            blk.non_modal = int_value;
            if (int_value == 28 || int_value == 30 || int_value == 92) {
              if (!(mantissa == 0 || mantissa == 10)) return kGrblGcodeUnsupportedCommand;
              blk.non_modal += mantissa;
              mantissa = 0;
            }
            break;
          case 0:
          case 1:
          case 2:
          case 3:
          case 38:
            if (axis_command) return kGrblGcodeAxisCommandConflict;
            axis_command = kAxisCommandMotionMode;
            [[fallthrough]];
          case 80:
            word_bit = kGroupG1;
            blk.modal.motion = int_value;
            if (int_value == 38) {
              if (!(mantissa == 20 || mantissa == 30 || mantissa == 40 || mantissa == 50)) {
                return kGrblGcodeUnsupportedCommand;
              }
              blk.modal.motion += mantissa / 10 + 100;
              mantissa = 0;
            }
            break;
          case 17:
          case 18:
          case 19:
            word_bit = kGroupG2;
            blk.modal.plane = int_value - 17;
            break;
          case 90:
          case 91:
            if (mantissa == 0) {
              word_bit = kGroupG3;
              blk.modal.incremental = int_value == 91;
            } else {
              word_bit = kGroupG4;
              if (mantissa != 10 || int_value == 90) return kGrblGcodeUnsupportedCommand;
              mantissa = 0;  // G91.1: arc IJK incremental, the default; does nothing
            }
            break;
          case 93:
          case 94:
            word_bit = kGroupG5;
            blk.modal.inverse_time = int_value == 93;
            break;
          case 20:
          case 21:
            word_bit = kGroupG6;
            blk.modal.inches = int_value == 20;
            break;
          case 40:
            word_bit = kGroupG7;
            break;
          case 43:
          case 49:
            word_bit = kGroupG8;
            if (axis_command) return kGrblGcodeAxisCommandConflict;
            axis_command = kAxisCommandToolLengthOffset;
            if (int_value == 49) {
              blk.modal.tool_length_dynamic = false;
            } else if (mantissa == 10) {
              blk.modal.tool_length_dynamic = true;
            } else {
              return kGrblGcodeUnsupportedCommand;
            }
            mantissa = 0;
            break;
          case 54:
          case 55:
          case 56:
          case 57:
          case 58:
          case 59:
            word_bit = kGroupG12;
            blk.modal.coord_select = int_value - 54;
            break;
          case 61:
            word_bit = kGroupG13;
            if (mantissa != 0) return kGrblGcodeUnsupportedCommand;
            break;
          default:
            return kGrblGcodeUnsupportedCommand;
        }
        if (mantissa > 0) return kGrblGcodeCommandValueNotInteger;
        if (command_words & word_bit) return kGrblGcodeModalGroupViolation;
        command_words |= word_bit;
        break;
      }
      case 'M': {
        if (mantissa > 0) return kGrblGcodeCommandValueNotInteger;
        unsigned word_bit = 0;
        switch (int_value) {
          case 0:
          case 1:
          case 2:
          case 30:
            word_bit = kGroupM4;
            if (int_value == 0) {
              blk.modal.program_flow = 3;  // PROGRAM_FLOW_PAUSED
            } else if (int_value != 1) {   // M1 optional stop: ignored
              blk.modal.program_flow = int_value;
            }
            break;
          case 3:
          case 4:
          case 5:
            word_bit = kGroupM7;
            blk.modal.spindle = int_value == 3 ? 1 : (int_value == 4 ? 2 : 0);
            break;
          case 8:
          case 9:
            word_bit = kGroupM8;
            if (int_value == 8) {
              blk.modal.coolant |= 1;
            } else {
              blk.modal.coolant = 0;
            }
            break;
          default:
            return kGrblGcodeUnsupportedCommand;
        }
        if (command_words & word_bit) return kGrblGcodeModalGroupViolation;
        command_words |= word_bit;
        break;
      }
      default: {
        unsigned word_bit = 0;
        switch (letter) {
          case 'F':
            word_bit = kWordF;
            v.f = value;
            break;
          case 'I':
            word_bit = kWordI;
            v.ijk[0] = value;
            ijk_words |= 1u;
            break;
          case 'J':
            word_bit = kWordJ;
            v.ijk[1] = value;
            ijk_words |= 2u;
            break;
          case 'K':
            word_bit = kWordK;
            v.ijk[2] = value;
            ijk_words |= 4u;
            break;
          case 'L':
            word_bit = kWordL;
            v.l = int_value;
            break;
          case 'N':
            word_bit = kWordN;
            v.n = std::trunc(value);
            break;
          case 'P':
            word_bit = kWordP;
            v.p = value;
            break;
          case 'R':
            word_bit = kWordR;
            v.r = value;
            break;
          case 'S':
            word_bit = kWordS;
            v.s = value;
            break;
          case 'T':
            word_bit = kWordT;
            if (value > 255) return kGrblGcodeMaxValueExceeded;
            v.t = int_value;
            break;
          case 'X':
            word_bit = kWordX;
            v.xyz[0] = value;
            axis_words |= 1u;
            break;
          case 'Y':
            word_bit = kWordY;
            v.xyz[1] = value;
            axis_words |= 2u;
            break;
          case 'Z':
            word_bit = kWordZ;
            v.xyz[2] = value;
            axis_words |= 4u;
            break;
          default:
            return kGrblGcodeUnsupportedCommand;
        }
        if (value_words & word_bit) return kGrblGcodeWordRepeated;
        if ((word_bit & (kWordF | kWordN | kWordP | kWordT | kWordS)) && value < 0.0) {
          return kGrblNegativeValue;
        }
        value_words |= word_bit;
        break;
      }
    }
  }

  // STEP 3: error-check.
  if (axis_words && !axis_command) axis_command = kAxisCommandMotionMode;
  if ((value_words & kWordN) && v.n > kMaxLineNumber) return kGrblGcodeInvalidLineNumber;

  // [2-3. Feed rate mode and feed rate]
  if (blk.jog) {
    if (!(value_words & kWordF)) return kGrblGcodeUndefinedFeedRate;
    if (blk.modal.inches) v.f *= kMmPerInch;
  } else if (blk.modal.inverse_time) {
    if (axis_command == kAxisCommandMotionMode && blk.modal.motion != kMotionNone &&
        blk.modal.motion != kMotionSeek && !(value_words & kWordF)) {
      return kGrblGcodeUndefinedFeedRate;
    }
  } else if (!gc.modal.inverse_time) {
    if (value_words & kWordF) {
      if (blk.modal.inches) v.f *= kMmPerInch;
    } else {
      v.f = gc.feed_rate;
    }
  }
  // [4. Spindle speed]
  if (!(value_words & kWordS)) v.s = gc.spindle_speed;
  // [10. Dwell]
  if (blk.non_modal == kNonModalDwell) {
    if (!(value_words & kWordP)) return kGrblGcodeValueWordMissing;
    value_words &= ~kWordP;
  }
  // [11. Plane]
  switch (blk.modal.plane) {
    case 0:
      blk.axis_0 = 0;
      blk.axis_1 = 1;
      blk.axis_linear = 2;
      break;
    case 1:
      blk.axis_0 = 2;
      blk.axis_1 = 0;
      blk.axis_linear = 1;
      break;
    default:
      blk.axis_0 = 1;
      blk.axis_1 = 2;
      blk.axis_linear = 0;
      break;
  }
  // [12. Units]
  if (blk.modal.inches) {
    for (int i = 0; i < 3; ++i) {
      if (axis_words & (1u << i)) v.xyz[i] *= kMmPerInch;
    }
  }
  // [14. Tool length offset]
  if (axis_command == kAxisCommandToolLengthOffset && blk.modal.tool_length_dynamic) {
    if (axis_words ^ (1u << 2)) return kGrblGcodeG43DynamicAxisError;
  }
  // [15. Coordinate system]
  blk.block_coord_system = gc.coord_system;
  if (command_words & kGroupG12) {
    if (blk.modal.coord_select > kNCoordinateSystem) return kGrblGcodeUnsupportedCoordSys;
    if (gc.modal.coord_select != blk.modal.coord_select) {
      blk.block_coord_system = coords.wcs[static_cast<std::size_t>(blk.modal.coord_select)];
    }
  }
  // [19. Non-modal actions]
  switch (blk.non_modal) {
    case kNonModalSetCoordinateData: {
      if (!axis_words) return kGrblGcodeNoAxisWords;
      if (!(value_words & (kWordP | kWordL))) return kGrblGcodeValueWordMissing;
      int coord_select = static_cast<int>(std::trunc(v.p));
      if (coord_select > kNCoordinateSystem) return kGrblGcodeUnsupportedCoordSys;
      if (v.l != 20) {
        if (v.l == 2) {
          if (value_words & kWordR) return kGrblGcodeUnsupportedCommand;
        } else {
          return kGrblGcodeUnsupportedCommand;
        }
      }
      value_words &= ~(kWordL | kWordP);
      coord_select = coord_select > 0 ? coord_select - 1 : blk.modal.coord_select;
      v.ijk = coords.wcs[static_cast<std::size_t>(coord_select)];
      for (int i = 0; i < 3; ++i) {
        if (!(axis_words & (1u << i))) continue;
        if (v.l == 20) {
          v.ijk[i] = gc.position[i] - gc.coord_offset[i] - v.xyz[i];
          if (i == 2) v.ijk[i] -= gc.tool_length_offset;
        } else {
          v.ijk[i] = v.xyz[i];
        }
      }
      blk.coord_data_index = coord_select;
      break;
    }
    case kNonModalSetCoordinateOffset:
      if (!axis_words) return kGrblGcodeNoAxisWords;
      for (int i = 0; i < 3; ++i) {
        if (axis_words & (1u << i)) {
          v.xyz[i] = gc.position[i] - blk.block_coord_system[i] - v.xyz[i];
          if (i == 2) v.xyz[i] -= gc.tool_length_offset;
        } else {
          v.xyz[i] = gc.coord_offset[i];
        }
      }
      break;
    default:
      if (axis_command != kAxisCommandToolLengthOffset && axis_words) {
        for (int i = 0; i < 3; ++i) {
          if (!(axis_words & (1u << i))) {
            v.xyz[i] = gc.position[i];
          } else if (blk.non_modal != kNonModalAbsoluteOverride) {
            if (!blk.modal.incremental) {
              v.xyz[i] += blk.block_coord_system[i] + gc.coord_offset[i];
              if (i == 2) v.xyz[i] += gc.tool_length_offset;
            } else {
              v.xyz[i] += gc.position[i];
            }
          }
        }
      }
      switch (blk.non_modal) {
        case kNonModalGoHome0:
        case kNonModalGoHome1:
          v.ijk = blk.non_modal == kNonModalGoHome0 ? coords.g28 : coords.g30;
          if (axis_words) {
            for (int i = 0; i < 3; ++i) {
              if (!(axis_words & (1u << i))) v.ijk[i] = gc.position[i];
            }
          } else {
            axis_command = kAxisCommandNone;
          }
          break;
        case kNonModalAbsoluteOverride:
          if (!(blk.modal.motion == kMotionSeek || blk.modal.motion == kMotionLinear)) {
            return kGrblGcodeG53InvalidMotionMode;
          }
          break;
        default:
          break;
      }
  }

  // [20. Motion modes]
  if (blk.modal.motion == kMotionNone) {
    if (axis_words) return kGrblGcodeAxisWordsExist;
  } else if (axis_command == kAxisCommandMotionMode) {
    if (blk.modal.motion == kMotionSeek) {
      if (!axis_words) axis_command = kAxisCommandNone;
    } else {
      if (v.f == 0.0) return kGrblGcodeUndefinedFeedRate;
      switch (blk.modal.motion) {
        case kMotionLinear:
          if (!axis_words) axis_command = kAxisCommandNone;
          break;
        case kMotionCwArc:
        case kMotionCcwArc: {
          blk.arc_clockwise = blk.modal.motion == kMotionCwArc;
          const int a0 = blk.axis_0, a1 = blk.axis_1;
          if (!axis_words) return kGrblGcodeNoAxisWords;
          if (!(axis_words & ((1u << a0) | (1u << a1)))) return kGrblGcodeNoAxisWordsInPlane;
          double x = v.xyz[a0] - gc.position[a0];
          double y = v.xyz[a1] - gc.position[a1];
          if (value_words & kWordR) {  // radius mode
            value_words &= ~kWordR;
            if (SamePosition(gc.position, v.xyz)) return kGrblGcodeInvalidTarget;
            if (blk.modal.inches) v.r *= kMmPerInch;
            double h_x2_div_d = 4.0 * v.r * v.r - x * x - y * y;
            if (h_x2_div_d < 0) return kGrblGcodeArcRadiusError;
            h_x2_div_d = -std::sqrt(h_x2_div_d) / std::hypot(x, y);
            if (blk.modal.motion == kMotionCcwArc) h_x2_div_d = -h_x2_div_d;
            if (v.r < 0) {
              h_x2_div_d = -h_x2_div_d;
              v.r = -v.r;
            }
            v.ijk[a0] = 0.5 * (x - (y * h_x2_div_d));
            v.ijk[a1] = 0.5 * (y + (x * h_x2_div_d));
          } else {  // centre offset mode
            if (!(ijk_words & ((1u << a0) | (1u << a1)))) return kGrblGcodeNoOffsetsInPlane;
            value_words &= ~(kWordI | kWordJ | kWordK);
            if (blk.modal.inches) {
              for (int i = 0; i < 3; ++i) {
                if (ijk_words & (1u << i)) v.ijk[i] *= kMmPerInch;
              }
            }
            x -= v.ijk[a0];
            y -= v.ijk[a1];
            const double target_r = std::hypot(x, y);
            v.r = std::hypot(v.ijk[a0], v.ijk[a1]);
            const double delta_r = std::abs(target_r - v.r);
            if (delta_r > 0.005) {
              if (delta_r > 0.5) return kGrblGcodeInvalidTarget;
              if (delta_r > 0.001 * v.r) return kGrblGcodeInvalidTarget;
            }
          }
          break;
        }
        case kMotionProbeToward:
        case kMotionProbeTowardNoError:
        case kMotionProbeAway:
        case kMotionProbeAwayNoError:
          if (!axis_words) return kGrblGcodeNoAxisWords;
          if (SamePosition(gc.position, v.xyz)) return kGrblGcodeInvalidTarget;
          break;
        default:
          break;
      }
    }
  }

  // [0. Unused words]
  if (blk.jog) {
    value_words &= ~(kWordN | kWordF);
  } else {
    value_words &= ~(kWordN | kWordF | kWordS | kWordT);
  }
  if (axis_command) value_words &= ~(kWordX | kWordY | kWordZ);
  if (value_words) return kGrblGcodeUnusedWords;

  if (blk.jog) {
    if (command_words & ~(kGroupG3 | kGroupG6 | kGroupG0)) return kGrblInvalidJogCommand;
    if (!(blk.non_modal == kNonModalAbsoluteOverride || blk.non_modal == kNonModalNone)) {
      return kGrblInvalidJogCommand;
    }
  }

  blk.axis_command = axis_command;
  blk.axis_words = axis_words;
  blk.feed_rate = v.f;
  blk.spindle_speed = v.s;
  blk.tool = v.t;  // GRBL: gc_state.tool = gc_block.values.t (0 when no T word)
  blk.line_number = static_cast<int>(v.n);
  blk.dwell_s = v.p;
  blk.xyz = v.xyz;
  blk.ijk = v.ijk;
  blk.radius = v.r;
  *out = blk;
  return kGrblOk;
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
  const int segments =
      chord > 0 ? static_cast<int>(std::floor(std::abs(0.5 * angular_travel * radius) / chord)) : 0;
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
