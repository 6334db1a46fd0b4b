#pragma once
// Where on the sensor impressions are weak: presses whose impression barely stood out of the
// camera's noise (PressCheck, capture/press_check.h), gathered over the sensor's surface, so that
// the user hears of a region the LEDs light badly, which they can fix, rather than of single
// probes.
//
// The surface is cut into bands along the axis (z, sensor frame, mm) and sectors around it
// (azimuth atan2(y, x), deg). A cell with at least min_presses presses, at least
// min_weak_fraction of them weak, is weak; weak cells side by side in a band join into one
// azimuth range, and ranges over the same sectors in bands one above the other into one height
// range.

#include <Eigen/Core>
#include <string>
#include <vector>

namespace gs360 {

struct ImpressionRegionOptions {
  double band_mm = 3.0;  // > 0
  int sectors = 12;      // 1..360
  // A press is weak when its signal-to-noise ratio is below weak_factor x the threshold it had
  // to reach: half as much contrast and it would have been lost. > 1.
  double weak_factor = 2.0;
  int min_presses = 3;             // >= 1
  double min_weak_fraction = 0.5;  // (0, 1]
  // A region lit at less than this fraction of the median press's reference level is "dimly lit"
  // in the message (what the user should change); (0, 1).
  double dim_fraction = 0.75;
  void Check() const;  // throws std::invalid_argument naming the field and value
};

struct WeakRegion {
  double z_min_mm = 0.0;
  double z_max_mm = 0.0;
  // [-180, 180]; the whole ring when all_around. max < min: the range crosses +-180 deg.
  double azimuth_min_deg = -180.0;
  double azimuth_max_deg = 180.0;
  bool all_around = false;
  int presses = 0;                      // in the region
  int weak = 0;                         // of them weak (failed ones included)
  int failed = 0;                       // of them below the threshold
  double snr_min = 0.0, snr_max = 0.0;  // over the weak ones
  double threshold = 0.0;               // the largest threshold they had to reach
  // The region's median reference level over the median of every press's: how lit it is.
  double light_ratio = 1.0;
  bool dim = false;  // light_ratio < dim_fraction
  // "impressions are weak at z 12.0-24.0 mm at azimuth 30 to 90 deg: ...; the LEDs light it
  // dimly (...)".
  std::string Describe() const;
};

class ImpressionRegionTally {
 public:
  explicit ImpressionRegionTally(const ImpressionRegionOptions& options = {});
  // One press at `point_sensor`: its snr, the threshold it had to reach, the reference's level
  // around its expected pixel (ImpressionSnr::reference_dn).
  void Add(const Eigen::Vector3d& point_sensor, double snr, double threshold, double reference_dn);
  int Presses() const { return static_cast<int>(presses_.size()); }
  // The median snr of the presses added, and the lowest of those that reached their threshold
  // (0 without any).
  double MedianSnr() const;
  double WeakestCounted() const;
  // The weak regions, most weak presses first.
  std::vector<WeakRegion> WeakRegions() const;

 private:
  struct Press {
    int band = 0, sector = 0;
    double z = 0.0, snr = 0.0, threshold = 0.0, reference_dn = 0.0;
    bool weak = false;
  };
  bool IsWeakCell(int band, int sector) const;
  WeakRegion Summarise(int band_first, int band_last, int sector_first, int sector_count,
                       double median_light) const;

  ImpressionRegionOptions options_;
  std::vector<Press> presses_;
  int bands_ = 0;
  std::vector<int> cell_presses_, cell_weak_;  // band-major, grown as presses come
};

}  // namespace gs360
