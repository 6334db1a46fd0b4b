#include "sim/grbl_planner.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>
#include <string>

namespace gs360 {
namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kSomeLargeValue = 1.0e38;        // GRBL's SOME_LARGE_VALUE
constexpr double kMinimumFeedRateMmPerMin = 1.0;  // GRBL's MINIMUM_FEED_RATE
constexpr double kLengthEps = 1e-9;               // mm
constexpr double kSpeedEps = 1e-9;                // mm/s

double Sqr(double x) {
  return x * x;
}

// Time to cover distance d from speed v with constant signed acceleration a (the first time the
// distance is reached). Numerically stable form of (-v + sqrt(v^2 + 2ad)) / a.
double TimeToCover(double v, double a, double d) {
  if (d <= 0.0) return 0.0;
  const double disc = std::max(0.0, v * v + 2.0 * a * d);
  const double denom = v + std::sqrt(disc);
  if (denom <= 0.0) return kInf;
  return 2.0 * d / denom;
}

// Squared maximum junction speed (mm^2/s^2), GRBL plan_buffer_line().
double JunctionSpeedSqr(const Eigen::Vector3d& prev_unit, const Eigen::Vector3d& unit,
                        const MotionLimits& limits) {
  const double junction_cos_theta = -prev_unit.dot(unit);
  if (junction_cos_theta > 0.999999) return 0.0;  // MINIMUM_JUNCTION_SPEED^2 = 0
  if (junction_cos_theta < -0.999999) return kSomeLargeValue;
  Eigen::Vector3d junction_unit = unit - prev_unit;
  junction_unit.normalize();
  const double junction_acceleration =
      LimitByAxisMaximum(limits.acceleration_mm_per_s2, junction_unit);
  const double sin_theta_d2 = std::sqrt(0.5 * (1.0 - junction_cos_theta));
  return std::max(0.0, junction_acceleration * limits.junction_deviation_mm * sin_theta_d2 /
                           (1.0 - sin_theta_d2));
}

void CheckPositive(const char* field, double value) {
  if (!(value > 0.0) || !std::isfinite(value)) {
    std::ostringstream os;
    os << "MotionLimits." << field << " must be > 0, got " << value;
    throw std::invalid_argument(os.str());
  }
}

}  // namespace

void MotionLimits::Check() const {
  static const char* kRate[] = {"max_rate_mm_per_min.x", "max_rate_mm_per_min.y",
                                "max_rate_mm_per_min.z"};
  static const char* kAccel[] = {"acceleration_mm_per_s2.x", "acceleration_mm_per_s2.y",
                                 "acceleration_mm_per_s2.z"};
  for (int i = 0; i < 3; ++i) {
    CheckPositive(kRate[i], max_rate_mm_per_min[i]);
    CheckPositive(kAccel[i], acceleration_mm_per_s2[i]);
  }
  if (!(junction_deviation_mm >= 0.0) || !std::isfinite(junction_deviation_mm)) {
    throw std::invalid_argument("MotionLimits.junction_deviation_mm must be >= 0, got " +
                                std::to_string(junction_deviation_mm));
  }
}

double LimitByAxisMaximum(const Eigen::Vector3d& axis_max, const Eigen::Vector3d& unit) {
  double limit = kSomeLargeValue;
  for (int i = 0; i < 3; ++i) {
    if (unit[i] != 0.0) limit = std::min(limit, std::abs(axis_max[i] / unit[i]));
  }
  return limit;
}

double JunctionSpeedLimit(const Eigen::Vector3d& prev_unit, const Eigen::Vector3d& unit,
                          const MotionLimits& limits) {
  const double v_sqr = JunctionSpeedSqr(prev_unit, unit, limits);
  if (v_sqr >= kSomeLargeValue) return kInf;
  return std::sqrt(v_sqr);
}

