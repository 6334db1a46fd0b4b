#include "plan/coverage.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "base/format.h"

namespace gs360 {
namespace {

constexpr double kPi = 3.14159265358979323846;

// A run of gap sectors [first, first + count) (mod sectors) in one band, and what it holds.
struct Run {
  int first = 0;
  int count = 0;
  int candidates = 0;
  std::array<int, kNumDropReasons> reasons{};
};

DropReason MostFrequent(const std::array<int, kNumDropReasons>& reasons) {
  return static_cast<DropReason>(std::max_element(reasons.begin(), reasons.end()) -
                                 reasons.begin());
}

}  // namespace

void CoverageOptions::Check() const {
  if (!(band_mm > 0.0) || !std::isfinite(band_mm)) {
    throw std::invalid_argument("CoverageOptions.band_mm must be > 0, got " +
                                FormatFixed(band_mm, 3));
  }
  if (sectors < 1 || sectors > 360) {
    throw std::invalid_argument("CoverageOptions.sectors must be in 1..360, got " +
                                std::to_string(sectors));
  }
  if (min_candidates < 1) {
    throw std::invalid_argument("CoverageOptions.min_candidates must be >= 1, got " +
                                std::to_string(min_candidates));
  }
}

std::string CoverageGap::Describe() const {
  std::string where = "z " + FormatFixed(z_min_mm, 1) + "-" + FormatFixed(z_max_mm, 1) + " mm ";
  if (all_around) {
    where += "all around";
  } else if (azimuth_max_deg < azimuth_min_deg) {  // across +-180
    where += "at azimuth " + FormatFixed(azimuth_min_deg, 0) + " to 180 and -180 to " +
             FormatFixed(azimuth_max_deg, 0) + " deg";
  } else {
    where += "at azimuth " + FormatFixed(azimuth_min_deg, 0) + " to " +
             FormatFixed(azimuth_max_deg, 0) + " deg";
  }
  return where + ": " + std::to_string(candidates) + " candidates, none kept (most for " +
         std::string(DropReasonName(reason)) + ")";
}

nlohmann::json CoverageGap::ToJson() const {
  return {{"z_min_mm", z_min_mm},
          {"z_max_mm", z_max_mm},
          {"azimuth_min_deg", azimuth_min_deg},
          {"azimuth_max_deg", azimuth_max_deg},
          {"all_around", all_around},
          {"candidates", candidates},
          {"reason", std::string(DropReasonName(reason))},
          {"text", Describe()}};
}

CoverageTally::CoverageTally(double height_mm, const CoverageOptions& options)
    : height_mm_(height_mm), options_(options) {
  options_.Check();
  if (!(height_mm > 0.0) || !std::isfinite(height_mm)) {
    throw std::invalid_argument("CoverageTally: the sensor height must be > 0, got " +
                                FormatFixed(height_mm, 3));
  }
  bands_ = std::max(1, static_cast<int>(std::ceil(height_mm / options_.band_mm - 1e-9)));
  cells_.resize(static_cast<std::size_t>(bands_) * options_.sectors);
}

void CoverageTally::Add(const Eigen::Vector3d& p, std::optional<DropReason> reason) {
  if (!p.allFinite()) return;
  const int band =
      std::clamp(static_cast<int>(std::floor(p.z() / options_.band_mm)), 0, bands_ - 1);
  const double turn = (std::atan2(p.y(), p.x()) + kPi) / (2.0 * kPi);  // [0, 1]
  const int sector =
      std::clamp(static_cast<int>(std::floor(turn * options_.sectors)), 0, options_.sectors - 1);
  Cell& c = cells_[static_cast<std::size_t>(band) * options_.sectors + sector];
  ++c.candidates;
  if (reason) {
    ++c.reasons[static_cast<int>(*reason)];
  } else {
    ++c.kept;
  }
}

bool CoverageTally::IsGap(const Cell& c) const {
  return c.kept == 0 && c.candidates >= options_.min_candidates;
}

std::vector<CoverageGap> CoverageTally::Gaps() const {
  const int n = options_.sectors;
  const double sector_deg = 360.0 / n;
  std::vector<CoverageGap> done;
  // Gaps still open in the band below: their sector run (its reasons summed over their bands so
  // far) and the gap itself.
  std::vector<std::pair<Run, CoverageGap>> open;
  auto close = [&](std::pair<Run, CoverageGap>& g) {
    g.second.reason = MostFrequent(g.first.reasons);
    done.push_back(g.second);
  };
  for (int band = 0; band < bands_; ++band) {
    const Cell* row = &cells_[static_cast<std::size_t>(band) * n];
    // Runs of gap cells around the ring; one that wraps past sector n - 1 starts before it.
    std::vector<Run> runs;
    const bool ring = std::all_of(row, row + n, [&](const Cell& c) { return IsGap(c); });
    int start = 0;
    if (!ring) {
      while (IsGap(row[start])) ++start;  // begin just after a gap's end: no run is cut in two
    }
    for (int k = 0; k < n;) {
      const int s = (start + k) % n;
      if (!IsGap(row[s])) {
        ++k;
        continue;
      }
      Run r;
      r.first = s;
      while (k < n && IsGap(row[(start + k) % n])) {
        const Cell& c = row[(start + k) % n];
        r.candidates += c.candidates;
        for (int i = 0; i < kNumDropReasons; ++i) r.reasons[i] += c.reasons[i];
        ++r.count;
        ++k;
      }
      runs.push_back(r);
    }
    std::vector<std::pair<Run, CoverageGap>> next;
    for (const Run& r : runs) {
      auto same = std::find_if(open.begin(), open.end(), [&](const auto& g) {
        return g.first.first == r.first && g.first.count == r.count &&
               MostFrequent(g.first.reasons) == MostFrequent(r.reasons);
      });
      std::pair<Run, CoverageGap> g;
      if (same != open.end()) {
        g = *same;
        open.erase(same);
        g.second.candidates += r.candidates;
        for (int i = 0; i < kNumDropReasons; ++i) g.first.reasons[i] += r.reasons[i];
      } else {
        g.first = r;
        g.second.z_min_mm = band * options_.band_mm;
        g.second.candidates = r.candidates;
        g.second.all_around = r.count == n;
        g.second.azimuth_min_deg = -180.0 + r.first * sector_deg;
        g.second.azimuth_max_deg = g.second.azimuth_min_deg + r.count * sector_deg;
        if (g.second.azimuth_max_deg > 180.0) g.second.azimuth_max_deg -= 360.0;
      }
      g.second.z_max_mm = std::min(height_mm_, (band + 1) * options_.band_mm);
      next.push_back(g);
    }
    for (auto& g : open) close(g);
    open = std::move(next);
  }
  for (auto& g : open) close(g);
  std::stable_sort(done.begin(), done.end(), [](const CoverageGap& a, const CoverageGap& b) {
    return a.candidates > b.candidates;
  });
  return done;
}

}  // namespace gs360
