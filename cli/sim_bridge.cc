#include "cli/sim_bridge.h"

#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <stdexcept>
#include <unordered_map>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "base/hash.h"
#include "base/json_reader.h"
#include "sim/checkerboard.h"
#include "sim/ground_truth.h"

namespace gs360::cli {

SimRigOptions SimRigOptionsFor(const RigConfig& rig, std::uint64_t seed) {
  SimRigOptions sim;
  sim.rig = rig;
  sim.seed = seed;
  return sim;
}

int WriteSimCheckerboards(const SimRig& rig, const std::filesystem::path& dir, int count,
                          std::uint64_t seed) {
  std::filesystem::create_directories(dir);
  const FisheyeIntrinsics& lens = SimGroundTruth::TrueIntrinsics(rig);
  CheckerboardOptions board;
  CheckerboardPoseOptions pose_options;
  pose_options.count = count;
  const std::vector<Rigid3d> poses = CheckerboardPoses(board, lens, pose_options, seed);
  int written = 0;
  for (std::size_t i = 0; i < poses.size(); ++i) {
    const cv::Mat image = RenderCheckerboard(board, poses[i], lens, seed * 1000 + i);
    char name[32];
    std::snprintf(name, sizeof(name), "board_%02zu.png", i);
    if (!cv::imwrite((dir / name).string(), image)) {
      throw std::runtime_error("cannot write " + (dir / name).string());
    }
    ++written;
  }
  return written;
}

std::string VirtualSetup::DaemonToml() const {
  return "[machine]\nuri = \"" + config.machine.uri + "\"\nfirmware = \"" +
         std::string(MachineFirmwareName(config.machine.firmware)) +
         "\"\nstatus_interval_ms = " + std::to_string(config.machine.status_interval_ms) +
         "\n\n[camera]\nuri = \"" + config.camera.uri + "\"\n";
}

RunReport ExecuteOnVirtualRig(RunEngine& engine, std::int64_t run_id, const RunConfig& config,
                              const std::string& what) {
  SessionOverrides overrides{.machine_uri = config.machine.uri, .camera_uri = config.camera.uri};
  RunReport report = engine.Execute(run_id, overrides);
  if (report.outcome == RunOutcome::kAwaiting) {
    RunDatabase db(engine.database());
    overrides.confirm = db.GetRun(run_id)->awaiting;
    report = engine.Execute(run_id, overrides);
  }
  if (report.outcome != RunOutcome::kDone) {
    throw std::runtime_error(what + " ended " + std::string(ToString(report.outcome)) + ": " +
                             report.message);
  }
  return report;
}

void MachineForConfig(const RunConfig& config, VirtualRigOptions* options) {
  // The virtual machine is the one the configuration's [plan.machine] describes (a lab with a
  // taller finger has a machine that reaches over it).
  const MachineSettings& machine = config.plan.machine;
  GrblSettings& settings = options->cnc.settings;
  settings.max_travel_mm = machine.max_travel_mm;
  settings.max_rate_mm_per_min = machine.max_rate_mm_per_min;
  settings.acceleration_mm_per_s2 = machine.acceleration_mm_per_s2;
  settings.junction_deviation_mm = machine.junction_deviation_mm;
}

void PrinterForConfig(const RunConfig& config, VirtualRigOptions* options) {
  GrblSettings& settings = options->cnc.settings;
  if (options->cnc.firmware == CncFirmware::kMarlin) {  // a printer's belts and lead screw
    const GrblSettings printer = GrblSettings::PrinterDefaults();
    settings.steps_per_mm = printer.steps_per_mm;
    settings.homing_seek_mm_per_min = printer.homing_seek_mm_per_min;
    settings.homing_feed_mm_per_min = printer.homing_feed_mm_per_min;
    options->cnc.initial_true_position = config.plan.start_machine;
  }
}

VirtualSetup MakeVirtualSetup(RunConfig config, double time_scale, std::uint64_t seed,
                              const std::filesystem::path& frame_socket, const std::string& symlink,
                              const std::function<void(VirtualRigOptions&)>& tweak) {
  VirtualRigOptions options;
  options.rig = SimRigOptionsFor(config.rig, seed);
  options.camera.sensor.seed = seed;
  options.cnc.time_scale = time_scale;
  options.cnc.symlink_path = symlink;
  // Enough motion history (pieces, and instant-mode clock jumps: ~9 per probe) and served-frame
  // records (~4 per probe) to verify every frame of a 10,000-probe run against the truth.
  options.cnc.history_pieces = 1u << 18;
  options.frame_log_capacity = 1u << 18;
  options.frame_socket = frame_socket;
  // At instant motion nothing but the host should pace a probe: the serial line's 115200 baud
  // (~10 ms for a press's lines) is not emulated either.
  if (time_scale == 0.0) options.cnc.baud_rate = 0;
  MachineForConfig(config, &options);
  if (tweak) tweak(options);
  PrinterForConfig(config, &options);
  VirtualSetup setup;
  setup.rig = std::make_unique<VirtualRig>(options);
  config.machine.uri = symlink.empty() ? setup.rig->PtyPath() : symlink;
  config.machine.firmware = options.cnc.firmware == CncFirmware::kMarlin ? MachineFirmware::kMarlin
                                                                         : MachineFirmware::kGrbl;
  // At instant motion nothing paces a probe but the host: the virtual firmware answers status
  // queries at any rate (a report is ~5 ms of 115200 baud), so asking at GRBL's 5 Hz would be the
  // bottleneck.
  if (time_scale == 0.0) config.machine.status_interval_ms = 10;
  config.camera.uri = setup.rig->FrameUri();
  setup.config = std::move(config);
  return setup;
}

}  // namespace gs360::cli

