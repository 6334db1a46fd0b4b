#pragma once
// What the calibration needs to know of a run's rig, from its stored configuration: the nominal
// meshes, camera and mount (rig/rig_config.h), and the lens's checkerboard images.

#include <cstdint>
#include <filesystem>

#include "calib/pipeline.h"
#include "run/run_config.h"
#include "storage/run_database.h"

namespace gs360 {

// The rig's nominal description (mesh, fins, camera, mount, tool) from a run's configuration, and
// the checkerboard images (sorted *.png / *.jpg files of `checkerboard_dir`, if given). Throws
// std::runtime_error naming the directory when it has no images.
CalibrationInputs CalibrationInputsFor(const RunConfig& config,
                                       const std::filesystem::path& checkerboard_dir = {});

// The same for a stored run (its configuration, StoredRunConfig), with the coverage gaps of its
// stored plan for the report's error map (none for a run planned before plans kept them).
CalibrationInputs CalibrationInputsFor(const RunDatabase& db, std::int64_t run_id,
                                       const std::filesystem::path& checkerboard_dir = {});

}  // namespace gs360
