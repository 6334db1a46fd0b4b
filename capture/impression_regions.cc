#include "capture/impression_regions.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "base/format.h"

namespace gs360 {
namespace {

constexpr double kPi = 3.14159265358979323846;

double Median(std::vector<double> v) {
  if (v.empty()) return 0.0;
  const auto mid = v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2);
  std::nth_element(v.begin(), mid, v.end());
  return *mid;
}

// A run of sectors [first, first + count) (mod sectors) in one band, and its bands so far.
struct Run {
  int first = 0;
  int count = 0;
  int band_first = 0;
  int band_last = 0;
};

}  // namespace

void ImpressionRegionOptions::Check() const {
  const auto bad = [](const std::string& field, double value, const char* rule) {
    throw std::invalid_argument("ImpressionRegionOptions." + field + " must be " + rule + ", got " +
                                FormatFixed(value, 3));
  };
  if (!(band_mm > 0.0 && std::isfinite(band_mm))) bad("band_mm", band_mm, "> 0");
  if (sectors < 1 || sectors > 360) bad("sectors", sectors, "in 1..360");
  if (!(weak_factor > 1.0 && std::isfinite(weak_factor))) bad("weak_factor", weak_factor, "> 1");
  if (min_presses < 1) bad("min_presses", min_presses, ">= 1");
  if (!(min_weak_fraction > 0.0 && min_weak_fraction <= 1.0)) {
    bad("min_weak_fraction", min_weak_fraction, "in (0, 1]");
  }
  if (!(dim_fraction > 0.0 && dim_fraction < 1.0)) bad("dim_fraction", dim_fraction, "in (0, 1)");
}

std::string WeakRegion::Describe() const {
  std::string where = "z " + FormatFixed(z_min_mm, 1) + "-" + FormatFixed(z_max_mm, 1) + " mm ";
  if (all_around) {
    where += "all around";
  } else if (azimuth_max_deg < azimuth_min_deg) {
    where += "at azimuth " + FormatFixed(azimuth_min_deg, 0) + " to 180 and -180 to " +
             FormatFixed(azimuth_max_deg, 0) + " deg";
  } else {
    where += "at azimuth " + FormatFixed(azimuth_min_deg, 0) + " to " +
             FormatFixed(azimuth_max_deg, 0) + " deg";
  }
  std::string text = "impressions are weak at " + where + ": " + std::to_string(weak) + " of " +
                     std::to_string(presses) +
                     " presses there barely stood out of the camera's noise (signal-to-noise " +
                     FormatFixed(snr_min, 1) + "-" + FormatFixed(snr_max, 1) + ", " +
                     FormatFixed(threshold, 1) + " needed)";
  if (failed > 0) text += ", " + std::to_string(failed) + " of them too faint to count";
  const std::string level = FormatFixed(100.0 * light_ratio, 0) + " % of the median press's";
  if (dim) {
    return text + ". The LEDs light it dimly (the reference frame there is at " + level +
           " level): brighter LEDs, LEDs that reach that part, or a longer exposure would make "
           "its presses count";
  }
  return text + ". It is not dim (the reference frame there is at " + level +
         " level): the light meets it at an angle that shows a press faintly, or a fin's edge "
         "hides part of it; LEDs that light it from the side would show its presses better";
}

ImpressionRegionTally::ImpressionRegionTally(const ImpressionRegionOptions& options)
    : options_(options) {
  options_.Check();
}

void ImpressionRegionTally::Add(const Eigen::Vector3d& p, double snr, double threshold,
                                double reference_dn) {
  if (!p.allFinite() || !std::isfinite(snr)) return;
  Press press;
  press.band = std::max(0, static_cast<int>(std::floor(p.z() / options_.band_mm)));
  if (press.band > 100000) return;  // no sensor is 300 m tall: a point in the wrong unit
  const double turn = (std::atan2(p.y(), p.x()) + kPi) / (2.0 * kPi);  // [0, 1]
  press.sector =
      std::clamp(static_cast<int>(std::floor(turn * options_.sectors)), 0, options_.sectors - 1);
  press.z = p.z();
  press.snr = snr;
  press.threshold = threshold;
  press.reference_dn = reference_dn;
  press.weak = snr < options_.weak_factor * threshold;
  if (press.band >= bands_) {
    bands_ = press.band + 1;
    cell_presses_.resize(static_cast<std::size_t>(bands_) * options_.sectors, 0);
    cell_weak_.resize(cell_presses_.size(), 0);
  }
  const std::size_t cell = static_cast<std::size_t>(press.band) * options_.sectors + press.sector;
  ++cell_presses_[cell];
  if (press.weak) ++cell_weak_[cell];
  presses_.push_back(press);
}

