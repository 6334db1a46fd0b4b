#pragma once
// The run engine's session (one RunEngine::Execute() call): private to run/run_engine.cc and
// run/run_recovery.cc, not part of any public contract.

#include <chrono>
#include <cmath>
#include <cstdio>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <spdlog/spdlog.h>
#include <opencv2/core/mat.hpp>

#include "capture/capture_press.h"
#include "capture/frame_source.h"
#include "capture/impression.h"
#include "capture/impression_regions.h"
#include "capture/press_check.h"
#include "gcode/machine.h"
#include "gcode/probe_program.h"
#include "geometry/fisheye.h"
#include "run/run_engine.h"
#include "storage/capture_committer.h"

namespace gs360 {
namespace session {

using Clock = std::chrono::steady_clock;

std::string Fmt3(const Eigen::Vector3d& v);

// The machine position a motion line of ours sends the tool to ("G53 G0|G1 X.. Y.. Z..", all
// three axes, after "G90 " in a press's approach line); nullopt for any other line.
inline std::optional<Eigen::Vector3d> MotionTarget(const std::string& line) {
  const auto x = line.find(" X");
  const std::size_t start = line.rfind("G90 ", 0) == 0 ? 4 : 0;
  double v[3];
  if (line.compare(start, 5, "G53 G") != 0 || x == std::string::npos ||
      std::sscanf(line.c_str() + x, " X%lf Y%lf Z%lf", &v[0], &v[1], &v[2]) != 3) {
    return std::nullopt;
  }
  return Eigen::Vector3d(v[0], v[1], v[2]);
}

inline std::chrono::milliseconds Ms(double seconds) {
  return std::chrono::milliseconds(static_cast<long long>(std::ceil(seconds * 1000.0)));
}

// How one probe's streaming ended.
enum class StepKind {
  kOk,
  kProbeError,    // error:N on one of its lines, or no frame / no position: the probe fails
  kAlarm,         // the machine raised an alarm: stop the run
  kReset,         // the controller reset: everything in flight is void, position lost
  kDisconnected,  // the port vanished
  kStall,         // no sync ok within the timeout, or a reply lost on the line
  kSafety,        // a line would break a safety limit: nothing of it was sent
  kHeld,          // the controller went into a feed hold the run did not ask for: stop the run
};

// How long a controller must stand idle, beyond the dwells sent, with a line unanswered before
// the line or its reply counts as lost (s): after unreadable bytes came in, and without.
inline constexpr double kLostReplyQuietS = 0.75;
inline constexpr double kLostLineQuietS = 2.0;

// While waiting for a reply, on a machine whose replies can be lost (Machine::RepliesCanBeLost;
// Marlin's numbered, checksummed lines are resent by its client instead). GRBL's lines and replies
// carry no checksum: noise can turn an `ok` into an unreadable line, or eat a line's newline so the
// controller never sees its end, and the wait would last the whole sync timeout (minutes). GRBL
// answers a line as soon as it is planned (a dwell after it has run), so a controller that stands
// idle longer than the dwells sent take with a line unanswered has lost it or its reply: the caller
// recovers (soft reset, position check) at once.
class LostReplyWatch {
 public:
  LostReplyWatch(Machine& machine, const std::vector<std::string>& lines);
  // Uses the status poller's reports; asks for one (at most every 250 ms) when they are old.
  bool Lost();
  // Unreadable lines since the lines were sent.
  std::uint64_t Garbled() const;

 private:
  Machine& machine_;
  std::uint64_t garbled_before_;
  std::chrono::steady_clock::time_point sent_at_;
  double dwell_s_ = 0.0;
  std::chrono::steady_clock::time_point next_query_{};
  std::optional<std::chrono::steady_clock::time_point> idle_since_;
};

struct Step {
  StepKind kind = StepKind::kOk;
  std::string message;
  // kProbeError: whether the probe may be pressed again (docs/running.md, "Failures and
  // attempts"); false for a reason a second press cannot change.
  bool retry = true;
};

// What a successful press produced.
struct Press {
  cv::Mat frame;
  cv::Mat reference;  // the no-contact frame taken first, when one was asked for
  Eigen::Vector3d mpos = Eigen::Vector3d::Zero();
  Clock::time_point sync{};
  Clock::time_point frame_time{};
};

// The run cannot go on safely without the user: what to confirm ("position", "sensor") and why.
struct Ask {
  std::string what;
  std::string message;
};

}  // namespace session

// One Execute() call: owns the connections for its duration.
class RunSession {
  using Clock = session::Clock;
  using Step = session::Step;
  using StepKind = session::StepKind;
  using Press = session::Press;
  using Ask = session::Ask;

