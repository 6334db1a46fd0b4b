// The virtual controller's motion control (GRBL's motion_control.c and limits.c): soft limits,
// lines and arcs into the planner, dwells, the probe cycle, and homing.

#include <algorithm>
#include <cmath>
#include <utility>

#include "sim/virtual_cnc_impl.h"

namespace gs360 {
namespace {

constexpr double kDwellTimeStep = 0.050;     // DWELL_TIME_STEP (s)
constexpr double kHomingSearchScalar = 1.5;  // HOMING_AXIS_SEARCH_SCALAR

}  // namespace

bool VirtualCnc::Impl::TravelOk(const Eigen::Vector3d& target) const {
  for (int i = 0; i < 3; ++i) {
    const bool negative = (settings_.homing_dir_mask >> i) & 1;
    if (options_.homing_force_set_origin && negative) {  // travel is 0..+max
      if (target[i] < 0.0 || target[i] > settings_.max_travel_mm[i]) return false;
    } else if (target[i] > 0.0 || target[i] < -settings_.max_travel_mm[i]) {
      return false;
    }
  }
  return true;
}

double VirtualCnc::Impl::HomedPosition(int axis) const {
  if (options_.homing_force_set_origin) return 0.0;
  const bool negative = (settings_.homing_dir_mask >> axis) & 1;
  return negative ? -settings_.max_travel_mm[axis] + settings_.homing_pulloff_mm
                  : -settings_.homing_pulloff_mm;
}

void VirtualCnc::Impl::LimitsSoftCheck(Lock& lk, const Eigen::Vector3d& target) {
  if (TravelOk(target)) return;
  soft_limit_ = true;
  if (state_ == GrblState::kRun) {  // controlled stop first: position is kept
    rt_feed_hold_ = true;
    while (true) {
      ExecuteRealtime(lk);
      if (abort_) return;
      if (state_ == GrblState::kIdle) break;
      Wait(lk);
    }
  }
  McReset();
  rt_alarm_ = kGrblAlarmSoftLimit;
  ExecuteRealtime(lk);
}

void VirtualCnc::Impl::McLine(Lock& lk, const Eigen::Vector3d& target, const MoveRate& rate) {
  if (settings_.soft_limits && state_ != GrblState::kJog) {
    LimitsSoftCheck(lk, target);
    if (abort_ || Aborting()) return;
  }
  if (state_ == GrblState::kCheck) return;
  while (true) {
    ExecuteRealtime(lk);
    if (abort_) return;
    if (!exec_.PlannerFull()) break;
    AutoCycleStart();
    Wait(lk);
  }
  const Eigen::Vector3d true_target = Quantize(target) + offset_;
  if (exec_.AddLine(true_target, rate, MachineNow(), armed_alarm_)) {
    armed_alarm_.reset();
    ++stats_.blocks_planned;
  }
}

void VirtualCnc::Impl::McArc(Lock& lk, const GcodeBlock& blk, const MoveRate& rate_in) {
  const std::vector<Eigen::Vector3d> points =
      ArcSegmentTargets(gc_.position, blk.xyz, blk.ijk, blk.radius, blk.axis_0, blk.axis_1,
                        blk.axis_linear, blk.arc_clockwise, settings_.arc_tolerance_mm);
  MoveRate rate = rate_in;
  if (rate.inverse_time && points.size() > 1) {
    rate.feed_mm_per_min *= static_cast<double>(points.size());
    rate.inverse_time = false;
  }
  for (const Eigen::Vector3d& p : points) {
    McLine(lk, p, rate);
    if (abort_ || Aborting()) return;
  }
}

void VirtualCnc::Impl::McDwell(Lock& lk, double seconds) {
  if (state_ == GrblState::kCheck) return;
  Synchronize(lk);
  if (abort_) return;
  ++stats_.dwells;
  if (std::exchange(reset_at_dwell_, false)) {
    if (Marlin()) return Reboot();  // a printer's reset is its MCU's: the board restarts
    McReset();
  }
  // delay_sec(seconds, DELAY_MODE_DWELL): ceil(seconds / 50 ms) steps of 50 ms, real-time
  // commands served between steps (a feed hold suspends the dwell).
  const long steps = static_cast<long>(std::ceil(seconds / kDwellTimeStep - 1e-9));
  for (long i = 0; i < steps; ++i) {
    if (Aborting()) return;
    ExecuteRealtime(lk);
    if (abort_) return;
    const double end = MachineNow() + kDwellTimeStep;
    if (clock_.instant()) {
      clock_.JumpTo(Clock::now(), end);
      continue;
    }
    while (MachineNow() < end) {
      Wait(lk, end);
      if (Aborting()) return;
    }
  }
}

void VirtualCnc::Impl::MachineDelay(Lock& lk, double seconds) {
  if (seconds <= 0.0) return;
  const double end = MachineNow() + seconds;
  if (clock_.instant()) {
    clock_.JumpTo(Clock::now(), end);
    return;
  }
  while (MachineNow() < end && !Aborting()) {
    UpdateMotion();
    Wait(lk, end);
  }
}

int VirtualCnc::Impl::McProbeCycle(Lock& lk, const GcodeBlock& blk, const MoveRate& rate) {
  if (state_ == GrblState::kCheck) return 0;
  Synchronize(lk);
  if (abort_) return 2;
  probe_succeeded_ = false;
  const bool away =
      blk.modal.motion == kMotionProbeAway || blk.modal.motion == kMotionProbeAwayNoError;
  const bool no_error =
      blk.modal.motion == kMotionProbeTowardNoError || blk.modal.motion == kMotionProbeAwayNoError;
  // No probe is wired to this rig: the input never triggers. Probing "away" expects contact at
  // the start, so it fails at once.
  if (away) {
    rt_alarm_ = kGrblAlarmProbeFailInitial;
    ExecuteRealtime(lk);
    return 2;
  }
  McLine(lk, blk.xyz, rate);
  if (abort_ || Aborting()) return 2;
  rt_cycle_start_ = true;
  while (true) {
    ExecuteRealtime(lk);
    if (abort_) return 2;
    if (state_ == GrblState::kIdle) break;
    Wait(lk);
  }
  if (no_error) {
    probe_position_ = Belief();
  } else {
    rt_alarm_ = kGrblAlarmProbeFailContact;
  }
  ExecuteRealtime(lk);
  exec_.Stop(MachineNow());
  Emit("[PRB:" + AxisValues(probe_position_) + ":0]\r\n");
  return 0;
}

// Homing (mc_homing_cycle / limits_go_home).

bool VirtualCnc::Impl::HomingMove(Lock& lk, const Eigen::Vector3d& target, double rate,
                                  bool abrupt) {
  exec_.AddSystemLine(target, rate, abrupt, MachineNow());
  exec_.StartCycle(MachineNow());
  while (true) {
    UpdateMotion();              // no status reports during homing, only a reset gets through
    if (Marlin()) MarlinIdle();  // a printer's keep-alive goes on
    if (Aborting()) return false;
    if (!exec_.Busy()) return true;
    Wait(lk);
  }
}

bool VirtualCnc::Impl::HomeAxes(Lock& lk, const std::vector<int>& axes) {
  const double n = static_cast<double>(axes.size());
  const double seek = settings_.homing_seek_mm_per_min * std::sqrt(n);
  const double feed = settings_.homing_feed_mm_per_min * std::sqrt(n);
  const double pulloff = settings_.homing_pulloff_mm;
  const double debounce = settings_.homing_debounce_ms / 1000.0;
  // Switch positions in the true frame: one pull-off beyond where homing leaves the machine,
  // so that a correct homing makes belief and truth agree.
  Eigen::Vector3d sw = Eigen::Vector3d::Zero();
  Eigen::Vector3d dir = Eigen::Vector3d::Zero();  // direction toward the switch
  for (int i : axes) {
    const bool negative = (settings_.homing_dir_mask >> i) & 1;
    dir[i] = negative ? -1.0 : 1.0;
    sw[i] = HomedPosition(i) + dir[i] * pulloff;
  }
  auto fail = [&](int alarm) {
    if (Rebooted()) return false;  // the board restarted: no alarm from the old run
    rt_alarm_ = alarm;
    McReset();
    ExecuteRealtime(lk);
    return false;
  };
  // Search: toward the switch, at most 1.5 * max travel.
  Eigen::Vector3d here = exec_.PositionAt(MachineNow());
  Eigen::Vector3d target = here;
  bool found = true;
  for (int i : axes) {
    const double distance = std::max(0.0, (sw[i] - here[i]) * dir[i]);
    const double limit = kHomingSearchScalar * settings_.max_travel_mm[i];
    if (distance > limit) {
      found = false;
      target[i] = here[i] + dir[i] * limit;
    } else {
      target[i] = sw[i];
    }
  }
  if (!HomingMove(lk, target, seek, true)) return fail(kGrblAlarmHomingFailReset);
  if (!found) return fail(kGrblAlarmHomingFailApproach);
  MachineDelay(lk, debounce);
  // Pull-off, locate slowly, pull-off again.
  for (int phase = 0; phase < 3; ++phase) {
    const bool approach = phase == 1;
    here = exec_.PositionAt(MachineNow());
    target = here;
    for (int i : axes) target[i] = approach ? sw[i] : sw[i] - dir[i] * pulloff;
    if (!approach && pulloff <= 0.0) return fail(kGrblAlarmHomingFailPulloff);
    if (!HomingMove(lk, target, approach ? feed : seek, approach)) {
      return fail(kGrblAlarmHomingFailReset);
    }
    MachineDelay(lk, debounce);
    if (Aborting()) return fail(kGrblAlarmHomingFailReset);
  }
  const Eigen::Vector3d truth = exec_.PositionAt(MachineNow());
  for (int i : axes) offset_[i] = truth[i] - HomedPosition(i);
  return true;
}

void VirtualCnc::Impl::HomingCycle(Lock& lk) {
  exec_.Stop(MachineNow());
  if (!HomeAxes(lk, {2})) return;     // HOMING_CYCLE_0: Z
  if (!HomeAxes(lk, {0, 1})) return;  // HOMING_CYCLE_1: X and Y
  ExecuteRealtime(lk);                // answers a status request made during homing (state Home)
  if (abort_) return;
  homed_ = true;
  gc_.position = Belief();
}

}  // namespace gs360
