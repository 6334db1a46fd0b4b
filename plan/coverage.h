#pragma once
// Where on the sensor a plan leaves no probe, and why: said before a run starts (the plan's
// summary, `gs360 run start`, the API) and drawn on the calibration report's error map.
//
// The sensor's surface is cut into bands along its axis (z, sensor frame, mm) and sectors
// around it (azimuth atan2(y, x), deg). A cell where at least `min_candidates` candidates were
// tested and none was kept is not probed; the reason that dropped most of them says why. Gap
// cells side by side in a band join into one azimuth range, and ranges over the same sectors
// with the same main reason in bands one above the other join into one height range.

#include <array>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <nlohmann/json.hpp>

#include "plan/drop_reason.h"

namespace gs360 {

struct CoverageOptions {
  double band_mm = 1.0;    // band height along the axis, > 0
  int sectors = 12;        // around the axis, 1..360
  int min_candidates = 2;  // a cell with fewer tested candidates says nothing, >= 1
  void Check() const;      // throws std::invalid_argument naming the field and value
};

struct CoverageGap {
  double z_min_mm = 0.0;
  double z_max_mm = 0.0;
  // [-180, 180]; the whole ring when all_around. max < min: the range crosses +-180 deg.
  double azimuth_min_deg = -180.0;
  double azimuth_max_deg = 180.0;
  bool all_around = false;
  int candidates = 0;                    // tested inside it (none kept)
  DropReason reason = DropReason::kFov;  // what dropped most of them

  // "z 26.0-30.0 mm all around: 187 candidates, none kept (most for view_angle)".
  std::string Describe() const;
  nlohmann::json ToJson() const;
};

class CoverageTally {
 public:
  // `height_mm`: the sensor's height above its base (z = 0); points outside [0, height] count
  // in the first or last band. Throws std::invalid_argument for a height <= 0 or bad options.
  explicit CoverageTally(double height_mm, const CoverageOptions& options = {});

  // One tested candidate (sensor frame): kept, or dropped for `reason`.
  void Add(const Eigen::Vector3d& point_sensor, std::optional<DropReason> reason);
  // The gaps, largest (most candidates) first.
  std::vector<CoverageGap> Gaps() const;

 private:
  struct Cell {
    int candidates = 0;
    int kept = 0;
    std::array<int, kNumDropReasons> reasons{};
  };
  bool IsGap(const Cell& c) const;

  double height_mm_;
  CoverageOptions options_;
  int bands_;
  std::vector<Cell> cells_;  // band-major: band * sectors + sector
};

}  // namespace gs360