double ImpressionRegionTally::MedianSnr() const {
  std::vector<double> snr;
  for (const Press& p : presses_) snr.push_back(p.snr);
  return Median(std::move(snr));
}

double ImpressionRegionTally::WeakestCounted() const {
  double weakest = 0.0;
  for (const Press& p : presses_) {
    if (p.snr >= p.threshold && (weakest == 0.0 || p.snr < weakest)) weakest = p.snr;
  }
  return weakest;
}

bool ImpressionRegionTally::IsWeakCell(int band, int sector) const {
  const std::size_t cell = static_cast<std::size_t>(band) * options_.sectors + sector;
  const int n = cell_presses_[cell];
  return n >= options_.min_presses && cell_weak_[cell] >= options_.min_weak_fraction * n;
}

WeakRegion ImpressionRegionTally::Summarise(int band_first, int band_last, int sector_first,
                                            int sector_count, double median_light) const {
  const int n = options_.sectors;
  WeakRegion r;
  r.all_around = sector_count == n;
  const double width = 360.0 / n;
  r.azimuth_min_deg = -180.0 + width * sector_first;
  r.azimuth_max_deg = -180.0 + width * ((sector_first + sector_count - 1) % n + 1);
  r.z_min_mm = 1e300;
  r.z_max_mm = -1e300;
  r.snr_min = 1e300;
  std::vector<double> light;
  for (const Press& p : presses_) {
    if (p.band < band_first || p.band > band_last) continue;
    if ((p.sector - sector_first + n) % n >= sector_count) continue;
    ++r.presses;
    light.push_back(p.reference_dn);
    r.z_min_mm = std::min(r.z_min_mm, p.z);
    r.z_max_mm = std::max(r.z_max_mm, p.z);
    if (!p.weak) continue;
    ++r.weak;
    if (p.snr < p.threshold) ++r.failed;
    r.snr_min = std::min(r.snr_min, p.snr);
    r.snr_max = std::max(r.snr_max, p.snr);
    r.threshold = std::max(r.threshold, p.threshold);
  }
  r.light_ratio = median_light > 0.0 ? Median(light) / median_light : 1.0;
  r.dim = r.light_ratio < options_.dim_fraction;
  return r;
}

std::vector<WeakRegion> ImpressionRegionTally::WeakRegions() const {
  const int n = options_.sectors;
  std::vector<double> light;
  for (const Press& p : presses_) light.push_back(p.reference_dn);
  const double median_light = Median(light);
  std::vector<Run> done, open;
  for (int band = 0; band <= bands_; ++band) {
    // Runs of weak cells around the ring (none past the last band: every open run closes).
    std::vector<Run> runs;
    if (band < bands_) {
      int weak = 0;
      for (int s = 0; s < n; ++s) weak += IsWeakCell(band, s) ? 1 : 0;
      if (weak == n) {
        runs.push_back({0, n, band, band});
      } else if (weak > 0) {
        int start = 0;
        while (IsWeakCell(band, start)) ++start;  // just after a run's end: none cut in two
        for (int k = 0; k < n;) {
          if (!IsWeakCell(band, (start + k) % n)) {
            ++k;
            continue;
          }
          Run r{(start + k) % n, 0, band, band};
          while (k < n && IsWeakCell(band, (start + k) % n)) ++r.count, ++k;
          runs.push_back(r);
        }
      }
    }
    std::vector<Run> next;
    for (Run r : runs) {
      const auto same = std::find_if(open.begin(), open.end(), [&](const Run& o) {
        return o.first == r.first && o.count == r.count;
      });
      if (same != open.end()) {
        r.band_first = same->band_first;
        open.erase(same);
      }
      next.push_back(r);
    }
    done.insert(done.end(), open.begin(), open.end());
    open = std::move(next);
  }
  std::vector<WeakRegion> out;
  for (const Run& r : done) {
    out.push_back(Summarise(r.band_first, r.band_last, r.first, r.count, median_light));
  }
  std::sort(out.begin(), out.end(),
            [](const WeakRegion& a, const WeakRegion& b) { return a.weak > b.weak; });
  return out;
}

}  // namespace gs360