double TrapezoidDuration(double length_mm, double entry_speed, double nominal_speed,
                         double exit_speed, double acceleration) {
  if (!(length_mm >= 0.0) || !(nominal_speed > 0.0) || !(acceleration > 0.0) ||
      !(entry_speed >= 0.0) || !(exit_speed >= 0.0)) {
    std::ostringstream os;
    os << "TrapezoidDuration: invalid arguments length=" << length_mm << " entry=" << entry_speed
       << " nominal=" << nominal_speed << " exit=" << exit_speed << " accel=" << acceleration;
    throw std::invalid_argument(os.str());
  }
  const double a = acceleration;
  const double tol = 1e-9 * std::max(1.0, Sqr(std::max({entry_speed, exit_speed, nominal_speed})));
  if (std::abs(Sqr(entry_speed) - Sqr(exit_speed)) > 2.0 * a * length_mm + tol ||
      exit_speed > nominal_speed * (1.0 + 1e-12)) {
    std::ostringstream os;
    os << "TrapezoidDuration: speeds " << entry_speed << " -> " << exit_speed
       << " mm/s cannot be met over " << length_mm << " mm at " << a << " mm/s^2 (nominal "
       << nominal_speed << ")";
    throw std::invalid_argument(os.str());
  }
  if (length_mm == 0.0) return 0.0;
  double t = 0.0;
  double v = entry_speed;
  double remaining = length_mm;
  if (v > nominal_speed) {  // decelerate to the nominal speed first
    t += (v - nominal_speed) / a;
    remaining -= (Sqr(v) - Sqr(nominal_speed)) / (2.0 * a);
    v = nominal_speed;
  }
  const double accel_dist = (Sqr(nominal_speed) - Sqr(v)) / (2.0 * a);
  const double decel_dist = (Sqr(nominal_speed) - Sqr(exit_speed)) / (2.0 * a);
  if (accel_dist + decel_dist <= remaining) {
    t += (nominal_speed - v) / a + (remaining - accel_dist - decel_dist) / nominal_speed +
         (nominal_speed - exit_speed) / a;
  } else {
    const double peak =
        std::sqrt(std::max(0.0, (2.0 * a * remaining + Sqr(v) + Sqr(exit_speed)) / 2.0));
    t += std::max(0.0, peak - v) / a + std::max(0.0, peak - exit_speed) / a;
  }
  return t;
}

double NominalSpeed(const Eigen::Vector3d& unit, double length_mm, const MoveRate& rate,
                    const MotionLimits& limits) {
  const double rapid_rate = LimitByAxisMaximum(limits.max_rate_mm_per_min, unit);
  double nominal = rapid_rate;
  if (!rate.rapid) {
    nominal = rate.inverse_time ? rate.feed_mm_per_min * length_mm : rate.feed_mm_per_min;
    nominal = std::min(nominal, rapid_rate);
  }
  return std::max(nominal, kMinimumFeedRateMmPerMin) / 60.0;
}

double IsolatedMoveDuration(const Eigen::Vector3d& from, const MoveRequest& move,
                            const MotionLimits& limits) {
  return PlannedPathDuration(from, {move}, limits);
}

