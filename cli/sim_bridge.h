#pragma once
// Builds the virtual rig that matches a user's rig configuration: the simulator takes the
// configured (nominal) sensor, fins, lens, mount and tool offset, then perturbs the camera to
// make its own hidden truth. Used by `demo`, `sim-rig` and the end-to-end tests only.

#include <filesystem>
#include <functional>
#include <memory>

#include "rig/rig_config.h"
#include "run/run_config.h"
#include "run/run_engine.h"
#include "sim/virtual_rig.h"

namespace gs360::cli {

SimRigOptions SimRigOptionsFor(const RigConfig& rig, std::uint64_t seed = 1);

// A virtual rig built from `config.rig` (plus its own hidden truth, drawn from `seed`), and the
// config pointed at the rig's pty (or `symlink`, kept pointing at it) and camera socket.
struct VirtualSetup {
  RunConfig config;
  std::unique_ptr<VirtualRig> rig;
  // The [machine] and [camera] sections of a gs360d.toml for this rig (its pty, its camera
  // socket, the status interval its time scale allows).
  std::string DaemonToml() const;
};
// Checkerboard images through the rig's TRUE lens (what a lab shoots before assembly), written
// as PNG files into `dir` (created). Returns the number written.
int WriteSimCheckerboards(const SimRig& rig, const std::filesystem::path& dir, int count,
                          std::uint64_t seed);

// `tweak`, when set, adjusts the rig's options (a firmware, its settings) before it is built.
// The virtual controller as `config`'s [plan.machine] describes it (travel, rates, accelerations,
// junction deviation).
void MachineForConfig(const RunConfig& config, VirtualRigOptions* options);
// For a Marlin printer (options->cnc.firmware): a printer's steps/mm and homing feeds, and the
// tool at plan.start_machine at power-up. Nothing for GRBL.
void PrinterForConfig(const RunConfig& config, VirtualRigOptions* options);

VirtualSetup MakeVirtualSetup(RunConfig config, double time_scale, std::uint64_t seed,
                              const std::filesystem::path& frame_socket = {},
                              const std::string& symlink = {},
                              const std::function<void(VirtualRigOptions&)>& tweak = {});

// Runs (or resumes) `run_id` on the virtual rig `config` points at (its pty and camera socket)
// until it ends. A resume on a fresh rig, whose controller restarted, is asked about by the run;
// here the answer is known (the virtual tool is clear, it homes) and given. Throws
// std::runtime_error naming `what` when the run does not end done.
RunReport ExecuteOnVirtualRig(RunEngine& engine, std::int64_t run_id, const RunConfig& config,
                              const std::string& what);

}  // namespace gs360::cli

#include <optional>
#include <vector>

#include "storage/run_database.h"

namespace gs360::cli {

// Ground-truth check of an acquisition on the virtual rig. Each stored press frame is matched,
// by content alone, to the K consecutive frames the rig's camera served whose rounded mean it is
// (K = the run's camera.capture.frames_to_average; ServedFrame fingerprints, sim/virtual_rig.h),
// so no clock conversion is involved. The frame is on target when the true tool position was
// within tolerance of the planned press point at the exposure start and end of each of those K
// frames and at the sync `ok`. The sync time is mapped onto the steady clock with the offset of
// the session that took the frame (its stored frame time minus the matched frame's steady
// timestamp), not with the offset of the clock at check time. Assumes one client read the
// rig's camera at a time (the daemon), so a capture's frames are consecutive in the log.
struct CaptureTruthOptions {
  // > 0; the machine's step resolution (half a step on each axis) is added.
  double tolerance_mm = 0.005;
  // System-minus-steady clock offset (s) assumed at check time: it only picks the nearest in
  // time among served windows of identical content (noise-free camera) and sets
  // CaptureTruth::max_clock_skew_s. Default: measured when the check runs. Tests inject one.
  std::optional<double> unix_minus_steady_s;
  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

struct CaptureTruth {
  int frames = 0;
  int off_target = 0;  // frames with the tool further than tolerance from the press point
  // Frames that cannot be checked: no served window matches the stored image (older than the
  // rig's frame log, or not served by this rig), or older than the CNC's motion history.
  int unverified = 0;
  double max_error_mm = 0.0;           // largest |true - planned press| over the checked instants
  double max_reported_error_mm = 0.0;  // largest |reported MPos - true position| at frame time
  // Largest |system-minus-steady offset of the session that stored a frame - the check-time
  // offset|: how far the two clocks moved apart between the acquisition and the check.
  double max_clock_skew_s = 0.0;
  std::vector<int> off_target_plan_indices;  // plan order
  std::vector<int> unverified_plan_indices;  // plan order
};
// Throws std::invalid_argument for invalid options, std::runtime_error for an unknown run,
// StorageError for a frame that cannot be read, ConfigError for a stored configuration that
// does not parse.
CaptureTruth CheckCapturesAgainstTruth(const VirtualRig& rig, const RunDatabase& db,
                                       std::int64_t run_id,
                                       const CaptureTruthOptions& options = {});

}  // namespace gs360::cli
