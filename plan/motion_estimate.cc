#include "plan/motion_estimate.h"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <limits>
#include <optional>
#include <sstream>
#include <stdexcept>

namespace gs360 {
namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

std::string Num(double v) {
  std::ostringstream os;
  os << v;
  return os.str();
}

void RequireAxesPositive(const char* field, const Eigen::Vector3d& v) {
  for (int i = 0; i < 3; ++i) {
    if (!(v[i] > 0.0) || !std::isfinite(v[i])) {
      throw std::invalid_argument(std::string("MachineSettings.") + field + "[" +
                                  std::to_string(i) + "] must be finite and > 0, got " + Num(v[i]));
    }
  }
}

// One planned block.
struct Block {
  double length = 0.0;
  Eigen::Vector3d unit = Eigen::Vector3d::Zero();
  double nominal = 0.0;        // mm/s
  double accel = 0.0;          // mm/s^2
  double max_entry_sqr = 0.0;  // (mm/s)^2
};

std::vector<Block> MakeBlocks(const Eigen::Vector3d& start, const std::vector<Move>& moves,
                              const MachineSettings& settings) {
  const Eigen::Vector3d rate_mm_s = settings.max_rate_mm_per_min / 60.0;
  std::vector<Block> blocks;
  blocks.reserve(moves.size());
  Eigen::Vector3d pos = start;
  for (const Move& m : moves) {
    if (!m.target.allFinite()) {
      throw std::invalid_argument("Move target must be finite, got (" + Num(m.target.x()) + ", " +
                                  Num(m.target.y()) + ", " + Num(m.target.z()) + ")");
    }
    const Eigen::Vector3d delta = m.target - pos;
    const double length = delta.norm();
    pos = m.target;
    if (!(length > 0.0)) continue;  // GRBL drops zero-length blocks
    Block b;
    b.length = length;
    b.unit = delta / length;
    const double rapid = MaxAlongDirection(rate_mm_s, b.unit);
    b.nominal = m.Rapid() ? rapid : std::min(rapid, m.feed_mm_per_min / 60.0);
    b.accel = MaxAlongDirection(settings.acceleration_mm_per_s2, b.unit);
    if (blocks.empty()) {
      b.max_entry_sqr = 0.0;  // the first block after a sync starts from rest
    } else {
      const Block& prev = blocks.back();
      b.max_entry_sqr = std::min({JunctionSpeedSqr(prev.unit, b.unit, settings),
                                  b.nominal * b.nominal, prev.nominal * prev.nominal});
    }
    blocks.push_back(b);
  }
  return blocks;
}

}  // namespace

void MachineSettings::Check() const {
  RequireAxesPositive("max_rate_mm_per_min", max_rate_mm_per_min);
  RequireAxesPositive("acceleration_mm_per_s2", acceleration_mm_per_s2);
  RequireAxesPositive("max_travel_mm", max_travel_mm);
  if (travel_min_mm && !travel_min_mm->allFinite()) {
    throw std::invalid_argument("MachineSettings.travel_min_mm must be finite");
  }
  if (!(junction_deviation_mm >= 0.0) || !std::isfinite(junction_deviation_mm)) {
    throw std::invalid_argument(
        "MachineSettings.junction_deviation_mm must be finite and >= 0, got " +
        Num(junction_deviation_mm));
  }
  if (planner_blocks < 1) {
    throw std::invalid_argument("MachineSettings.planner_blocks must be >= 1, got " +
                                std::to_string(planner_blocks));
  }
}

MachineSettings MachineSettings::FromGrblSettings(const std::map<int, double>& settings) {
  MachineSettings s;
  auto take = [&](int number, double& field) {
    if (auto it = settings.find(number); it != settings.end()) field = it->second;
  };
  for (int i = 0; i < 3; ++i) {
    take(110 + i, s.max_rate_mm_per_min[i]);
    take(120 + i, s.acceleration_mm_per_s2[i]);
    take(130 + i, s.max_travel_mm[i]);
  }
  take(11, s.junction_deviation_mm);
  s.Check();
  return s;
}

std::string_view JunctionModelName(JunctionModel model) {
  switch (model) {
    case JunctionModel::kStop:
      return "stop";
    case JunctionModel::kGrbl:
      return "grbl";
  }
  return "unknown";
}

double MaxAlongDirection(const Eigen::Vector3d& axis_max, const Eigen::Vector3d& unit) {
  double limit = kInf;
  for (int i = 0; i < 3; ++i) {
    if (unit[i] != 0.0) limit = std::min(limit, std::abs(axis_max[i] / unit[i]));
  }
  return limit;
}

double JunctionSpeedSqr(const Eigen::Vector3d& prev_unit, const Eigen::Vector3d& unit,
                        const MachineSettings& settings) {
  const double junction_cos_theta = -prev_unit.dot(unit);
  if (junction_cos_theta > 0.999999) return 0.0;    // reversal (GRBL: MINIMUM_JUNCTION_SPEED = 0)
  if (junction_cos_theta < -0.999999) return kInf;  // straight on
  const Eigen::Vector3d junction_unit = (unit - prev_unit).normalized();
  const double junction_accel = MaxAlongDirection(settings.acceleration_mm_per_s2, junction_unit);
  const double sin_theta_d2 = std::sqrt(0.5 * (1.0 - junction_cos_theta));
  return std::max(
      0.0, junction_accel * settings.junction_deviation_mm * sin_theta_d2 / (1.0 - sin_theta_d2));
}