double PlannedPathDuration(const Eigen::Vector3d& start, const std::vector<MoveRequest>& moves,
                           const MotionLimits& limits) {
  struct B {
    double length, accel, nominal, max_entry_sqr, entry_sqr;
  };
  std::vector<B> blocks;
  Eigen::Vector3d position = start;
  Eigen::Vector3d prev_unit = Eigen::Vector3d::Zero();
  double prev_nominal = 0.0;
  for (const MoveRequest& m : moves) {
    const Eigen::Vector3d delta = m.target - position;
    const double length = delta.norm();
    if (length < kLengthEps) continue;
    const Eigen::Vector3d unit = delta / length;
    B b;
    b.length = length;
    b.accel = LimitByAxisMaximum(limits.acceleration_mm_per_s2, unit);
    b.nominal = NominalSpeed(unit, length, m.rate, limits);
    const double junction_sqr = blocks.empty() ? 0.0 : JunctionSpeedSqr(prev_unit, unit, limits);
    b.max_entry_sqr = std::min(junction_sqr, Sqr(std::min(b.nominal, prev_nominal)));
    b.entry_sqr = 0.0;
    blocks.push_back(b);
    prev_unit = unit;
    prev_nominal = b.nominal;
    position = m.target;
  }
  const int n = static_cast<int>(blocks.size());
  if (n == 0) return 0.0;
  // Reverse pass: the last block ends at rest.
  blocks[n - 1].entry_sqr =
      std::min(blocks[n - 1].max_entry_sqr, 2.0 * blocks[n - 1].accel * blocks[n - 1].length);
  for (int i = n - 2; i >= 0; --i) {
    blocks[i].entry_sqr =
        std::min(blocks[i].max_entry_sqr,
                 blocks[i + 1].entry_sqr + 2.0 * blocks[i].accel * blocks[i].length);
  }
  blocks[0].entry_sqr = 0.0;  // starts from rest
  // Forward pass.
  for (int i = 0; i + 1 < n; ++i) {
    blocks[i + 1].entry_sqr = std::min(
        blocks[i + 1].entry_sqr, blocks[i].entry_sqr + 2.0 * blocks[i].accel * blocks[i].length);
  }
  double total = 0.0;
  for (int i = 0; i < n; ++i) {
    const double entry = std::sqrt(blocks[i].entry_sqr);
    const double exit = i + 1 < n ? std::sqrt(blocks[i + 1].entry_sqr) : 0.0;
    total += TrapezoidDuration(blocks[i].length, entry, blocks[i].nominal, exit, blocks[i].accel);
  }
  return total;
}

Eigen::Vector3d MotionPiece::PositionAt(double t) const {
  const double tau = std::clamp(t, t0, t1) - t0;
  return p0 + dir * (v0 * tau + 0.5 * accel * tau * tau);
}

double MotionPiece::SpeedAt(double t) const {
  const double tau = std::clamp(t, t0, t1) - t0;
  return std::max(0.0, v0 + accel * tau);
}

double MotionPiece::Length() const {
  const double tau = t1 - t0;
  return v0 * tau + 0.5 * accel * tau * tau;
}

MotionExecutor::MotionExecutor(const Options& options, const Eigen::Vector3d& position, double t)
    : options_(options) {
  if (options_.planner_blocks < 1) {
    throw std::invalid_argument("MotionExecutor::Options.planner_blocks must be >= 1, got " +
                                std::to_string(options_.planner_blocks));
  }
  state_.position = position;
  state_.t = t;
}

Eigen::Vector3d MotionExecutor::PlannerPosition() const {
  return state_.blocks.empty() ? state_.position : state_.blocks.back().target;
}

bool MotionExecutor::AddLine(const Eigen::Vector3d& target, const MoveRate& rate, double t,
                             std::optional<ArmedAlarm> alarm) {
  SplitAt(t);
  const Eigen::Vector3d start = PlannerPosition();
  const Eigen::Vector3d delta = target - start;
  const double length = delta.norm();
  if (length < kLengthEps) return false;
  Block b;
  b.start = start;
  b.target = target;
  b.unit = delta / length;
  b.remaining = length;
  b.length = length;
  b.accel = LimitByAxisMaximum(limits_.acceleration_mm_per_s2, b.unit);
  b.nominal = NominalSpeed(b.unit, length, rate, limits_);
  const double junction_sqr =
      state_.blocks.empty() ? 0.0 : JunctionSpeedSqr(previous_unit_, b.unit, limits_);
  b.max_entry_sqr = std::min(junction_sqr, Sqr(std::min(b.nominal, previous_nominal_)));
  b.alarm = alarm;
  previous_unit_ = b.unit;
  previous_nominal_ = b.nominal;
  state_.blocks.push_back(b);
  Replan();
  return true;
}

void MotionExecutor::AddSystemLine(const Eigen::Vector3d& target, double rate_mm_per_min,
                                   bool abrupt_end, double t) {
  SplitAt(t);
  if (!state_.blocks.empty()) {
    throw std::logic_error("MotionExecutor::AddSystemLine: the planner is not empty");
  }
  const Eigen::Vector3d delta = target - state_.position;
  const double length = delta.norm();
  if (length < kLengthEps) return;
  Block b;
  b.start = state_.position;
  b.target = target;
  b.unit = delta / length;
  b.remaining = length;
  b.length = length;
  b.accel = LimitByAxisMaximum(limits_.acceleration_mm_per_s2, b.unit);
  MoveRate rate;
  rate.rapid = false;
  rate.feed_mm_per_min = rate_mm_per_min;
  b.nominal = NominalSpeed(b.unit, length, rate, limits_);
  b.max_entry_sqr = 0.0;
  b.abrupt_end = abrupt_end;
  state_.blocks.push_back(b);
  state_.speed = 0.0;
  Replan();
}

