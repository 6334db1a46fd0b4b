// The run engine's session: connecting, knowing where the tool is, getting out of the gel,
// recovering from resets and disconnects, checking the sensor on resume, parking
// (docs/running.md, "Faults").

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <limits>

#include <spdlog/spdlog.h>

#include "base/format.h"
#include "capture/impression.h"
#include "gcode/open_machine.h"
#include "run/run_session.h"

namespace gs360 {

using session::Ask;
using session::Fmt3;
using session::Ms;
using session::Press;
using session::Step;
using session::StepKind;

void RunSession::ConnectMachine() {
  Publish("connecting");
  OpenMachineOptions options;
  options.transport.baud = config_.machine.baud;
  options.grbl.status_min_interval = std::chrono::milliseconds(config_.machine.status_interval_ms);
  options.grbl.status_poll_interval =
      std::max(options.grbl.status_poll_interval, options.grbl.status_min_interval);
  MachineFirmware firmware = config_.machine.firmware;
  machine_ = OpenMachine(config_.machine.firmware, config_.machine.uri, options, &firmware);
  if (config_.machine.firmware == MachineFirmware::kAuto) {
    Event(EventLevel::kInfo, std::string("the controller at ") + config_.machine.uri + " speaks " +
                                 (firmware == MachineFirmware::kMarlin ? "Marlin" : "GRBL") +
                                 " (set [machine] firmware = \"" +
                                 std::string(MachineFirmwareName(firmware)) + "\" to skip asking)");
  }
  const MachineInfo info = machine_->Connect();
  Event(EventLevel::kInfo, "connected to " + info.description + " at " + config_.machine.uri);
  for (const std::string& note : info.notes) Event(EventLevel::kInfo, note);
  CompareFirmware(info);
}

void RunSession::CompareFirmware(const MachineInfo& info) {
  const MachineSettings& actual = info.settings;
  const MachineSettings& planned = config_.plan.machine;
  // Travel: every planned position must lie inside the controller's soft limits.
  if (info.travel_known) {
    try {
      CheckTravel(plan_, actual, 0.0);
    } catch (const std::exception& e) {
      throw std::runtime_error(
          "the controller's travel (" + info.travel_source + " = " +
          FormatFixed(actual.max_travel_mm.x(), 1) + ", " +
          FormatFixed(actual.max_travel_mm.y(), 1) + ", " +
          FormatFixed(actual.max_travel_mm.z(), 1) + " mm) does not reach the plan: " + e.what() +
          ". Fix the controller's $13x or [plan.machine] max_travel_mm and the rig's "
          "mount in gs360d.toml.");
    }
  }
  // Rates and accelerations: the plan's time estimate assumed [plan.machine]; a controller with
  // others makes the ETA wrong (not the motion: GRBL enforces its own limits).
  const auto differs = [](const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
    return (a - b).cwiseAbs().maxCoeff() > 1e-6;
  };
  if (info.rates_known &&
      (differs(actual.max_rate_mm_per_min, planned.max_rate_mm_per_min) ||
       differs(actual.acceleration_mm_per_s2, planned.acceleration_mm_per_s2))) {
    Event(EventLevel::kWarning,
          "the controller's rates and accelerations (" + info.rates_source + " = " +
              Fmt3(actual.max_rate_mm_per_min) + " mm/min, " + Fmt3(actual.acceleration_mm_per_s2) +
              " mm/s^2) differ from [plan.machine] (" + Fmt3(planned.max_rate_mm_per_min) + ", " +
              Fmt3(planned.acceleration_mm_per_s2) + "): the ETA will be off");
  }
}

std::optional<double> RunSession::HomingLift(const std::vector<Eigen::Vector3d>& where) const {
  if (machine_->HomesZFirst()) return 0.0;
  if (where.empty()) return std::nullopt;
  double lo = where.front().z(), hi = lo;
  for (const Eigen::Vector3d& p : where) {
    lo = std::min(lo, p.z());
    hi = std::max(hi, p.z());
  }
  const double lift = std::max(0.0, travel_->OverZMachine() + config_.plan.travel_clearance - lo);
  if (hi + lift > config_.plan.machine.TravelMax().z() + 1e-9) return std::nullopt;
  // Straight up from each point must stay clear of the sensor (the mount's plane is no gel).
  const double gap = 0.5 * config_.plan.travel_clearance;
  for (const Eigen::Vector3d& p : where) {
    for (double dz = 0.0; dz <= lift + 1e-9; dz += 0.25) {
      const Eigen::Vector3d q = travel_->BallFromMachine(p + Eigen::Vector3d(0.0, 0.0, dz));
      if (travel_->SensorGap(q) < gap) return std::nullopt;
    }
  }
  return lift;
}

std::optional<Ask> RunSession::HomeFrom(const std::vector<Eigen::Vector3d>& where,
                                        const std::string& why) {
  const std::optional<double> lift = HomingLift(where);
  if (!lift && overrides_.confirm != "position") {
    return Ask{"position",
               why + (why.empty() ? "" : "; and ") +
                   "this machine's homing (G28) moves X and Y first, at the tool's height: " +
                   (where.empty()
                        ? std::string("with no motion on record")
                        : "from where the tool may be (last sent to " + Fmt3(where.back()) + ")") +
                   " it cannot be raised above the sensor for certain. Nothing was moved. Raise "
                   "the tool above the sensor by hand, then " +
                   ResumeConfirming() + " (it homes)."};
  }
  if (!lift) {
    Event(EventLevel::kWarning,
          "confirmed by the user: the tool is above the sensor; homing (G28) without raising it");
  }
  Home(lift.value_or(0.0));
  return std::nullopt;
}

void RunSession::Home(double lift_mm) {
  Publish("homing");
  // Killed while it homes, the next session finds the tool off every point of the last path.
  db_.MarkHomingSent(run_id_);
  homing_sent_ = true;
  if (lift_mm > 0.0) {
    Event(EventLevel::kInfo, "raising Z " + FormatFixed(lift_mm, 1) +
                                 " mm before homing: its homing moves X and Y first");
  }
  const MachineReply reply = machine_->Home(lift_mm);
  if (!reply.Ok()) {
    throw std::runtime_error("homing failed at " + config_.machine.uri + ": " + reply.Describe());
  }
}

std::optional<Ask> RunSession::EstablishPosition(const std::vector<Eigen::Vector3d>& sent,
                                                 bool homing_sent) {
  Publish("verifying");
  // Lines sent while it restarted may run after its welcome, a homing cycle may still be on its
  // way: let them finish before looking.
  if (!machine_->Alarmed()) {
    machine_->WaitIdle(homing_sent
                           ? std::max(Ms(config_.engine.sync_timeout_s), machine_->HomingTimeout())
                           : Ms(config_.engine.sync_timeout_s));
  }
  const std::uint64_t stray = machine_->StrayRepliesSinceWelcome();
  const std::optional<Ask> ask = machine_->PositionLost() || stray > 0
                                     ? RecoverLostPosition(sent, stray)
                                     : VerifyPosition(sent, homing_sent);
  if (ask) return ask;
  for (const std::string& line : ProgramPreamble()) {
    const MachineReply r = machine_->WaitForOk(machine_->Send(line), std::chrono::seconds(10));
    if (!r.Ok()) throw std::runtime_error("preamble '" + line + "' failed: " + r.Describe());
  }
  const auto status = machine_->QueryStatus(std::chrono::seconds(5));
  if (!status || !status->machine_position) {
    throw std::runtime_error("the controller at " + config_.machine.uri +
                             " reports no machine position");
  }
  position_ = *status->machine_position;
  last_path_ = {position_};
  at_retract_of_ = (position_ - plan_.start_machine).norm() < 1e-3 ? -1 : -2;
  return std::nullopt;
}

std::string RunSession::ResumeConfirming() const {
  return "`gs360 run resume " + std::to_string(run_id_) + " --confirm position`";
}

std::optional<Ask> RunSession::RecoverLostPosition(const std::vector<Eigen::Vector3d>& sent,
                                                   std::uint64_t stray) {
  const bool confirmed = overrides_.confirm == "position";
  const std::string resume = ResumeConfirming();
  const std::string why =
      machine_->Alarmed()
          ? "the controller is in alarm (" + machine_->AlarmText() + "): its position is lost"
      : machine_->PositionLost()
          ? machine_->AlarmText()
          : "the controller restarted and then executed " + std::to_string(stray) +
                " line(s) sent while it did: where it stands cannot be checked against the "
                "motion sent";
  if (config_.machine.home) {
    // It stopped somewhere on the last motion sent: home only if all of it is clear.
    const bool clear = PathClearOfGel(sent);
    if (!confirmed && !clear) {
      return Ask{"position", why +
                                 ", and the ball may be in or near the gel (it was last sent "
                                 "to " +
                                 Fmt3(sent.back()) + "): homing moves " +
                                 (machine_->HomesZFirst() ? "Z" : "X and Y") +
                                 " first and would drag it. Nothing was moved. "
                                 "Move the tool clear of the sensor by hand, then " +
                                 resume + " (it homes)."};
    }
    if (!clear) {
      Event(EventLevel::kWarning,
            "confirmed by the user: the tool was moved clear of the sensor (" + why +
                "; it was last sent to " + Fmt3(sent.back()) + ", in or near the gel); homing");
      Home(0.0);  // the user moved it: where it was sent says nothing now
      return std::nullopt;
    }
    return HomeFrom(sent, why);
  }
  if (!confirmed) {
    return Ask{"position", why +
                               " and homing is off, so where the tool is cannot be known. "
                               "Nothing was moved. Make the controller's position true "
                               "(or move the tool to where MPos says it is), then " +
                               resume + "."};
  }
  if (machine_->Alarmed()) Unlock();
  machine_->MarkPositionTrusted();
  const auto status = machine_->QueryStatus(std::chrono::seconds(5));
  if (!status || !status->machine_position) {
    throw std::runtime_error("the controller at " + config_.machine.uri +
                             " reports no machine position");
  }
  position_ = *status->machine_position;
  Event(EventLevel::kWarning,
        "position confirmed by the user (" + why + "): MPos " + Fmt3(position_) + " taken as true" +
            (sent.empty() ? "" : "; the tool was last sent to " + Fmt3(sent.back())));
  // As after a verified position: a ball left in the gel comes out along its probe's axis.
  BackOutOfGel();
  return std::nullopt;
}

std::optional<Ask> RunSession::VerifyPosition(const std::vector<Eigen::Vector3d>& sent,
                                              bool homing_sent) {
  const bool confirmed = overrides_.confirm == "position";
  const std::string resume = ResumeConfirming();
  const auto status = machine_->QueryStatus(std::chrono::seconds(5));
  if (!status || !status->machine_position) {
    throw std::runtime_error("the controller at " + config_.machine.uri +
                             " reports no machine position");
  }
  const Eigen::Vector3d reported = *status->machine_position;
  // Lines are executed whole and in order: a controller that kept its position stands where
  // one of the last motion's lines took it (or where it started).
  double nearest = std::numeric_limits<double>::infinity();
  for (const Eigen::Vector3d& p : sent) nearest = std::min(nearest, (reported - p).norm());
  // Idle and not in alarm after a $H: it either never read the $H (and stands on the path) or
  // finished the cycle, which set its position; an interrupted cycle ends in alarm.
  const bool homed = homing_sent && status->state == MachineState::kIdle;
  const bool off_path = !sent.empty() && nearest > config_.machine.verify_tolerance_mm;
  if (!confirmed && off_path && !homed) {
    return Ask{"position",
               "the controller reports MPos " + Fmt3(reported) + " but the tool was last sent to " +
                   Fmt3(sent.back()) + " (" + FormatFixed(nearest, 3) +
                   " mm from any point of that motion): it may have restarted or been moved by "
                   "hand. Nothing was moved. Check the machine, then " +
                   resume + " to take its position as true" +
                   (config_.machine.home ? " (it homes)." : ".")};
  }
  const bool unhomed_start = sent.empty() && !config_.machine.home;
  if (!confirmed && unhomed_start) {
    return Ask{"position", "homing is off: check that the controller's position (MPos " +
                               Fmt3(reported) + ") is where the tool really is, then " + resume +
                               "."};
  }
  // The checks above ran; what the user's confirmation answered goes on record, with the figures.
  if (confirmed && off_path && !homed) {
    Event(EventLevel::kWarning, "position confirmed by the user: the controller reports MPos " +
                                    Fmt3(reported) + ", " + FormatFixed(nearest, 3) +
                                    " mm from any point of the motion last sent (to " +
                                    Fmt3(sent.back()) + "); taken as true");
  } else if (off_path) {
    Event(EventLevel::kInfo,
          "the controller finished the homing cycle sent before the daemon stopped: it stands "
          "at " +
              Fmt3(reported));
  } else if (confirmed && unhomed_start) {
    Event(EventLevel::kWarning, "position confirmed by the user: MPos " + Fmt3(reported) +
                                    " taken as where the tool is (homing is off)");
  } else if (!sent.empty()) {
    Event(EventLevel::kInfo,
          "position verified: the controller stands where the last motion sent took it, " +
              Fmt3(reported));
  }
  machine_->MarkPositionTrusted();
  position_ = reported;
  BackOutOfGel();
  if (config_.machine.home) return HomeFrom({position_}, "");
  return std::nullopt;
}

void RunSession::Unlock() {
  Event(EventLevel::kWarning,
        "unlocking the controller ($X): its position was confirmed by the user");
  const MachineReply unlock = machine_->Unlock();
  if (unlock.Ok()) return;
  // grblHAL refuses $X while its homing lock holds (error:46): only homing clears it.
  throw std::runtime_error("unlock ($X) failed: " + unlock.Describe() +
                           (unlock.error_code == 46
                                ? ". This controller must be homed before it moves: set home = "
                                  "true in [machine] of gs360d.toml (or turn its homing lock "
                                  "off, $22), then resume"
                                : ""));
}

bool RunSession::PathClearOfGel(const std::vector<Eigen::Vector3d>& path) const {
  if (path.empty()) return true;
  const double gap = 0.5 * config_.plan.travel_clearance;
  if (path.size() == 1) return travel_->ToolGaps(travel_->BallFromMachine(path[0])).Min() >= gap;
  for (std::size_t i = 1; i < path.size(); ++i) {
    if (!travel_->SegmentClear(travel_->BallFromMachine(path[i - 1]),
                               travel_->BallFromMachine(path[i]), gap)) {
      return false;
    }
  }
  return true;
}

void RunSession::BackOutOfGel() {
  const Eigen::Vector3d ball = travel_->BallFromMachine(position_);
  // The sensor's own surface: a ball resting on a printer's bed is near the mount's plane, not
  // in the gel (travel lifts it off: TravelPlanner::Path).
  if (travel_->SensorGap(ball) >= 0.5 * config_.plan.travel_clearance) return;
  // The probe whose press axis runs through the ball: straight out along it to its approach.
  Eigen::Vector3d target;
  std::string along;
  double best = 0.25;  // mm from the axis
  for (const PlannedProbe& p : plan_.probes) {
    const Eigen::Vector3d a = travel_->BallFromMachine(p.press_machine);
    const Eigen::Vector3d b = travel_->BallFromMachine(p.approach_machine);
    const double t =
        std::clamp((ball - a).dot(b - a) / std::max(1e-12, (b - a).squaredNorm()), 0.0, 1.0);
    const double d = (ball - (a + t * (b - a))).norm();
    if (d < best) {
      best = d;
      target = p.approach_machine;
      along = "probe " + std::to_string(p.plan_index) + "'s axis";
    }
  }
  if (along.empty()) {
    // Not on any probe's axis: out along the surface's normal where the ball is nearest to it.
    const SurfaceDistance::Closest c = travel_->Distance().ClosestPoint(ball);
    const double out = config_.plan.ball_radius + config_.plan.clearance;
    target = travel_->MachineFromBall(c.point + c.normal * out);
    along = "the surface normal";
  }
  const std::string line = MachineMoveLine(target, config_.plan.press_feed_mm_per_min);
  if (auto bad = Unsafe({line}, position_)) {
    throw std::runtime_error("cannot back out of the gel from " + Fmt3(position_) + ": " + *bad);
  }
  Publish("backing out");
  Commanded({line}, position_);
  const MachineReply r =
      machine_->WaitForOk(machine_->Send(line), Ms(config_.engine.sync_timeout_s));
  if (!r.Ok()) throw std::runtime_error("backing out of the gel failed: " + r.Describe());
  machine_->WaitIdle(Ms(config_.engine.sync_timeout_s));
  Event(EventLevel::kInfo, "the tool was in or near the gel at " + Fmt3(position_) +
                               ": backed out along " + along + " to " + Fmt3(target));
  position_ = target;
  at_retract_of_ = -2;
}

void RunSession::Commanded(const std::vector<std::string>& lines, const Eigen::Vector3d& from) {
  std::vector<Eigen::Vector3d> targets;
  for (const std::string& line : lines) {
    if (const auto target = session::MotionTarget(line)) targets.push_back(*target);
  }
  if (targets.empty()) return;
  // Until a sync shows where the controller stands, it may stand at any point sent since: a
  // retract sent without waiting, then refused after a reset, leaves the tool at the press.
  if (last_path_.empty() || (last_path_.back() - from).norm() > 1e-6) last_path_.push_back(from);
  last_path_.insert(last_path_.end(), targets.begin(), targets.end());
  db_.SetCommandedPath(run_id_, last_path_);
  homing_sent_ = false;
}

void RunSession::ReturnToSafety(const PlannedProbe& planned) {
  // After a failed line the tool may be anywhere on this probe's way in; its approach point is
  // straight out along the normal, so going there first is always clear.
  machine_->WaitIdle(Ms(config_.engine.sync_timeout_s));
  const auto status = machine_->QueryStatus(std::chrono::seconds(2));
  if (status && status->machine_position) position_ = *status->machine_position;
  const TravelPlanner::Gaps gaps = travel_->ToolGaps(travel_->BallFromMachine(position_));
  if (gaps.Min() < config_.plan.travel_clearance * 0.5) {
    const std::string line = MachineMoveLine(planned.approach_machine);
    if (Unsafe({line}, position_)) return;
    Commanded({line}, position_);
    const MachineReply r =
        machine_->WaitForOk(machine_->Send(line), Ms(config_.engine.sync_timeout_s));
    if (r.Ok()) position_ = planned.approach_machine;
  }
  at_retract_of_ = -2;
}

bool RunSession::Recover(const Step& step) {
  if (++recoveries_ > config_.engine.max_recoveries) return false;
  ++report_.recoveries;
  Event(EventLevel::kWarning, step.message + "; recovering (" + std::to_string(recoveries_) + "/" +
                                  std::to_string(config_.engine.max_recoveries) + ")");
  if (step.kind == StepKind::kDisconnected || !machine_->Connected()) {
    Publish("reconnecting");
    if (!machine_->Reconnect(Ms(config_.engine.reconnect_timeout_s))) {
      Event(EventLevel::kError, "the controller at " + config_.machine.uri +
                                    " did not come back within " +
                                    FormatFixed(config_.engine.reconnect_timeout_s, 0) + " s");
      return false;
    }
  } else if (step.kind == StepKind::kStall) {
    // A controller that stopped answering: a soft reset voids whatever it still holds.
    if (!machine_->SoftReset()) return false;
  }
  try {
    // The controller may have reset: where the tool is must be known before anything moves.
    if (auto ask = EstablishPosition(last_path_, homing_sent_)) {
      ask_ = std::move(ask);
      return false;
    }
  } catch (const std::exception& e) {
    Event(EventLevel::kError, std::string("after recovery: ") + e.what());
    return false;
  }
  return true;
}

std::vector<RunSession::RecheckPick> RunSession::PickRecheckProbes(
    const std::vector<CapturedProbe>& captured, int want) const {
  // Spread over the run (early, middle, late); from each spot the nearest probe whose stored
  // impression is clear, looking at most kSearch probes either way.
  constexpr int kSearch = 12;
  std::vector<RecheckPick> picks;
  std::vector<bool> taken(captured.size(), false);
  const auto n = static_cast<std::ptrdiff_t>(captured.size());
  for (int i = 0; i < want; ++i) {
    const std::ptrdiff_t spot =
        want == 1 ? n - 1 : static_cast<std::ptrdiff_t>(i) * (n - 1) / (want - 1);
    for (int step = 0; step <= 2 * kSearch; ++step) {
      const std::ptrdiff_t k = spot + (step % 2 == 0 ? step / 2 : -(step + 1) / 2);
      if (k < 0 || k >= n || taken[static_cast<std::size_t>(k)]) continue;
      const CapturedProbe& probe = captured[static_cast<std::size_t>(k)];
      const auto ref_info = db_.NearestReferenceFrame(run_id_, probe.frame_time);
      if (!ref_info) continue;
      cv::Mat press = db_.LoadFrame(probe.frame_id);
      cv::Mat reference = db_.LoadFrame(ref_info->id);
      const auto stored = FindClearImpression(press, reference, config_.engine.recheck_min_peak_dn);
      if (!stored) continue;
      taken[static_cast<std::size_t>(k)] = true;
      picks.push_back({&probe, *stored, std::move(press), std::move(reference)});
      break;
    }
  }
  return picks;
}

std::optional<Ask> RunSession::RecheckSensor() {
  const auto captured = db_.ListCapturedProbes(run_id_);
  const int want = std::min<int>(config_.engine.recheck_probes, static_cast<int>(captured.size()));
  if (want == 0) return std::nullopt;
  Publish("rechecking");
  const std::vector<RecheckPick> picks = PickRecheckProbes(captured, want);
  cv::Mat reference;
  int compared = 0;
  double worst = 0.0;
  for (std::size_t k = 0; k < picks.size(); ++k) {
    const CapturedProbe& old = *picks[k].probe;
    const PlannedProbe& planned = plan_.probes.at(static_cast<std::size_t>(old.probe.plan_index));
    Press press;
    const Step step = PressProbe(planned, k == 0, &press);
    if (step.kind != StepKind::kOk) {
      return Ask{"", "re-pressing probe " + std::to_string(old.probe.plan_index) +
                         " failed: " + step.message};
    }
    if (k == 0) reference = press.reference;
    if (reference.empty()) continue;
    const Impression& a = picks[k].stored;
    const auto b = FindClearImpression(press.frame, reference, config_.engine.recheck_min_peak_dn);
    if (!b) continue;
    // Not the two centroids' distance: where each capture's threshold cuts the blob moves them
    // by 1 to 40 px with nothing moved (capture/impression.h).
    const ImpressionShift moved =
        MeasureImpressionShift(picks[k].press, picks[k].reference, a, press.frame, reference);
    const double shift = ImpressionDistance(moved, a, *b);
    const Eigen::Vector2d now_at =
        shift > moved.px.norm() ? b->centroid : Eigen::Vector2d(a.centroid + moved.px);
    worst = std::max(worst, shift);
    ++compared;
    if (shift > config_.engine.recheck_max_shift_px) {
      return Ask{"", "the sensor has moved since the run was interrupted: probe " +
                         std::to_string(old.probe.plan_index) + "'s impression was at (" +
                         FormatFixed(a.centroid.x(), 1) + ", " + FormatFixed(a.centroid.y(), 1) +
                         ") px and is now at (" + FormatFixed(now_at.x(), 1) + ", " +
                         FormatFixed(now_at.y(), 1) + ") px, a shift of " + FormatFixed(shift, 2) +
                         " px (limit " + FormatFixed(config_.engine.recheck_max_shift_px, 2) +
                         "). Re-seat the sensor exactly as before, or start a new run."};
    }
  }
  if (compared == 0) {
    const std::string why =
        (picks.empty()
             ? "resume: no committed probe near the " + std::to_string(want) +
                   " spots checked has a clear stored impression (engine.recheck_min_peak_dn)"
             : "resume: none of the " + std::to_string(picks.size()) +
                   " re-pressed probes showed a clear impression to compare with its stored "
                   "frame") +
        ", so the sensor's position could not be verified";
    if (overrides_.confirm != "sensor" && config_.engine.unverified_resume == "ask") {
      return Ask{"sensor", why +
                               ". Nothing else was pressed. Check that the sensor sits as it "
                               "did, then `gs360 run resume " +
                               std::to_string(run_id_) + " --confirm sensor`."};
    }
    Event(EventLevel::kWarning, why + (overrides_.confirm == "sensor"
                                           ? ": going on, as the user confirmed"
                                           : ": going on (engine.unverified_resume = continue)"));
  } else {
    Event(EventLevel::kInfo, "resume: " + std::to_string(compared) +
                                 " re-pressed probes match their stored frames (largest shift " +
                                 FormatFixed(worst, 2) + " px)");
  }
  return std::nullopt;
}

void RunSession::Park() {
  Publish("parking");
  const auto path = travel_->Path(position_, plan_.start_machine);
  if (!path) {
    Event(EventLevel::kWarning,
          "no clear path back to the start position; the tool stays at " + Fmt3(position_));
    return;
  }
  std::vector<std::string> lines = TravelLines(*path);
  lines.push_back(MachineMoveLine(plan_.start_machine));
  if (auto bad = Unsafe(lines, position_)) {
    Event(EventLevel::kError, "not parking: " + *bad);
    return;
  }
  Commanded(lines, position_);
  for (const auto& line : lines) machine_->Send(line);
  position_ = plan_.start_machine;
  machine_->WaitIdle(Ms(config_.engine.sync_timeout_s));
}

}  // namespace gs360
