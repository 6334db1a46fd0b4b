#pragma once
// A less biased impression centre for pose estimation. capture/impression.h FindImpression
// weights the blob by the colour difference, which follows the LED directions: a spherical
// imprint lights up on one side and darkens on the other (and its centre, whose normal is
// unchanged, barely differs from the reference), so the weighted centroid is pulled toward the
// lit side by several pixels. Here the imprint's REGION is estimated instead: the pixels where the
// blurred difference magnitude exceeds a fraction of its peak, near the peak, closed by their
// convex hull (the imprint of a ball is a convex blob in the image of a smooth surface).
// That region still follows the lighting where one side of the imprint changes colour much less
// than the other (an imprint seen face-on and lit from one side, as every probe of a dome is):
// a threshold at a fraction of the GLOBAL peak keeps the lit side's whole slope but cuts the dim
// side well inside its edge, a crescent whose centre sits several pixels toward the lit side. So
// the edge is then found per direction (`directions` rays from the region's centre): where the
// magnitude along the ray falls below threshold_fraction of that ray's own maximum, beyond it.
// The lighting scales each direction's profile by its own gain, which that ratio divides out.
// The centre is the area centroid of the polygon of those edge points, the rays cast again from
// it (`direction_rounds`). It estimates the centroid of the deformed region, which
// calib/render.h's contact_centroid models (the elastic rim widens the region almost
// symmetrically).
//
// Pixels: (u right, v down), as geometry/fisheye.h.

#include <Eigen/Core>
#include <optional>
#include <vector>

#include <opencv2/core/mat.hpp>

namespace gs360 {

struct ImpressionCentroidOptions {
  double blur_sigma_px = 1.5;       // Gaussian blur of the difference magnitude (>= 0)
  double min_peak_dn = 6.0;         // weaker peaks: no impression (> 0)
  double threshold_fraction = 0.2;  // region = pixels above this fraction of the peak, (0, 1)
  double min_threshold_dn = 3.0;    // ... and above this many DN (noise floor, >= 0)
  double window_px = 60.0;          // only pixels within this distance of the peak (> 0)
  // With an expected pixel: a peak farther than this from it is looked for again near it (> 0).
  double search_radius_px = 40.0;
  // More than this fraction of the usable pixels above the threshold, anywhere: no press but a
  // frame unlike the reference everywhere (saturated, black, corrupt): no impression ((0, 1]).
  double max_area_fraction = 0.25;
  // The per-direction edge (see above): rays around the region's centre (0 = the hull centroid
  // alone, else >= 8); how often they are cast again from the new centre (>= 1); a ray whose
  // maximum is below this fraction of the peak (or below min_threshold_dn) has no edge of its own
  // ([0, 1)); fewer rays with an edge than min_direction_share of them (or a ray leaving the
  // image or `mask` before its edge): the hull centroid is kept ((0, 1]).
  int directions = 72;
  int direction_rounds = 3;
  double min_direction_fraction = 0.05;
  double min_direction_share = 0.75;
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("blur_sigma_px", self.blur_sigma_px);
    visit("min_peak_dn", self.min_peak_dn);
    visit("threshold_fraction", self.threshold_fraction);
    visit("min_threshold_dn", self.min_threshold_dn);
    visit("window_px", self.window_px);
    visit("search_radius_px", self.search_radius_px);
    visit("max_area_fraction", self.max_area_fraction);
    visit("directions", self.directions);
    visit("direction_rounds", self.direction_rounds);
    visit("min_direction_fraction", self.min_direction_fraction);
    visit("min_direction_share", self.min_direction_share);
  }
  void Check() const;  // throws std::invalid_argument naming the field and value
};

struct ImpressionRegion {
  // The centre (px): the per-direction edge polygon's area centroid, or hull_centroid where the
  // directions found no edge (or `directions` is 0).
  Eigen::Vector2d centroid = Eigen::Vector2d::Zero();
  Eigen::Vector2d hull_centroid = Eigen::Vector2d::Zero();      // the thresholded region's hull
  bool directional = false;                                     // centroid from the directions
  Eigen::Vector2d weighted_centroid = Eigen::Vector2d::Zero();  // difference-weighted (px)
  double peak_dn = 0.0;
  bool near_expected = false;  // the peak lies within search_radius_px of expected_px
  double area_px = 0.0;        // hull area
  int pixels = 0;              // pixels in the region (above the threshold, connected to the peak)
  cv::Rect box;                // bounding box of the region
};

// `press`, `reference`: CV_8UC3 of one size (std::invalid_argument otherwise); optional `mask`
// (CV_8U, non-zero = usable). nullopt when no peak reaches min_peak_dn, or when more than
// max_area_fraction of the usable pixels exceed the threshold. `expected_px` (optional, pixels):
// where the press should show (its contact point through the nominal pose). When the frame's
// strongest change lies farther than options.search_radius_px from it, the strongest change
// within that radius is taken instead, if it reaches min_peak_dn, so that another change in the
// frame (LED drift, a fin's edge) is not taken for a faint press; a non-finite one is ignored.
// The region is the pixels above the threshold within window_px of the peak and connected to it.
std::optional<ImpressionRegion> FindImpressionRegion(
    const cv::Mat& press, const cv::Mat& reference, const ImpressionCentroidOptions& options = {},
    const cv::Mat& mask = cv::Mat(), const std::optional<Eigen::Vector2d>& expected_px = {});

// The same on a change magnitude already computed and blurred (CV_32F, non-empty; what
// FindImpressionRegion computes from the press and reference; std::invalid_argument otherwise).
// calib/pose.h's bias model runs it on rendered imprints.
std::optional<ImpressionRegion> FindImpressionRegionInMagnitude(
    const cv::Mat& magnitude, const ImpressionCentroidOptions& options,
    const cv::Mat& mask = cv::Mat(), const std::optional<Eigen::Vector2d>& expected_px = {});

// Whether a run's nominal pose holds: at least half of its `found` impressions are `near` their
// expected pixel. When it does, an impression found far from it is another change in its frame,
// not the press; when it does not, the nominal pose is off and the pose fit sorts them out.
bool NominalPoseHolds(int found, int near);

// The run rule above over a run's impressions: when the nominal pose holds, each item `found` far
// from its expected pixel (its `near` flag false) is set not found. Returns how many were.
template <typename Item>
int DropFarFromNominal(std::vector<Item>& items, bool Item::*found, bool Item::*near) {
  int n_found = 0, n_near = 0;
  for (const Item& item : items) {
    n_found += item.*found ? 1 : 0;
    n_near += item.*found && item.*near ? 1 : 0;
  }
  if (!NominalPoseHolds(n_found, n_near)) return 0;
  for (Item& item : items) item.*found = item.*found && item.*near;
  return n_found - n_near;
}

}  // namespace gs360