void MotionExecutor::StartCycle(double t) {
  SplitAt(t);
  if (state_.running || state_.blocks.empty()) return;
  state_.running = true;
  state_.holding = false;
}

void MotionExecutor::FeedHold(double t) {
  SplitAt(t);
  state_.holding = true;
  if (!state_.running || state_.blocks.empty()) state_.speed = 0.0;
}

void MotionExecutor::Resume(double t) {
  SplitAt(t);
  state_.holding = false;
  state_.speed = 0.0;
  Replan();
  state_.running = !state_.blocks.empty();
}

void MotionExecutor::Stop(double t) {
  SplitAt(t);
  state_.blocks.clear();
  state_.speed = 0.0;
  state_.running = false;
  state_.holding = false;
  previous_unit_ = Eigen::Vector3d::Zero();
  previous_nominal_ = 0.0;
}

std::optional<FiredAlarm> MotionExecutor::TakeFiredAlarm() {
  std::optional<FiredAlarm> f = fired_;
  fired_.reset();
  return f;
}

void MotionExecutor::Replan() {
  auto& blocks = state_.blocks;
  const int n = static_cast<int>(blocks.size());
  if (n == 0) return;
  Block& last = blocks[n - 1];
  last.entry_sqr = std::min(last.max_entry_sqr, 2.0 * last.accel * last.remaining);
  for (int i = n - 2; i >= 1; --i) {
    blocks[i].entry_sqr =
        std::min(blocks[i].max_entry_sqr,
                 blocks[i + 1].entry_sqr + 2.0 * blocks[i].accel * blocks[i].remaining);
  }
  // The front block is executing (or about to start): its entry is the current speed.
  blocks[0].entry_sqr = Sqr(state_.speed);
  for (int i = 0; i + 1 < n; ++i) {
    blocks[i + 1].entry_sqr = std::min(
        blocks[i + 1].entry_sqr, blocks[i].entry_sqr + 2.0 * blocks[i].accel * blocks[i].remaining);
  }
}

