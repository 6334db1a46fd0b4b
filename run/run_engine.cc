#include "run/run_engine.h"
#include "base/format.h"
#include "run/run_session.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <future>
#include <optional>
#include <stdexcept>
#include <thread>

#include <spdlog/spdlog.h>
#include <nlohmann/json.hpp>

#include "base/hash.h"
#include "base/json_reader.h"
#include "capture/capture_press.h"
#include "capture/frame_source.h"
#include "capture/impression.h"
#include "gcode/probe_program.h"

namespace gs360 {
namespace {}  // namespace

using session::Clock;
using session::Fmt3;
using session::Ms;
using session::Press;
using session::Step;
using session::StepKind;

std::string session::Fmt3(const Eigen::Vector3d& v) {
  return "(" + FormatFixed(v.x(), 3) + ", " + FormatFixed(v.y(), 3) + ", " + FormatFixed(v.z(), 3) +
         ")";
}

std::string_view ToString(RunOutcome outcome) {
  switch (outcome) {
    case RunOutcome::kDone:
      return "done";
    case RunOutcome::kPaused:
      return "paused";
    case RunOutcome::kStopped:
      return "stopped";
    case RunOutcome::kCancelled:
      return "cancelled";
    case RunOutcome::kFailed:
      return "failed";
    case RunOutcome::kAwaiting:
      return "awaiting confirmation";
  }
  return "unknown";
}

// ---------------------------------------------------------------------------------------------

void RunSession::LoadRun() {
  const auto run = db_.GetRun(run_id_);
  if (!run)
    throw std::runtime_error("no run " + std::to_string(run_id_) + " in " + db_.path().string());
  if (IsTerminal(run->state)) {
    throw std::runtime_error("run " + std::to_string(run_id_) + " is already " +
                             std::string(ToString(run->state)) + "; nothing to resume");
  }
  const std::string where = db_.path().string() + " (run " + std::to_string(run_id_) + " config)";
  config_ = RunConfigFromJson(ParseJsonText(run->config_json, where), where);
  if (!overrides_.machine_uri.empty() && overrides_.machine_uri != config_.machine.uri) {
    Event(EventLevel::kInfo, "this session uses the controller at " + overrides_.machine_uri +
                                 " (configured: " + config_.machine.uri + ")");
    config_.machine.uri = overrides_.machine_uri;
  }
  if (!overrides_.camera_uri.empty() && overrides_.camera_uri != config_.camera.uri) {
    Event(EventLevel::kInfo, "this session uses the camera " + overrides_.camera_uri +
                                 " (configured: " + config_.camera.uri + ")");
    config_.camera.uri = overrides_.camera_uri;
  }
  plan_ = RunEngine::LoadPlan(db_, run_id_);
  travel_ = std::make_shared<TravelPlanner>(MakeRigGeometry(config_.rig), config_.plan);
  camera_ = std::make_unique<FisheyeCamera>(config_.rig.camera);
  if (config_.engine.require_impression && config_.engine.impression_min_contrast == 0.0) {
    PressCheckOptions check;
    check.radius_px = config_.engine.impression_radius_px;
    check.min_snr = config_.engine.impression_min_snr;
    check.seed = static_cast<std::uint64_t>(run_id_);
    std::vector<Eigen::Vector2d> plan_px;
    const Rigid3d cam_from_sensor = config_.rig.cam_from_sensor();
    for (const PlannedProbe& p : plan_.probes) {
      if (const auto px = camera_->CamToPixel(cam_from_sensor * p.point_sensor)) {
        plan_px.push_back(*px);
      }
    }
    press_check_ = std::make_unique<PressCheck>(check, std::move(plan_px));
  }
  if (engine_.limits_) {
    guard_ = std::make_unique<SafetyGuard>(*engine_.limits_, travel_, config_.rig.ball_radius,
                                           config_.rig.gel_thickness);
  }
  references_.every_m_probes = config_.plan.reference_every;
  const ProbeCounts counts = db_.CountProbes(run_id_);
  if (counts.total != static_cast<std::int64_t>(plan_.probes.size())) {
    throw std::runtime_error("run " + std::to_string(run_id_) + ": the stored plan has " +
                             std::to_string(plan_.probes.size()) + " probes but the database " +
                             std::to_string(counts.total));
  }
  probes_done_ = counts.captured + counts.skipped;
}

void RunSession::Publish(const std::string& phase, int plan_index) {
  RunProgress p;
  p.run_id = run_id_;
  p.counts = db_.CountProbes(run_id_);
  const RunStatus status = db_.GetRunStatus(run_id_);
  p.elapsed_s = status.elapsed_s;
  p.phase = phase;
  p.plan_index = plan_index;
  if (machine_) {
    p.machine_connected = machine_->Connected();
    if (const auto sample = machine_->LatestStatus()) {
      p.machine_state = sample->state_text;
      p.machine_position = sample->machine_position;
    }
  }
  const double remaining = static_cast<double>(p.counts.planned + p.counts.failed);
  if (recent_probe_s_ > 0.0) {
    p.probes_per_hour = 3600.0 / recent_probe_s_;
    p.eta_s = remaining * recent_probe_s_;
  } else if (!plan_.probes.empty()) {
    p.eta_s = plan_.estimate.Total() * remaining / static_cast<double>(plan_.probes.size());
  }
  engine_.Publish(p);
}

std::optional<std::vector<Eigen::Vector3d>> RunSession::TravelTo(const PlannedProbe& planned) {
  // Consecutive in plan order: the planner's waypoints are valid from where we are.
  if (at_retract_of_ == planned.plan_index - 1) return planned.travel_machine;
  return travel_->Path(position_, planned.approach_machine);
}

Step RunSession::Classify(const std::vector<MachineHandle>& handles) {
  // Replies come in order, so once the last line is answered every earlier one is too.
  for (const MachineHandle& h : handles) {
    const MachineReply r = h.Wait(std::chrono::milliseconds(0));
    if (r.alarm || machine_->Alarmed()) {
      return {StepKind::kAlarm,
              (r.alarm ? *r.alarm : machine_->AlarmText()) + " after '" + r.line + "'"};
    }
    switch (r.kind) {
      case MachineReplyKind::kOk:
        break;
      case MachineReplyKind::kError:
        return {StepKind::kProbeError, r.error + " on '" + r.line + "'"};
      case MachineReplyKind::kReset:
        return {StepKind::kReset, "controller reset: " + r.Describe()};
      case MachineReplyKind::kRefused:
        return {machine_->Alarmed() ? StepKind::kAlarm : StepKind::kReset,
                "line refused: " + r.Describe()};
      case MachineReplyKind::kDisconnected:
      case MachineReplyKind::kClosed:
        return {StepKind::kDisconnected, "controller disconnected: " + r.Describe()};
      case MachineReplyKind::kTimeout:
        return {StepKind::kStall, "no reply within " +
                                      FormatFixed(config_.engine.sync_timeout_s, 0) + " s to '" +
                                      r.line + "'"};
    }
  }
  return {StepKind::kOk, ""};
}

std::optional<std::string> RunSession::Unsafe(const std::vector<std::string>& lines,
                                              const Eigen::Vector3d& from) {
  if (!guard_) return std::nullopt;
  Eigen::Vector3d at = from;
  for (const std::string& line : lines) {
    if (auto bad = guard_->CheckLine(line, at)) {
      safety_stop_ = "refused to send '" + line + "': " + *bad;
      return safety_stop_;
    }
    if (const auto target = session::MotionTarget(line)) at = *target;
  }
  return std::nullopt;
}

session::LostReplyWatch::LostReplyWatch(Machine& machine, const std::vector<std::string>& lines)
    : machine_(machine), garbled_before_(machine.UnreadableLines()), sent_at_(Clock::now()) {
  // Idle covers a dwell too (GRBL reports Idle in G4): wait it out, and then some.
  for (const std::string& line : lines) {
    const std::size_t g4 = line.find("G4");
    const std::size_t p = line.find('P', g4 == std::string::npos ? line.size() : g4);
    if (p != std::string::npos) dwell_s_ += std::strtod(line.c_str() + p + 1, nullptr);
  }
}

bool session::LostReplyWatch::Lost() {
  // The poller's latest report, or a fresh one when it is old (or the poller is off).
  if (!machine_.RepliesCanBeLost()) return false;
  std::optional<MachineStatus> status = machine_.LatestStatus();
  const auto now = Clock::now();
  if (!status || now - status->received_at > std::chrono::milliseconds(300)) {
    if (now < next_query_) return false;
    next_query_ = now + std::chrono::milliseconds(250);
    status = machine_.QueryStatus(std::chrono::milliseconds(500));
  }
  if (!status || status->received_at <= sent_at_) return false;
  if (status->state != MachineState::kIdle) {
    idle_since_.reset();
    return false;
  }
  if (!idle_since_) idle_since_ = status->received_at;
  const double quiet = dwell_s_ + (Garbled() > 0 ? kLostReplyQuietS : kLostLineQuietS);
  return status->received_at - *idle_since_ >= Ms(quiet);
}

std::uint64_t session::LostReplyWatch::Garbled() const {
  return machine_.UnreadableLines() - garbled_before_;
}

Step RunSession::SendAndSync(const std::vector<std::string>& lines, Clock::time_point* sync_at) {
  if (auto bad = Unsafe(lines, position_)) return {StepKind::kSafety, *bad};
  Commanded(lines, position_);
  std::vector<MachineHandle> handles;
  handles.reserve(lines.size());
  session::LostReplyWatch lost(*machine_, lines);  // before sending: replies come at once
  for (const std::string& line : lines) handles.push_back(machine_->Send(line));
  // An alarm on an earlier line leaves the later ones unanswered (GRBL flushes nothing and waits
  // for a reset): stop waiting as soon as the controller is in alarm or gone, not at the timeout.
  const auto deadline = Clock::now() + Ms(config_.engine.sync_timeout_s);
  MachineReply last;
  for (;;) {
    last = machine_->WaitForOk(handles.back(), std::chrono::milliseconds(100));
    if (last.kind != MachineReplyKind::kTimeout) break;
    if (machine_->Alarmed() || !machine_->Connected() || Clock::now() >= deadline) break;
    if (machine_->Held()) {
      return {StepKind::kHeld, "the controller went into a feed hold during '" + lines.back() +
                                   "' (a hold button, or noise on the serial line read as '!')"};
    }
    if (lost.Lost()) {
      const std::uint64_t garbled = lost.Garbled();
      return {StepKind::kStall,
              "the controller stands idle with '" + lines.back() + "' unanswered: " +
                  (garbled > 0 ? "a reply was lost (the serial line brought " +
                                     std::to_string(garbled) + " unreadable line(s))"
                               : std::string("a line or its reply was lost on the serial line"))};
    }
  }
  Step step = Classify(handles);
  if (step.kind == StepKind::kOk) {
    *sync_at = last.received_at;
    if (!last_path_.empty()) last_path_ = {last_path_.back()};  // all executed: at the end
  }
  return step;
}

std::string RunSession::CaptureFailure(const std::string& what, const PressCaptureResult& r) {
  return what + ": " + std::string(ToString(r.status)) + " (" + std::to_string(r.frames_used) +
         " frames, " + std::to_string(r.stale_dropped) + " stale" +
         (r.status == PressCaptureStatus::kInconsistent
              ? ", no " + std::to_string(config_.camera.capture.frames_to_average) +
                    " of them agree: a camera or transfer fault?"
              : std::string()) +
         ")";
}

void RunSession::NoteOutliers(const std::string& what, int plan_index,
                              const PressCaptureResult& r) {
  if (r.outliers_rejected == 0) return;
  Event(EventLevel::kWarning, "probe " + std::to_string(plan_index) + ": " +
                                  std::to_string(r.outliers_rejected) + " camera frame(s) of the " +
                                  what +
                                  " left out: they disagreed with the others (a camera or "
                                  "transfer fault?)");
}

Step RunSession::TakeReference(const PlannedProbe& planned, const ProbeProgram& program,
                               Press* out) {
  Clock::time_point sync;
  Step step = SendAndSync(program.reference, &sync);
  position_ = planned.approach_machine;
  at_retract_of_ = -2;
  if (step.kind != StepKind::kOk) return step;
  const PressCaptureResult ref = CapturePress(*source_, sync, config_.camera.capture);
  if (!ref.ok()) return {StepKind::kProbeError, CaptureFailure("reference frame", ref)};
  NoteOutliers("reference frame", planned.plan_index, ref);
  if (press_check_) {
    // The same still scene again: its difference from the first is the camera's noise alone.
    const PressCaptureResult second = CapturePress(*source_, sync, config_.camera.capture);
    if (!second.ok()) {
      return {StepKind::kProbeError, CaptureFailure("second reference frame", second)};
    }
    NoteOutliers("second reference frame", planned.plan_index, second);
    press_check_->SetReference(ref.image, second.image);
  }
  db_.AddReferenceFrame(run_id_, ref.image, ToUnix(ref.last_timestamp));
  last_reference_at_ = probes_done_;
  out->reference = ref.image;
  session_reference_ = ref.image;
  return step;
}

Step RunSession::PressProbe(const PlannedProbe& planned_in, bool take_reference, Press* out) {
  last_check_.reset();
  const auto path = TravelTo(planned_in);
  if (!path) {
    return {StepKind::kProbeError, "no collision-free travel from " + Fmt3(position_) +
                                       " to the approach " + Fmt3(planned_in.approach_machine)};
  }
  PlannedProbe planned = planned_in;
  planned.travel_machine = *path;
  planned.reference_before = take_reference;
  const ProbeProgram program = MakeProbeProgram(planned, config_.plan);

  if (take_reference) {
    Step step = TakeReference(planned, program, out);
    if (step.kind != StepKind::kOk) return step;
  }

  Clock::time_point sync;
  Step step = SendAndSync(program.press, &sync);
  position_ = planned.press_machine;
  at_retract_of_ = -2;
  if (step.kind != StepKind::kOk) return step;

  // The status report (MPos) is fetched while the frames are being taken.
  auto status = std::async(std::launch::async,
                           [this] { return machine_->QueryStatus(std::chrono::seconds(2)); });
  const PressCaptureResult capture = CapturePress(*source_, sync, config_.camera.capture);
  const auto sample = status.get();
  SendRetract(program, planned);
  if (!capture.ok()) return {StepKind::kProbeError, CaptureFailure("press frame", capture)};
  NoteOutliers("press frame", planned.plan_index, capture);
  if (!sample || !sample->machine_position) {
    return {StepKind::kProbeError, "no status report (machine position) after the press"};
  }
  // GRBL lines carry no checksum: a garbled digit can still parse as a valid move. The machine
  // must report the press position before the frame counts as that probe's. Checked before the
  // impression: a press elsewhere leaves none here, and is pressed again.
  const double off = (*sample->machine_position - planned.press_machine).norm();
  if (off > config_.machine.verify_tolerance_mm) {
    return {StepKind::kProbeError, "the machine reports " + Fmt3(*sample->machine_position) +
                                       " instead of the press position " +
                                       Fmt3(planned.press_machine) + " (" + FormatFixed(off, 3) +
                                       " mm off: a corrupted line?)"};
  }
  // A press that left no mark (the ball missed the gel, the sensor moved, the camera froze) is
  // not a calibration sample.
  if (auto failed = CheckImpression(planned, capture.image)) return *failed;
  out->frame = capture.image;
  out->mpos = *sample->machine_position;
  out->sync = sync;
  out->frame_time = capture.last_timestamp;
  return {StepKind::kOk, ""};
}

std::optional<Step> RunSession::CheckImpression(const PlannedProbe& planned, const cv::Mat& frame) {
  if (!config_.engine.require_impression || session_reference_.empty()) return std::nullopt;
  const auto expected = camera_->CamToPixel(config_.rig.cam_from_sensor() * planned.point_sensor);
  if (!expected) return std::nullopt;
  const std::string near =
      "near pixel (" + FormatFixed(expected->x(), 0) + ", " + FormatFixed(expected->y(), 0) + ")";
  if (!press_check_) {  // a run stored before the signal-to-noise check
    const double contrast = ImpressionContrast(frame, session_reference_, *expected,
                                               config_.engine.impression_radius_px);
    if (contrast >= config_.engine.impression_min_contrast) return std::nullopt;
    return Step{StepKind::kProbeError, "no impression in the press frame " + near + ": contrast " +
                                           FormatFixed(contrast, 2) +
                                           " against the session's reference frame (at least " +
                                           FormatFixed(config_.engine.impression_min_contrast, 2) +
                                           "); the ball did not mark the gel where planned"};
  }
  const PressCheckResult r = press_check_->Check(frame, *expected);
  last_check_ = r;
  switch (r.verdict) {
    case PressVerdict::kImpression:
      return std::nullopt;
    case PressVerdict::kFrozen:
      return Step{StepKind::kProbeError,
                  std::string("the press frame is identical to ") +
                      (r.frozen_on_reference ? "the session's reference frame"
                                             : "the previous press frame") +
                      ": the camera delivers a frozen picture"};
    case PressVerdict::kChangedEverywhere:
      last_reference_at_.reset();  // the next press starts with a fresh one
      return Step{StepKind::kProbeError,
                  "the press frame differs from the reference frame away from the press too "
                  "(signal-to-noise " +
                      FormatFixed(r.null_snr, 1) + " where nothing was pressed, " +
                      FormatFixed(r.threshold, 1) +
                      " counts as a press): the light or the camera changed; a fresh reference "
                      "frame is taken"};
    case PressVerdict::kNoImpression:
      break;
  }
  const std::string limit =
      r.null_samples > 0
          ? "from this session's frames at " + std::to_string(r.null_samples) +
                " places where nothing was pressed"
          : (config_.engine.impression_min_snr > 0.0 ? std::string("engine.impression_min_snr")
                                                     : std::string("the least any session needs"));
  return Step{StepKind::kProbeError,
              "no impression in the press frame " + near + ": signal-to-noise " +
                  FormatFixed(r.press.snr, 1) + ", at least " + FormatFixed(r.threshold, 1) +
                  " needed (" + limit +
                  "); the ball did not mark the gel there, or something hides the spot from the "
                  "camera. Not pressed again: a second press would show the same",
              /*retry=*/false};
}

void RunSession::ReportImpressions() {
  if (press_check_ && impression_regions_.Presses() > 0) {
    Event(EventLevel::kInfo,
          "impression check: " + std::to_string(impression_regions_.Presses()) +
              " presses, signal-to-noise median " +
              FormatFixed(impression_regions_.MedianSnr(), 1) + ", weakest counted " +
              FormatFixed(impression_regions_.WeakestCounted(), 1) + "; needed " +
              FormatFixed(press_check_->Threshold(), 1) + " (from " +
              std::to_string(press_check_->NullSamples()) +
              " places where nothing was pressed: median " +
              FormatFixed(press_check_->NullQuantile(0.5), 1) + ", 99th percentile " +
              FormatFixed(press_check_->NullQuantile(0.99), 1) + ", largest " +
              FormatFixed(press_check_->NullQuantile(1.0), 1) + ")");
  }
  constexpr std::size_t kMaxNamed = 8;
  const std::vector<WeakRegion> regions = impression_regions_.WeakRegions();
  for (std::size_t i = 0; i < regions.size() && i < kMaxNamed; ++i) {
    Event(EventLevel::kWarning, regions[i].Describe());
  }
  if (regions.size() > kMaxNamed) {
    Event(EventLevel::kWarning, std::to_string(regions.size() - kMaxNamed) +
                                    " more regions with weak impressions (the largest are named)");
  }
  impression_regions_ = ImpressionRegionTally();  // each is said once
}

void RunSession::TallyImpression(const PlannedProbe& planned) {
  if (last_check_ && (last_check_->verdict == PressVerdict::kImpression ||
                      last_check_->verdict == PressVerdict::kNoImpression)) {
    impression_regions_.Add(planned.point_sensor, last_check_->press.snr, last_check_->threshold,
                            last_check_->press.reference_dn);
  }
  last_check_.reset();
}

void RunSession::SendRetract(const ProbeProgram& program, const PlannedProbe& planned) {
  if (Unsafe(program.retract, position_)) return;
  Commanded(program.retract, position_);
  for (const std::string& line : program.retract) machine_->Send(line);
  position_ = planned.retract_machine;
  at_retract_of_ = planned.plan_index;
}

void RunSession::SettleAndRecord() {
  if (!machine_ || !machine_->Connected() || machine_->Alarmed() || machine_->Held() ||
      !machine_->PositionTrusted()) {
    return;
  }
  // The motion sent has ended where it was sent: the next session starts from one known point.
  if (machine_->WaitIdle(Ms(config_.engine.sync_timeout_s)) == MachineWaitResult::kIdle &&
      !last_path_.empty()) {
    last_path_ = {last_path_.back()};
    db_.SetCommandedPath(run_id_, last_path_);
    homing_sent_ = false;
  }
}

RunReport RunSession::Awaiting(const Ask& ask) {
  committer_.Wait();
  report_.outcome = RunOutcome::kAwaiting;
  report_.message = ask.message;
  SettleAndRecord();
  if (db_.GetRun(run_id_)->state == RunState::kRunning) {
    db_.SetRunState(run_id_, RunState::kInterrupted);
  }
  spdlog::warn("run {}: waiting for the user to confirm the {}: {}", run_id_, ask.what,
               ask.message);
  db_.SetRunAwaiting(run_id_, ask.what, ask.message);
  report_.counts = db_.CountProbes(run_id_);
  report_.seconds = std::chrono::duration<double>(Clock::now() - session_start_).count();
  Publish("idle");
  return report_;
}

RunReport RunSession::Run() {
  LoadRun();
  if (!overrides_.confirm.empty() && db_.GetRun(run_id_)->awaiting.empty()) {
    // Nobody asked: the checks run and ask as if it had not been given (the daemon refuses it).
    Event(EventLevel::kWarning, "a confirmation of the " + overrides_.confirm +
                                    " that the run did not ask for is ignored");
    overrides_.confirm.clear();
  }
  if (const auto run = db_.GetRun(run_id_);
      !run->awaiting.empty() && overrides_.confirm != run->awaiting) {
    // Still waiting for the user: a fresh look at the machine cannot answer what a restart or
    // a failed check left open (its MPos may even agree with the motion sent). Nothing is
    // opened, nothing moves.
    report_.outcome = RunOutcome::kAwaiting;
    report_.message = run->last_error;
    report_.counts = db_.CountProbes(run_id_);
    return report_;
  }
  const bool resuming = db_.CountProbes(run_id_).captured > 0;
  source_ = OpenFrameSource(config_.camera.uri, config_.camera.controls);
  source_->Start();
  ConnectMachine();
  const RunRecord run = *db_.GetRun(run_id_);
  if (auto ask = EstablishPosition(run.commanded_path, run.homing_sent)) {
    return Awaiting(*ask);
  }
  db_.SetRunState(run_id_, RunState::kRunning);
  Event(EventLevel::kInfo, std::string(resuming ? "resumed" : "started") + ": " +
                               std::to_string(db_.CountProbes(run_id_).planned) + " probes to go");
  if (resuming && config_.engine.recheck_probes > 0) {
    if (auto problem = RecheckSensor()) {
      if (problem->what.empty()) {
        return Finish(RunOutcome::kFailed, RunState::kInterrupted, problem->message);
      }
      return Awaiting(*problem);
    }
  }
  // A confirmation answers the question asked before this session; a later one (a restart
  // mid-run) is asked again.
  overrides_.confirm.clear();
  last_reference_at_.reset();  // every session starts with a fresh reference frame
  return ProbeLoop();
}

RunReport RunSession::Finish(RunOutcome outcome, RunState state, const std::string& message) {
  committer_.Wait();
  ReportImpressions();
  report_.outcome = outcome;
  report_.message = message;
  SettleAndRecord();
  db_.SetRunState(run_id_, state);
  if (outcome == RunOutcome::kFailed) {
    spdlog::error("run {}: {}", run_id_, message);
    db_.SetRunError(run_id_, message);
  } else {
    Event(EventLevel::kInfo, message);
  }
  report_.counts = db_.CountProbes(run_id_);
  report_.seconds = std::chrono::duration<double>(Clock::now() - session_start_).count();
  Publish("idle");
  return report_;
}

std::optional<RunReport> RunSession::OnRequest() {
  switch (engine_.request_.load()) {
    case 1:
      return Finish(RunOutcome::kStopped, RunState::kInterrupted, "stopped on request");
    case 2:
      return Finish(RunOutcome::kPaused, RunState::kPaused, "paused");
    case 3:
      Park();
      return Finish(RunOutcome::kCancelled, RunState::kCancelled,
                    "cancelled; the captured probes are kept");
    case 4: {
      // Ends the run early (it has converged): what is left of the plan is skipped, not lost.
      committer_.Wait();
      const std::string why = engine_.FinishReason();
      const std::int64_t skipped = db_.SkipOpenProbes(run_id_, why);
      Park();
      const ProbeCounts counts = db_.CountProbes(run_id_);
      return Finish(RunOutcome::kDone, RunState::kDone,
                    "done early (" + why + "): " + std::to_string(counts.captured) + " captured, " +
                        std::to_string(skipped) + " planned probes skipped");
    }
    default:
      return std::nullopt;
  }
}

RunReport RunSession::ProbeLoop() {
  for (;;) {
    if (auto report = OnRequest()) return *report;
    if (safety_stop_) {
      return Finish(RunOutcome::kFailed, RunState::kInterrupted,
                    "safety limit: " + *safety_stop_ + ". Nothing of that line was sent.");
    }
    const auto probe =
        db_.NextPendingProbe(run_id_, config_.engine.max_attempts, committer_.InFlight());
    if (!probe) break;
    const PlannedProbe& planned = plan_.probes.at(static_cast<std::size_t>(probe->plan_index));
    if ((planned.press_machine - probe->plan.press_machine).norm() > 1e-6) {
      return Finish(
          RunOutcome::kFailed, RunState::kInterrupted,
          "stored plan and probe rows disagree at plan index " + std::to_string(probe->plan_index));
    }
    Publish("probing", probe->plan_index);
    const auto t0 = Clock::now();
    const bool take_reference = references_.NeedsReference(probes_done_, last_reference_at_);
    Press press;
    const Step step = PressProbe(planned, take_reference, &press);
    if (auto report = AfterPress(step, *probe, planned, press, t0)) return *report;
  }
  committer_.Wait();
  Park();
  const ProbeCounts counts = db_.CountProbes(run_id_);
  return Finish(RunOutcome::kDone, RunState::kDone,
                "done: " + std::to_string(counts.captured) + " captured, " +
                    std::to_string(counts.failed) + " failed, " + std::to_string(counts.skipped) +
                    " skipped");
}

std::optional<RunReport> RunSession::AfterPress(const Step& step, const ProbeRecord& probe,
                                                const PlannedProbe& planned, const Press& press,
                                                Clock::time_point t0) {
  switch (step.kind) {
    case StepKind::kOk: {
      TallyImpression(planned);
      CaptureReport report;
      report.machine_position = press.mpos;
      report.sync_time = ToUnix(press.sync);
      report.frame_time = ToUnix(press.frame_time);
      committer_.Submit(probe.id, press.frame, report);
      ++report_.captured;
      ++probes_done_;
      const double dt = std::chrono::duration<double>(Clock::now() - t0).count();
      recent_probe_s_ = recent_probe_s_ > 0.0 ? 0.9 * recent_probe_s_ + 0.1 * dt : dt;
      return std::nullopt;
    }
    case StepKind::kProbeError:
      TallyImpression(planned);
      db_.MarkProbeFailed(probe.id, step.message, step.retry);
      ++report_.failed;
      Event(EventLevel::kWarning,
            "probe " + std::to_string(probe.plan_index) + " failed: " + step.message);
      ReturnToSafety(planned);
      return std::nullopt;
    case StepKind::kAlarm:
      db_.MarkProbeFailed(probe.id, step.message);
      ++report_.failed;
      return Finish(RunOutcome::kFailed, RunState::kInterrupted,
                    "the machine raised an alarm at probe " + std::to_string(probe.plan_index) +
                        ": " + step.message +
                        ". Nothing moves until you check the machine; `resume` re-homes and "
                        "continues.");
    case StepKind::kSafety:
      return Finish(RunOutcome::kFailed, RunState::kInterrupted,
                    "safety limit: " + step.message + ". Nothing of that line was sent.");
    case StepKind::kHeld:
      // Perhaps a person at the machine: nothing more moves until a user says so.
      return Finish(RunOutcome::kFailed, RunState::kInterrupted,
                    step.message +
                        ". Nothing more was sent. Check the machine; `resume` "
                        "ends the hold with a soft reset (a hold keeps the position) "
                        "and continues.");
    case StepKind::kReset:
    case StepKind::kDisconnected:
    case StepKind::kStall:
      // Not the probe's fault: it stays pending and is probed again after recovery.
      if (Recover(step)) return std::nullopt;
      if (ask_) return Awaiting(*ask_);
      return Finish(
          RunOutcome::kFailed, RunState::kInterrupted,
          "could not recover from: " + step.message + ". Resume when the machine is back.");
  }
  return std::nullopt;
}

// ---------------------------------------------------------------------------------------------

RunEngine::RunEngine(std::filesystem::path database, RunDatabaseOptions options)
    : database_(std::move(database)), database_options_(std::move(options)) {
  database_options_.Check();
}

RunEngine::~RunEngine() {
  if (thread_.joinable()) {
    RequestStop();
    thread_.join();
  }
}

void RunEngine::Start(std::int64_t run_id, const SessionOverrides& overrides) {
  if (running_.exchange(true)) throw std::logic_error("RunEngine::Start: a run is already running");
  if (thread_.joinable()) thread_.join();
  thread_error_ = nullptr;
  request_ = 0;
  thread_ = std::thread([this, run_id, overrides] {
    try {
      thread_report_ = Execute(run_id, overrides);
    } catch (...) {
      thread_error_ = std::current_exception();
    }
    running_ = false;
  });
}

bool RunEngine::Running() const {
  return running_.load();
}

RunReport RunEngine::Wait() {
  if (thread_.joinable()) thread_.join();
  if (thread_error_) std::rethrow_exception(std::exchange(thread_error_, nullptr));
  return thread_report_;
}

RunEngine::PlannedRun RunEngine::PlanRun(const RunConfig& config, const SafetyLimits* limits) {
  config.Check();
  const RigGeometry rig = MakeRigGeometry(config.rig);
  ProbePlan plan;
  try {
    plan = MakeProbePlan(rig, config.plan);
  } catch (const MeshError&) {
    throw;
  } catch (const ConfigError&) {
    throw;
  } catch (const std::runtime_error& e) {
    // Nothing survives the filters: the rig or the plan's settings, not the daemon, are at fault.
    throw ConfigError(e.what(), "plan");
  }
  CheckTravel(plan, config.plan.machine, config.plan.travel_limit_margin);
  if (limits != nullptr) {
    const SafetyGuard guard(*limits, std::make_shared<TravelPlanner>(rig, config.plan),
                            config.rig.ball_radius, config.rig.gel_thickness);
    if (auto bad = guard.CheckPlan(plan, config.plan)) {
      throw ConfigError("the plan breaks a safety limit at " + *bad, "plan");
    }
  }
  return {std::move(plan), ToHex64(rig.sensor_mesh.Hash())};
}

std::int64_t RunEngine::StoreRun(const RunConfig& config, const PlannedRun& planned) {
  const ProbePlan& plan = planned.plan;
  RunDatabase db(database_, database_options_);
  const std::int64_t run_id =
      db.CreateRun(RunConfigToJson(config).dump(), planned.sensor_mesh_hash, config.name);
  std::vector<ProbePlanEntry> entries;
  entries.reserve(plan.probes.size());
  for (const PlannedProbe& p : plan.probes) {
    entries.push_back(
        {p.point_sensor, p.normal_sensor, p.approach_machine, p.press_machine, p.retract_machine});
  }
  db.InsertPlan(run_id, entries);
  const std::string blob = PlanToJson(plan, config.plan).dump();
  db.PutArtifact(run_id, kPlanArtifactStage, plan.options_hash,
                 std::span(reinterpret_cast<const std::uint8_t*>(blob.data()), blob.size()),
                 PlanSummaryJson(plan, config.plan).dump());
  db.AppendEvent(run_id, EventLevel::kInfo,
                 "planned " + std::to_string(plan.probes.size()) + " probes of " +
                     std::to_string(plan.candidates) + " candidates; estimated " +
                     FormatFixed(plan.estimate.Hours(), 2) + " h");
  return run_id;
}

std::int64_t RunEngine::CreateRun(const RunConfig& config, ProbePlan* plan_out) {
  PlannedRun planned = PlanRun(config, limits_ ? &*limits_ : nullptr);
  const std::int64_t run_id = StoreRun(config, planned);
  if (plan_out) *plan_out = std::move(planned.plan);
  return run_id;
}

void RunEngine::SetSafetyLimits(const SafetyLimits& limits) {
  limits.Check();
  limits_ = limits;
}

ProbePlan RunEngine::LoadPlan(const RunDatabase& db, std::int64_t run_id) {
  for (const ArtifactRecord& a : db.ListArtifacts(run_id)) {
    if (a.stage != kPlanArtifactStage) continue;
    const auto full = db.GetArtifact(run_id, kPlanArtifactStage, a.input_hash);
    if (!full) break;
    const std::string text(full->blob.begin(), full->blob.end());
    return PlanFromJson(
        ParseJsonText(text, db.path().string() + " (run " + std::to_string(run_id) + " plan)"));
  }
  throw std::runtime_error("run " + std::to_string(run_id) + " in " + db.path().string() +
                           " has no stored plan");
}

RunReport RunEngine::Execute(std::int64_t run_id, const SessionOverrides& overrides) {
  if (!running_.load()) request_ = 0;  // Start() already cleared it: keep an early RequestStop
  RunSession session(*this, run_id, overrides);
  try {
    return session.Run();
  } catch (...) {
    // Leave a resumable state behind whatever happened.
    try {
      RunDatabase db(database_, database_options_);
      const auto run = db.GetRun(run_id);
      if (run && run->state == RunState::kRunning) db.SetRunState(run_id, RunState::kInterrupted);
    } catch (...) {
    }
    throw;
  }
}

void RunEngine::RequestStop() {
  request_.store(1);
}
void RunEngine::RequestPause() {
  request_.store(2);
}
void RunEngine::RequestCancel() {
  request_.store(3);
}
void RunEngine::RequestFinish(const std::string& reason) {
  {
    std::lock_guard lock(progress_mutex_);
    finish_reason_ = reason;
  }
  request_.store(4);
}
std::string RunEngine::FinishReason() const {
  std::lock_guard lock(progress_mutex_);
  return finish_reason_;
}

void RunEngine::SetProgressCallback(ProgressCallback callback) {
  std::lock_guard lock(progress_mutex_);
  callback_ = std::move(callback);
}

RunProgress RunEngine::Progress() const {
  std::lock_guard lock(progress_mutex_);
  return progress_;
}

void RunEngine::Publish(const RunProgress& progress) {
  ProgressCallback cb;
  {
    std::lock_guard lock(progress_mutex_);
    progress_ = progress;
    cb = callback_;
  }
  if (cb) cb(progress);
}

}  // namespace gs360