 public:
  RunSession(RunEngine& engine, std::int64_t run_id, SessionOverrides overrides)
      : engine_(engine),
        run_id_(run_id),
        db_(engine.database_, engine.database_options_),
        committer_(engine.database_, engine.database_options_),
        overrides_(std::move(overrides)) {}

  RunReport Run();

 private:
  // The probing loop, after the set-up and the resume check.
  RunReport ProbeLoop();
  // A stop, pause, cancel or finish the engine was asked for: the session's report; nullopt:
  // none.
  std::optional<RunReport> OnRequest();
  // What a press's outcome does: commit, fail the probe, recover, or end the session (the
  // report).
  std::optional<RunReport> AfterPress(const Step& step, const ProbeRecord& probe,
                                      const PlannedProbe& planned, const Press& press,
                                      Clock::time_point t0);
  // Ends the session: waits for the commits, records where the tool is, sets the run's state.
  RunReport Finish(RunOutcome outcome, RunState state, const std::string& message);
  // Set-up.
  void LoadRun();
  void ConnectMachine();
  // The controller's travel, rates and accelerations against the plan's machine; throws when its
  // travel does not reach every planned position.
  void CompareFirmware(const MachineInfo& info);
  // Knows where the tool is before anything moves (run_engine.h "Position"); `sent`: the last
  // motion sent (start, then targets; empty if none): an idle controller must stand on one of
  // its points, or, with `homing_sent` (a $H sent after it), wherever the homing cycle left it.
  // Asks the user when it cannot know; otherwise leaves the tool out of the gel, homed if
  // configured, with the preamble sent. Throws std::runtime_error when the controller fails (no
  // status, homing failed).
  std::optional<Ask> EstablishPosition(const std::vector<Eigen::Vector3d>& sent, bool homing_sent);
  // EstablishPosition's two cases: the controller in alarm or restarted (homes, or asks), and
  // one that kept its position (checked against `sent`; backs out of the gel, homes).
  std::optional<Ask> RecoverLostPosition(const std::vector<Eigen::Vector3d>& sent,
                                         std::uint64_t stray);
  std::optional<Ask> VerifyPosition(const std::vector<Eigen::Vector3d>& sent, bool homing_sent);
  std::string ResumeConfirming() const;  // the command that resumes confirming the position
  // $H / G28, recorded as sent (RunDatabase::MarkHomingSent) before it goes out, after raising Z
  // `lift_mm` on a machine whose homing moves X and Y first; throws when it fails.
  void Home(double lift_mm);
  // How far to raise Z so that a homing which moves X and Y first (Marlin's G28) starts above
  // the sensor, the tool anywhere on `where` (machine frame): 0 for GRBL ($H seeks Z first);
  // nullopt when that is not known to be clear within the travel (nothing on record, an overhang,
  // the travel's top).
  std::optional<double> HomingLift(const std::vector<Eigen::Vector3d>& where) const;
  // Homes from `where` (HomingLift), or asks (`why` first) when it cannot be raised for certain
  // and the user has not confirmed the position.
  std::optional<Ask> HomeFrom(const std::vector<Eigen::Vector3d>& where, const std::string& why);
  // $X after the user confirmed the position, said in the run's events; throws when refused.
  void Unlock();
  // In or near the gel: out along the probe's own axis (its approach point), or the surface
  // normal where no probe's axis passes, at the press feed.
  void BackOutOfGel();
  // True when every segment of `path` (machine positions) keeps the tool clear of the sensor.
  bool PathClearOfGel(const std::vector<Eigen::Vector3d>& path) const;
  // Records the targets of motion `lines` about to be sent from `from`: appended to last_path_
  // (reset to its end point by each sync) and stored as the run's commanded path.
  void Commanded(const std::vector<std::string>& lines, const Eigen::Vector3d& from);
  // Probing.
  Step PressProbe(const PlannedProbe& planned, bool take_reference, Press* out);
  // The no-contact reference frame at the approach (and, for the impression check, a second
  // capture of it: the camera's noise).
  Step TakeReference(const PlannedProbe& planned, const ProbeProgram& program, Press* out);
  // Whether the press frame shows the press where the plan puts it; nullopt when it does (or
  // nothing is checked). Sets last_check_.
  std::optional<Step> CheckImpression(const PlannedProbe& planned, const cv::Mat& frame);
  // This session's impression check in the run's events: what it measured (info), and the
  // regions where impressions were weak (a warning each).
  void ReportImpressions();
  // Adds the last press's impression check (a probe-loop press, not a resume's re-press) to
  // impression_regions_.
  void TallyImpression(const PlannedProbe& planned);
  // What a failed capture says; a warning event for frames left out of a good one.
  std::string CaptureFailure(const std::string& what, const PressCaptureResult& r);
  void NoteOutliers(const std::string& what, int plan_index, const PressCaptureResult& r);
  Step SendAndSync(const std::vector<std::string>& lines, Clock::time_point* sync_at);
  Step Classify(const std::vector<MachineHandle>& handles);
  std::optional<std::vector<Eigen::Vector3d>> TravelTo(const PlannedProbe& planned);
  bool Recover(const Step& step);
  void ReturnToSafety(const PlannedProbe& planned);
  // Re-presses a few committed probes on resume: nullopt when they match their stored frames;
  // an Ask with `what` empty when the sensor moved (the run fails), "sensor" when nothing could
  // be compared (the run asks, unless the user confirmed or the config says continue).
  std::optional<Ask> RecheckSensor();
  // Up to `want` committed probes to re-press, spread over the run, each with its stored
  // impression (only clear ones: engine.recheck_min_peak_dn).
  struct RecheckPick {
    const CapturedProbe* probe;  // into the caller's list
    Impression stored;
    cv::Mat press, reference;  // the stored frames it was found in
  };
  std::vector<RecheckPick> PickRecheckProbes(const std::vector<CapturedProbe>& captured,
                                             int want) const;
  // The run stops, without moving, until the user confirms what `ask` says.
  RunReport Awaiting(const Ask& ask);
  // At the end of a session: waits for the motion sent to end and records its end point as the
  // run's commanded path (a trusted, connected, unalarmed controller only).
  void SettleAndRecord();
  void Park();
  void SendRetract(const ProbeProgram& program, const PlannedProbe& planned);
  // The lines that would break a safety limit, sent from `from` in order; nullopt when all pass
  // (or no limits are set). Records the violation for the run loop to stop on.
  std::optional<std::string> Unsafe(const std::vector<std::string>& lines,
                                    const Eigen::Vector3d& from);
  // Bookkeeping.
  double ToUnix(Clock::time_point t) const {
    return std::chrono::duration<double>(t - steady_origin_).count() + unix_origin_;
  }
  void Publish(const std::string& phase, int plan_index = -1);
  void Event(EventLevel level, const std::string& message) {
    if (level >= EventLevel::kWarning) {
      spdlog::warn("run {}: {}", run_id_, message);
    } else {
      spdlog::info("run {}: {}", run_id_, message);
    }
    db_.AppendEvent(run_id_, level, message);
  }