std::optional<MotionExecutor::Step> MotionExecutor::NextStep(const State& s) {
  if (!s.running || s.blocks.empty()) return std::nullopt;
  const Block& b = s.blocks.front();
  const double v = s.speed;
  const double L = b.remaining;
  const double a = b.accel;
  double tau = 0.0;
  double accel = 0.0;
  double end_speed = v;
  bool ends_block = false;

  if (s.holding) {
    if (v <= 0.0) return std::nullopt;  // hold complete
    accel = -a;
    if (Sqr(v) / (2.0 * a) < L - kLengthEps) {
      tau = v / a;
      end_speed = 0.0;
    } else {
      tau = TimeToCover(v, -a, L);
      end_speed = std::sqrt(std::max(0.0, Sqr(v) - 2.0 * a * L));
      ends_block = true;
    }
  } else if (b.abrupt_end) {
    const double vn = b.nominal;
    if (v < vn - kSpeedEps && (Sqr(vn) - Sqr(v)) / (2.0 * a) < L - kLengthEps) {
      accel = a;
      tau = (vn - v) / a;
      end_speed = vn;
    } else if (v < vn - kSpeedEps) {
      accel = a;
      tau = TimeToCover(v, a, L);
      end_speed = 0.0;  // stops dead at the switch
      ends_block = true;
    } else {
      accel = 0.0;
      tau = L / v;
      end_speed = 0.0;
      ends_block = true;
    }
  } else {
    const double vn = b.nominal;
    const double ve = s.blocks.size() > 1 ? std::sqrt(s.blocks[1].entry_sqr) : 0.0;
    const double decel_all = (Sqr(v) - Sqr(ve)) / (2.0 * a);
    if (v > ve + kSpeedEps && decel_all >= L - kLengthEps) {
      // Deceleration only, to the end of the block. When it lands on the planned exit speed
      // (the usual case) the time is (v - ve) / a exactly; the square root of v^2 - 2aL would
      // amplify rounding near a zero exit speed.
      accel = -a;
      if (decel_all <= L + kLengthEps) {
        tau = (v - ve) / a;
        end_speed = ve;
      } else {
        tau = TimeToCover(v, -a, L);
        end_speed = std::sqrt(std::max(0.0, Sqr(v) - 2.0 * a * L));
      }
      ends_block = true;
    } else if (v > vn + kSpeedEps) {
      accel = -a;
      tau = (v - vn) / a;
      end_speed = vn;
    } else {
      const double accel_dist = std::max(0.0, (Sqr(vn) - Sqr(v)) / (2.0 * a));
      const double decel_dist = (Sqr(vn) - Sqr(ve)) / (2.0 * a);
      if (accel_dist + decel_dist <= L + kLengthEps) {
        if (v < vn - kSpeedEps) {
          accel = a;
          tau = (vn - v) / a;
          end_speed = vn;
        } else if (L - decel_dist > kLengthEps) {
          accel = 0.0;
          tau = (L - decel_dist) / v;
          end_speed = v;
        } else {
          accel = -a;
          tau = std::max(0.0, v - ve) / a;
          end_speed = ve;
          ends_block = true;
        }
      } else {
        const double peak = std::sqrt(std::max(0.0, (2.0 * a * L + Sqr(v) + Sqr(ve)) / 2.0));
        if (peak > v + kSpeedEps) {
          accel = a;
          tau = (peak - v) / a;
          end_speed = peak;
        } else {
          accel = -a;
          tau = std::max(0.0, v - ve) / a;
          end_speed = ve;
          ends_block = true;
        }
      }
    }
  }

  Step step;
  step.piece.t0 = s.t;
  step.piece.p0 = s.position;
  step.piece.dir = b.unit;
  step.piece.v0 = v;
  step.piece.accel = accel;
  step.piece.t1 = s.t + tau;
  step.ends_block = ends_block;

  if (b.alarm) {
    const double fire_remaining = b.length * (1.0 - std::clamp(b.alarm->fraction, 0.0, 1.0));
    const double covered = ends_block ? L : step.piece.Length();
    if (L - covered <= fire_remaining + kLengthEps) {
      const double d = std::max(0.0, L - fire_remaining);
      const double t_fire = TimeToCover(v, accel, d);
      step.piece.t1 = s.t + (std::isfinite(t_fire) ? std::min(t_fire, tau) : tau);
      step.fires_alarm = true;
      step.ends_block = false;
      end_speed = step.piece.SpeedAt(step.piece.t1);
    }
  }
  step.end_speed = end_speed;
  return step;
}

std::optional<FiredAlarm> MotionExecutor::ApplyStep(State& s, const Step& step) {
  Block& b = s.blocks.front();
  const MotionPiece& p = step.piece;
  s.t = p.t1;
  std::optional<FiredAlarm> fired;
  if (step.ends_block) {
    s.position = b.target;
    s.speed = step.end_speed;
    s.blocks.pop_front();
    if (!s.blocks.empty()) s.blocks.front().start = s.position;
  } else {
    s.position = p.End();
    s.speed = step.end_speed;
    b.remaining = std::max(0.0, b.remaining - p.Length());
    b.start = s.position;
    if (step.fires_alarm) {
      fired = FiredAlarm{b.alarm->code, p.t1, s.position};
      s.blocks.clear();
      s.speed = 0.0;
      s.running = false;
      s.holding = false;
      return fired;
    }
    if (b.remaining <= kLengthEps) {
      s.position = b.target;
      s.blocks.pop_front();
      if (!s.blocks.empty()) s.blocks.front().start = s.position;
    }
  }
  if (s.holding && s.speed <= kSpeedEps) s.speed = 0.0;
  if (s.blocks.empty()) {
    s.running = false;
    s.speed = 0.0;
  }
  return fired;
}

