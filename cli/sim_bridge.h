#pragma once
// Builds the virtual rig that matches a user's rig configuration: the simulator takes the
// configured (nominal) sensor, fins, lens, mount and tool offset, then perturbs the camera to
// make its own hidden truth. Used by `demo`, `sim-rig` and the end-to-end tests only.

#include <filesystem>
#include <memory>

#include "daemon/rig_config.h"
#include "daemon/run_config.h"
#include "sim/virtual_rig.h"

namespace gs360::cli {

SimRigOptions SimRigOptionsFor(const RigConfig& rig, std::uint64_t seed = 1);

// A virtual rig built from `config.rig` (plus its own hidden truth, drawn from `seed`), and the
// config pointed at the rig's pty (or `symlink`, kept pointing at it) and camera socket.
struct VirtualSetup {
  RunConfig config;
  std::unique_ptr<VirtualRig> rig;
};
// Checkerboard images through the rig's TRUE lens (what a lab shoots before assembly), written
// as PNG files into `dir` (created). Returns the number written.
int WriteSimCheckerboards(const SimRig& rig, const std::filesystem::path& dir, int count,
                          std::uint64_t seed);

VirtualSetup MakeVirtualSetup(RunConfig config, double time_scale, std::uint64_t seed,
                              const std::filesystem::path& frame_socket = {},
                              const std::string& symlink = {});

}  // namespace gs360::cli

#include "storage/run_database.h"

namespace gs360::cli {

// Ground-truth check of an acquisition on the virtual rig: for every captured probe, where the
// virtual CNC truly was at its sync time and at its frame time, against the planned press
// position. Times are converted from the stored Unix seconds with this process's clock offset.
struct CaptureTruth {
  int frames = 0;
  int off_target = 0;         // frames with the tool further than tolerance from the press point
  int unverified = 0;         // frames older than the virtual CNC's kept motion history
  double max_error_mm = 0.0;  // largest |true - planned press| at sync or frame time
  double max_reported_error_mm = 0.0;  // largest |reported MPos - true position| at frame time
};
CaptureTruth CheckCapturesAgainstTruth(const VirtualCnc& cnc, const RunDatabase& db,
                                       std::int64_t run_id, double tolerance_mm = 0.005);

}  // namespace gs360::cli