double TrapezoidTime(double length, double entry_speed, double nominal_speed, double exit_speed,
                     double acceleration) {
  if (!(length >= 0.0) || !(nominal_speed > 0.0) || !(acceleration > 0.0) ||
      !(entry_speed >= 0.0) || !(exit_speed >= 0.0)) {
    throw std::invalid_argument("TrapezoidTime: invalid arguments length=" + Num(length) +
                                " entry=" + Num(entry_speed) + " nominal=" + Num(nominal_speed) +
                                " exit=" + Num(exit_speed) + " acceleration=" + Num(acceleration));
  }
  if (length == 0.0) return 0.0;
  const double v0 = std::min(entry_speed, nominal_speed);
  const double v1 = std::min(exit_speed, nominal_speed);
  const double reach = 2.0 * acceleration * length;
  if (std::abs(v0 * v0 - v1 * v1) > reach * (1.0 + 1e-9) + 1e-12) {
    throw std::invalid_argument("TrapezoidTime: speeds " + Num(v0) + " -> " + Num(v1) +
                                " mm/s cannot be met within " + Num(length) + " mm at " +
                                Num(acceleration) + " mm/s^2");
  }
  const double v_sqr = nominal_speed * nominal_speed;
  const double accel_dist = (v_sqr - v0 * v0) / (2.0 * acceleration);
  const double decel_dist = (v_sqr - v1 * v1) / (2.0 * acceleration);
  if (accel_dist + decel_dist <= length) {
    return (nominal_speed - v0) / acceleration + (nominal_speed - v1) / acceleration +
           (length - accel_dist - decel_dist) / nominal_speed;
  }
  // Triangle: peak speed where the acceleration and deceleration ramps meet.
  const double peak = std::sqrt(std::max({0.5 * (reach + v0 * v0 + v1 * v1), v0 * v0, v1 * v1}));
  return (peak - v0) / acceleration + (peak - v1) / acceleration;
}

double MoveTime(const Eigen::Vector3d& from, const Move& move, const MachineSettings& settings) {
  return PathTime(from, {move}, settings, JunctionModel::kStop);
}

double RapidTime(const Eigen::Vector3d& from, const Eigen::Vector3d& to,
                 const MachineSettings& settings) {
  const Eigen::Vector3d delta = to - from;
  const double length = delta.norm();
  if (!(length > 0.0)) return 0.0;
  const Eigen::Vector3d unit = delta / length;
  const double v = MaxAlongDirection(settings.max_rate_mm_per_min, unit) / 60.0;
  const double a = MaxAlongDirection(settings.acceleration_mm_per_s2, unit);
  if (length >= v * v / a) return length / v + v / a;
  return 2.0 * std::sqrt(length / a);
}

std::vector<BlockProfile> PlanPath(const Eigen::Vector3d& start, const std::vector<Move>& moves,
                                   const MachineSettings& settings, JunctionModel model) {
  const std::vector<Block> blocks = MakeBlocks(start, moves, settings);
  const int n = static_cast<int>(blocks.size());
  std::vector<BlockProfile> out(n);
  std::vector<double> entry_sqr(n + 1, 0.0);  // entry_sqr[n] = exit of the last block = 0
  if (model == JunctionModel::kGrbl && n > 1) {
    const int window = std::max(1, settings.planner_blocks);
    // Block k's exit speed is fixed while it runs, by the plan over the blocks then in the
    // planner (k .. k + window - 1, the newest ending at rest), and by what k can reach.
    for (int k = 0; k < n; ++k) {
      const int last = std::min(k + window - 1, n - 1);
      double exit_sqr = 0.0;
      for (int j = last; j > k; --j) {
        exit_sqr =
            std::min(blocks[j].max_entry_sqr, exit_sqr + 2.0 * blocks[j].accel * blocks[j].length);
      }
      entry_sqr[k + 1] =
          k + 1 < n ? std::min(exit_sqr, entry_sqr[k] + 2.0 * blocks[k].accel * blocks[k].length)
                    : 0.0;
    }
  }
  for (int k = 0; k < n; ++k) {
    const Block& b = blocks[k];
    BlockProfile& p = out[k];
    p.length = b.length;
    p.nominal_speed = b.nominal;
    p.acceleration = b.accel;
    p.entry_speed = std::sqrt(entry_sqr[k]);
    p.exit_speed = std::sqrt(entry_sqr[k + 1]);
    p.time = TrapezoidTime(b.length, p.entry_speed, b.nominal, p.exit_speed, b.accel);
  }
  return out;
}

double PathTime(const Eigen::Vector3d& start, const std::vector<Move>& moves,
                const MachineSettings& settings, JunctionModel model) {
  double t = 0.0;
  for (const BlockProfile& p : PlanPath(start, moves, settings, model)) t += p.time;
  return t;
}