  RunEngine& engine_;
  std::int64_t run_id_;
  RunDatabase db_;
  // A probe's frame is encoded and committed while the machine goes to the next probe.
  CaptureCommitter committer_;
  SessionOverrides overrides_;
  RunConfig config_;
  ProbePlan plan_;
  std::shared_ptr<TravelPlanner> travel_;
  std::unique_ptr<SafetyGuard> guard_;
  std::optional<std::string> safety_stop_;  // a refused line: the run stops after this probe
  std::optional<Ask> ask_;  // set by a recovery that needs the user: the run stops and asks
  // The motion sent since the last sync: where it started, then each target (machine frame).
  std::vector<Eigen::Vector3d> last_path_;
  bool homing_sent_ = false;   // a $H sent after last_path_ (RunRecord::homing_sent)
  cv::Mat session_reference_;  // the latest no-contact frame of this session
  // The impression check, with the noise and null measured in this session (null: no check, or
  // the legacy contrast check of an older run, engine.impression_min_contrast).
  std::unique_ptr<PressCheck> press_check_;
  std::optional<PressCheckResult> last_check_;  // of the last press, for the region tally
  ImpressionRegionTally impression_regions_;    // this session's probe-loop presses
  std::unique_ptr<FisheyeCamera> camera_;       // the nominal camera, for where a press should show
  std::unique_ptr<Machine> machine_;
  std::unique_ptr<FrameSource> source_;
  ReferenceSchedule references_;
  Eigen::Vector3d position_ = Eigen::Vector3d::Zero();  // where the streamed lines leave the tool
  int at_retract_of_ = -2;  // plan index whose retract position the tool is at (-1: plan start)
  std::optional<std::int64_t> last_reference_at_;  // probes done when the last reference was taken
  std::int64_t probes_done_ = 0;
  int recoveries_ = 0;
  RunReport report_;
  Clock::time_point session_start_ = Clock::now();
  Clock::time_point steady_origin_ = Clock::now();
  double unix_origin_ =
      std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
  double recent_probe_s_ = 0.0;  // exponential mean of seconds per committed probe
};

}  // namespace gs360