void MotionExecutor::Record(const MotionPiece& piece) {
  if (!(piece.t1 > piece.t0)) return;
  history_.push_back(piece);
  while (history_.size() > options_.history_pieces) {
    history_.pop_front();
    history_truncated_ = true;
  }
}

void MotionExecutor::AdvanceTo(double t) {
  while (true) {
    std::optional<Step> step = NextStep(state_);
    if (!step) {
      state_.t = std::max(state_.t, t);
      return;
    }
    if (step->piece.t1 > t) return;  // partial: the state stays at the piece's start
    Record(step->piece);
    std::optional<FiredAlarm> f = ApplyStep(state_, *step);
    if (f) fired_ = f;
  }
}

void MotionExecutor::SplitAt(double t) {
  AdvanceTo(t);
  std::optional<Step> step = NextStep(state_);
  if (!step) {
    state_.t = std::max(state_.t, t);
    return;
  }
  if (!(step->piece.t0 < t)) return;
  MotionPiece part = step->piece;
  part.t1 = t;
  Record(part);
  Block& b = state_.blocks.front();
  state_.position = part.End();
  state_.speed = part.SpeedAt(t);
  state_.t = t;
  b.remaining = std::max(0.0, b.remaining - part.Length());
  b.start = state_.position;
  if (b.remaining <= kLengthEps) {
    state_.position = b.target;
    state_.blocks.pop_front();
    if (state_.blocks.empty()) {
      state_.running = false;
      state_.speed = 0.0;
    }
  }
}

Eigen::Vector3d MotionExecutor::PositionAt(double t) const {
  if (t >= state_.t) {
    State s = state_;
    for (int guard = 0; guard < 100000; ++guard) {
      std::optional<Step> step = NextStep(s);
      if (!step) return s.position;
      if (step->piece.t1 >= t) return step->piece.PositionAt(t);
      ApplyStep(s, *step);
    }
    return s.position;
  }
  if (history_.empty()) return state_.position;
  // Before the oldest kept piece the answer is only known if nothing was ever evicted (then it
  // is the starting position). Ground truth must not guess.
  if (history_truncated_ && t < history_.front().t0) {
    throw std::out_of_range("MotionExecutor::PositionAt: machine time " + std::to_string(t) +
                            " s is older than the kept history (from " +
                            std::to_string(history_.front().t0) + " s, " +
                            std::to_string(history_.size()) + " pieces); raise history_pieces");
  }
  auto it = std::upper_bound(history_.begin(), history_.end(), t,
                             [](double value, const MotionPiece& p) { return value < p.t0; });
  if (it == history_.begin()) return history_.front().p0;
  --it;
  return it->PositionAt(t);
}

double MotionExecutor::SpeedAt(double t) const {
  if (t >= state_.t) {
    State s = state_;
    for (int guard = 0; guard < 100000; ++guard) {
      std::optional<Step> step = NextStep(s);
      if (!step) return 0.0;
      if (step->piece.t1 >= t) return step->piece.SpeedAt(t);
      ApplyStep(s, *step);
    }
    return 0.0;
  }
  if (history_.empty()) return 0.0;
  auto it = std::upper_bound(history_.begin(), history_.end(), t,
                             [](double value, const MotionPiece& p) { return value < p.t0; });
  if (it == history_.begin()) return 0.0;
  --it;
  return t <= it->t1 ? it->SpeedAt(t) : 0.0;
}

double MotionExecutor::NextEventTime() const {
  std::optional<Step> step = NextStep(state_);
  return step ? step->piece.t1 : kInf;
}

double MotionExecutor::FinishTime() const {
  State s = state_;
  for (int guard = 0; guard < 100000; ++guard) {
    std::optional<Step> step = NextStep(s);
    if (!step) break;
    ApplyStep(s, *step);
  }
  return s.t;
}

std::vector<MotionPiece> MotionExecutor::History(double t0, double t1) const {
  std::vector<MotionPiece> out;
  for (const MotionPiece& p : history_) {
    if (p.t1 >= t0 && p.t0 <= t1) out.push_back(p);
  }
  return out;
}

}  // namespace gs360