namespace gs360::cli {
namespace {

using Fingerprint = std::array<std::uint8_t, 3 * kFingerprintPixels>;
using SteadyClock = std::chrono::steady_clock;

double Seconds(SteadyClock::time_point t) {
  return std::chrono::duration<double>(t.time_since_epoch()).count();
}

SteadyClock::time_point SteadyAt(double seconds) {
  return SteadyClock::time_point(
      std::chrono::duration_cast<SteadyClock::duration>(std::chrono::duration<double>(seconds)));
}

// The rounded mean of the k frames served[clean[end - k + 1 .. end]] at the fingerprint pixels,
// computed as CapturePress averages (float sums, convertTo with 1/K: round half to even,
// saturate).
Fingerprint WindowMean(const std::vector<ServedFrame>& served,
                       const std::vector<std::size_t>& clean, std::size_t end, int k) {
  cv::Mat sum = cv::Mat::zeros(1, kFingerprintPixels, CV_32FC3);
  for (std::size_t i = end + 1 - static_cast<std::size_t>(k); i <= end; ++i) {
    const cv::Mat frame(1, kFingerprintPixels, CV_8UC3,
                        const_cast<std::uint8_t*>(served[clean[i]].fingerprint.data()));
    cv::accumulate(frame, sum);
  }
  Fingerprint out{};
  cv::Mat mean(1, kFingerprintPixels, CV_8UC3, out.data());
  sum.convertTo(mean, CV_8U, 1.0 / k);
  return out;
}

std::uint64_t Key(const Fingerprint& f) {
  return Hasher().Add(f.data(), f.size()).Digest();
}

// The undamaged served frames, and each window of k consecutive ones by its mean's hash.
struct ServedWindows {
  std::vector<std::size_t> clean;                              // indices into served
  std::unordered_multimap<std::uint64_t, std::size_t> by_key;  // -> index in clean of the last
};

ServedWindows IndexWindows(const std::vector<ServedFrame>& served, int k) {
  ServedWindows w;
  for (std::size_t i = 0; i < served.size(); ++i) {
    if (!served[i].corrupted) w.clean.push_back(i);
  }
  for (std::size_t end = static_cast<std::size_t>(k) - 1; end < w.clean.size(); ++end) {
    w.by_key.emplace(Key(WindowMean(served, w.clean, end, k)), end);
  }
  return w;
}

// The served window with exactly the stored content (its last frame's index in clean); among
// identical ones (a noise-free camera) the one whose time is nearest `hint` (steady seconds).
std::optional<std::size_t> NearestWindow(const std::vector<ServedFrame>& served,
                                         const ServedWindows& windows, const Fingerprint& stored,
                                         int k, double hint) {
  std::optional<std::size_t> match;
  const auto& clean = windows.clean;
  const auto [first, last] = windows.by_key.equal_range(Key(stored));
  for (auto it = first; it != last; ++it) {
    if (WindowMean(served, clean, it->second, k) != stored) continue;  // a hash collision
    if (!match || std::abs(Seconds(served[clean[it->second]].timestamp) - hint) <
                      std::abs(Seconds(served[clean[*match]].timestamp) - hint)) {
      match = it->second;
    }
  }
  return match;
}

}  // namespace

void CaptureTruthOptions::Check() const {
  if (!(tolerance_mm > 0.0)) {
    throw std::invalid_argument("CaptureTruthOptions.tolerance_mm must be > 0, got " +
                                std::to_string(tolerance_mm));
  }
  if (unix_minus_steady_s && !std::isfinite(*unix_minus_steady_s)) {
    throw std::invalid_argument("CaptureTruthOptions.unix_minus_steady_s must be finite, got " +
                                std::to_string(*unix_minus_steady_s));
  }
}

CaptureTruth CheckCapturesAgainstTruth(const VirtualRig& rig, const RunDatabase& db,
                                       std::int64_t run_id, const CaptureTruthOptions& options) {
  options.Check();
  const std::optional<RunRecord> run = db.GetRun(run_id);
  if (!run) {
    throw std::runtime_error("CheckCapturesAgainstTruth: no run " + std::to_string(run_id) +
                             " in " + db.path().string());
  }
  const std::string where = db.path().string() + ", run " + std::to_string(run_id);
  const int k = RunConfigFromJson(ParseJsonText(run->config_json, where), where)
                    .camera.capture.frames_to_average;
  const double check_offset = options.unix_minus_steady_s.value_or(
      std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count() -
      Seconds(SteadyClock::now()));

  // Every window of k consecutive undamaged served frames (a capture leaves a damaged one out
  // and reads the next), by the hash of its rounded mean. A stored image with a damaged frame
  // averaged in matches none: unverified.
  const std::vector<ServedFrame> served = rig.ServedFrames();
  const ServedWindows windows = IndexWindows(served, k);
  const std::vector<std::size_t>& clean = windows.clean;

  const VirtualCnc& cnc = rig.cnc();
  // The tool can stand only on whole steps: half a step on each axis from the press point is
  // still on it (a printer's 80 steps/mm belts leave up to 0.009 mm).
  const double tolerance =
      options.tolerance_mm + 0.5 * cnc.Settings().steps_per_mm.cwiseInverse().norm();
  CaptureTruth truth;
  for (const CapturedProbe& c : db.ListCapturedProbes(run_id)) {
    ++truth.frames;
    const int index = c.probe.plan_index;
    const Fingerprint stored = FrameFingerprint(db.LoadFrame(c.frame_id));
    // The served window with exactly this content; among identical ones (a noise-free camera),
    // the one nearest in time to where the check-time clock offset puts the stored frame.
    const std::optional<std::size_t> match =
        NearestWindow(served, windows, stored, k, c.frame_time - check_offset);
    if (!match) {
      ++truth.unverified;
      truth.unverified_plan_indices.push_back(index);
      continue;
    }
    const ServedFrame& last_frame = served[clean[*match]];
    // The offset of the session that stored this frame: its Unix frame time is the steady
    // timestamp of the last averaged frame, mapped with that session's offset.
    const double session_offset = c.frame_time - Seconds(last_frame.timestamp);
    truth.max_clock_skew_s =
        std::max(truth.max_clock_skew_s, std::abs(session_offset - check_offset));
    const Eigen::Vector3d& press = c.probe.plan.press_machine;
    double err = 0.0;
    try {
      for (std::size_t i = *match + 1 - static_cast<std::size_t>(k); i <= *match; ++i) {
        const ServedFrame& f = served[clean[i]];
        err = std::max(err, (f.machine_position - press).norm());
        err = std::max(err, (cnc.TruePosition(f.timestamp - f.exposure) - press).norm());
      }
      const double sync = *c.probe.sync_time - session_offset;
      err = std::max(err, (cnc.TruePosition(SteadyAt(sync)) - press).norm());
    } catch (const std::out_of_range&) {
      ++truth.unverified;
      truth.unverified_plan_indices.push_back(index);
      continue;
    }
    truth.max_error_mm = std::max(truth.max_error_mm, err);
    if (err > tolerance) {
      ++truth.off_target;
      truth.off_target_plan_indices.push_back(index);
    }
    if (c.probe.machine_position) {
      truth.max_reported_error_mm =
          std::max(truth.max_reported_error_mm,
                   (*c.probe.machine_position - last_frame.machine_position).norm());
    }
  }
  return truth;
}

}  // namespace gs360::cli