// --- G-code program estimate -------------------------------------------------------------------

namespace {

[[noreturn]] void ThrowLine(int number, const std::string& line, const std::string& why) {
  throw std::invalid_argument("EstimateProgram: line " + std::to_string(number) + " \"" + line +
                              "\": " + why);
}

// Strips comments ((...) and ;...), spaces and upper-cases.
std::string CleanLine(const std::string& raw) {
  std::string out;
  out.reserve(raw.size());
  bool in_paren = false;
  for (char c : raw) {
    if (in_paren) {
      if (c == ')') in_paren = false;
      continue;
    }
    if (c == '(') {
      in_paren = true;
      continue;
    }
    if (c == ';') break;
    if (c == ' ' || c == '\t' || c == '\r' || c == '\n') continue;
    out.push_back(static_cast<char>(c >= 'a' && c <= 'z' ? c - 'a' + 'A' : c));
  }
  return out;
}

}  // namespace

ProgramEstimate EstimateProgram(const std::vector<std::string>& lines, const Eigen::Vector3d& start,
                                const MachineSettings& settings, JunctionModel model,
                                const Eigen::Vector3d& work_offset) {
  settings.Check();
  ProgramEstimate est;
  Eigen::Vector3d pos = start;            // machine position at the end of the queued motion
  Eigen::Vector3d segment_start = start;  // where the current sync group started
  std::vector<Move> pending;
  int motion_mode = 0;  // 0: G0, 1: G1
  bool absolute = true;
  double unit_scale = 1.0;  // mm per program unit
  double feed = 0.0;        // mm/min, 0 = not set
  auto flush = [&]() {
    for (const BlockProfile& p : PlanPath(segment_start, pending, settings, model)) {
      est.motion_s += p.time;
      ++est.moves;
    }
    pending.clear();
    segment_start = pos;
  };
  for (std::size_t li = 0; li < lines.size(); ++li) {
    const int number = static_cast<int>(li) + 1;
    const std::string line = CleanLine(lines[li]);
    if (line.empty() || line[0] == '%' || line[0] == '$') continue;
    bool g53 = false, dwell = false, motion_word = false;
    std::optional<double> axis[3];
    std::optional<double> p_word;
    std::size_t i = 0;
    while (i < line.size()) {
      const char letter = line[i++];
      if (letter < 'A' || letter > 'Z') ThrowLine(number, lines[li], "expected a letter");
      double value = 0.0;
      const char* first = line.data() + i;
      const char* last = line.data() + line.size();
      if (first != last && *first == '+') ++first;
      const auto [ptr, ec] = std::from_chars(first, last, value);
      if (ec != std::errc() || !std::isfinite(value)) {
        ThrowLine(number, lines[li], std::string("bad number after '") + letter + "'");
      }
      i = static_cast<std::size_t>(ptr - line.data());
      switch (letter) {
        case 'G': {
          const int code10 = static_cast<int>(std::lround(value * 10.0));
          switch (code10) {
            case 0:
              motion_mode = 0;
              motion_word = true;
              break;
            case 10:
              motion_mode = 1;
              motion_word = true;
              break;
            case 40:
              dwell = true;
              break;
            case 530:
              g53 = true;
              break;
            case 900:
              absolute = true;
              break;
            case 910:
              absolute = false;
              break;
            case 200:
              unit_scale = 25.4;
              break;
            case 210:
              unit_scale = 1.0;
              break;
            case 20:
            case 30:
            case 280:
            case 300:
            case 100:
            case 920:
            case 382:
            case 383:
            case 384:
            case 385:
            case 381:
              ThrowLine(number, lines[li], "unsupported G" + Num(value));
            default:
              break;  // plane, offsets selection, feed mode, cancels: no motion
          }
          break;
        }
        case 'X':
          axis[0] = value;
          break;
        case 'Y':
          axis[1] = value;
          break;
        case 'Z':
          axis[2] = value;
          break;
        case 'F':
          feed = value * unit_scale;
          break;
        case 'P':
          p_word = value;
          break;
        default:
          break;  // N, M, S, T, ...: no motion
      }
    }
    (void)motion_word;
    if (dwell) {
      if (!p_word || *p_word < 0.0) ThrowLine(number, lines[li], "G4 needs P >= 0 (seconds)");
      flush();
      est.dwell_s += *p_word;
      ++est.syncs;
      continue;
    }
    if (!axis[0] && !axis[1] && !axis[2]) continue;
    Eigen::Vector3d target = pos;
    for (int a = 0; a < 3; ++a) {
      if (!axis[a]) continue;
      const double v = *axis[a] * unit_scale;
      if (g53) {
        target[a] = v;
      } else if (absolute) {
        target[a] = v + work_offset[a];
      } else {
        target[a] = pos[a] + v;
      }
    }
    Move m;
    m.target = target;
    if (motion_mode == 1) {
      if (!(feed > 0.0)) ThrowLine(number, lines[li], "G1 without a feed rate (F)");
      m.feed_mm_per_min = feed;
    }
    pending.push_back(m);
    pos = target;
  }
  flush();
  est.end_position = pos;
  return est;
}

}  // namespace gs360
