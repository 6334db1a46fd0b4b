#pragma once
// Run-time reconstruction: a tactile frame in, the shape of what touches the gel out.
//
//   frame -> normalised difference against the reference (recon/features.h)
//         -> contact regions (blobs of change, grown into rectangular ROIs)
//         -> per visible ROI pixel, the MLP's tangent-frame slopes (gx, gy)
//         -> normals n = normalise(n0 + gx t1 + gy t2) (recon/surface_map.h)
//         -> gradients of psi = log(rho / rho0) -> integration with psi = 0 on the ROI border
//            (recon/integration.h) -> rho = rho0 e^psi
//         -> indentation and a point cloud.
// Frames without contact cost one difference and a threshold.
//
// Outputs (per region, roi-sized, row = v): rho (mm along the pixel's unit ray from the camera
// centre), indentation (mm, + into the gel: how far the gel moved along its own undeformed
// normal to reach the reconstructed point, recon/integration.h NormalIndentation), normals in
// the camera frame.
// Points are in the SENSOR frame (cam_from_sensor of the model), mm.
//
// Thread safety: Reconstruct is const and may run on several threads at once.

#include <Eigen/Core>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json_fwd.hpp>
#include <opencv2/core/mat.hpp>

#include "geometry/fisheye.h"
#include "recon/features.h"
#include "recon/integration.h"
#include "recon/mlp.h"
#include "recon/surface_map.h"

namespace gs360 {

struct ReconstructionOptions {
  DifferenceOptions difference;
  ContactDetectionOptions detection;
  GradientOptions gradients;
  IntegrationOptions integration;
  // A half-size look at the frame first: a frame that nowhere differs from the reference by
  // half the detection threshold has no contact, and costs a fraction of the full difference.
  // A run-time choice, not part of a model (not serialised).
  bool screen = true;
  // The MLP on every n-th pixel of a region in u and v, bilinear between (1: every pixel).
  // Run-time, not serialised.
  int mlp_stride = 1;
  // With mlp_stride > 1: a grid cell whose nodes' slopes differ by more than this (either
  // component) is evaluated at every pixel (an imprint's rim, where bilinear blurs a jump).
  // Run-time, not serialised. >= 0 (0: every cell with any difference).
  double mlp_refine_slope = 0.2;
  // Throws std::invalid_argument naming the field (delegates to the nested Check()s).
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("difference", self.difference);
    visit("detection", self.detection);
    visit("gradients", self.gradients);
    visit("integration", self.integration);
    visit("screen", self.screen);
    visit("mlp_stride", self.mlp_stride);
    visit("mlp_refine_slope", self.mlp_refine_slope);
  }
  void Check() const;
};
nlohmann::json ReconstructionOptionsToJson(const ReconstructionOptions& options);
// Strict: unknown keys or wrong types throw std::invalid_argument naming `where` and the field.
// Missing keys keep their defaults, except difference.context_sigmas_px: a "difference" object
// without it was written before context features existed, and means none; and
// integration.height_field_oblique_iterations: without it, height_field_iterations applies at
// every view angle, as it did then.
ReconstructionOptions ReconstructionOptionsFromJson(const nlohmann::json& json,
                                                    const std::string& where);

struct RegionReconstruction {
  ContactRegion region;
  cv::Mat slopes;       // CV_32FC2 (gx, gy); 0 where not visible
  cv::Mat normals;      // CV_64FC3 camera frame; NaN where not visible
  cv::Mat rho;          // CV_64F mm; NaN where not visible
  cv::Mat indentation;  // CV_64F mm (+ into the gel); NaN where not visible
  double peak_indentation_mm = 0.0;
  double mlp_seconds = 0.0;
  double integration_seconds = 0.0;
};

struct DetectedContacts {
  cv::Mat difference;                  // CV_32FC3 full image; empty when the screen saw nothing
  std::vector<ContactRegion> regions;  // largest first
  cv::Vec3d gain{1.0, 1.0, 1.0};
  cv::Rect window;  // where the difference was computed (the whole image without the screen)
};

struct FrameReconstruction {
  std::vector<RegionReconstruction> regions;  // empty = no contact
  cv::Vec3d gain{1.0, 1.0, 1.0};              // LED drift gain found against the reference
  // Empty for a usable frame. Otherwise why the frame was not reconstructed (regions is then
  // empty): its brightness in a channel is outside half to twice the reference's (a black or
  // saturated frame, the LEDs off), or it differs from the reference over more of the image
  // than any contact could (a corrupt frame, the lighting changed, the camera moved).
  std::string problem;
  double changed_fraction = 0.0;  // of the visible pixels, the share the detection marks changed
  double seconds = 0.0;
};

// Mean view angle (deg, recon/surface_map.h) over the roi's visible pixels whose slopes
// (CV_32FC2, roi-sized) exceed 0.3 in magnitude -- the imprint -- or over all visible pixels
// when none does; 0 when none is visible. Picks the integrator for kHeightField.
double ImprintViewAngleDeg(const SurfaceMap& map, const cv::Rect& roi, const cv::Mat& slopes);

// Where the height field solves for a region (HeightFieldOptions::window_grow_fraction): the
// blob grown, clipped to region.roi, in image pixels; region.roi itself when the fraction is at
// least the detection's grow_fraction or the window would be smaller than 3 x 3.
cv::Rect HeightFieldWindow(const ContactRegion& region, const ContactDetectionOptions& detection,
                           const HeightFieldOptions& height_field);

class Reconstructor {
 public:
  // `reference`: CV_8UC3 of the map's size. Throws std::invalid_argument for mismatched sizes,
  // an MLP that is not kFeatureCount -> 2, or invalid options.
  Reconstructor(std::shared_ptr<const SurfaceMap> map, const FisheyeCamera& camera, Mlp mlp,
                cv::Mat reference, const ReconstructionOptions& options);

  const SurfaceMap& map() const { return *map_; }
  const FisheyeCamera& camera() const { return camera_; }
  const Mlp& mlp() const { return mlp_; }
  const cv::Mat& reference() const { return reference_; }
  const ReconstructionOptions& options() const { return options_; }

  // Against the model's reference frame, or a given (newer) one.
  FrameReconstruction Reconstruct(const cv::Mat& frame) const;
  FrameReconstruction Reconstruct(const cv::Mat& frame, const cv::Mat& reference) const;

  // The screen (ReconstructionOptions::screen): nullopt when the frame certainly has no contact,
  // else the window of the image the full-resolution difference must cover.
  std::optional<cv::Rect> ScreenWindow(const cv::Mat& frame, const cv::Mat& reference) const;
  bool MayTouch(const cv::Mat& frame, const cv::Mat& reference) const;
  // The screen, the normalised difference inside its window (0 outside) and the contact regions
  // found there: the first half of Reconstruct.
  DetectedContacts Detect(const cv::Mat& frame, const cv::Mat& reference) const;

  // The pieces, for validation and tools:
  // CV_32FC3 normalised difference, masked to visible pixels.
  cv::Mat Difference(const cv::Mat& frame, const cv::Mat& reference,
                     cv::Vec3d* gain = nullptr) const;
  // MLP slopes (CV_32FC2, roi-sized) for the visible pixels of roi, or only of those inside
  // `window` (image pixels; 0 elsewhere).
  cv::Mat PredictSlopes(const cv::Mat& normalized_difference, const cv::Rect& roi) const;
  cv::Mat PredictSlopes(const cv::Mat& normalized_difference, const cv::Rect& roi,
                        const cv::Rect& window) const;
  // Where IntegrateSlopes uses slopes for `region` with these options (the height field's
  // window, else region.roi): PredictSlopes need not evaluate the MLP beyond it.
  cv::Rect SlopesWindow(const ContactRegion& region, const IntegrationOptions& integration) const;
  // Slopes -> normals -> integration on region.roi with the given integration options.
  RegionReconstruction ReconstructRegion(const cv::Mat& normalized_difference,
                                         const ContactRegion& region,
                                         const IntegrationOptions& integration) const;
  // Given slopes for region.roi (CV_32FC2): normals, integration, indentation.
  RegionReconstruction IntegrateSlopes(const cv::Mat& slopes, const ContactRegion& region,
                                       const IntegrationOptions& integration) const;

  // Points (sensor frame, mm) of the pixels whose indentation exceeds min_indentation_mm.
  std::vector<Eigen::Vector3f> PointCloud(const FrameReconstruction& reconstruction,
                                          double min_indentation_mm = 0.02) const;

 private:
  // ScreenWindow, and the LED drift gain it estimated on the way (when `gain` is not null).
  std::optional<cv::Rect> Screen(const cv::Mat& frame, const cv::Mat& reference,
                                 cv::Vec3d* gain) const;
  // The MLP's slopes for `pixels` (inside win, inside roi), written into *slopes (roi-sized
  // CV_32FC2); `context` covers win.
  void EvaluateSlopes(const cv::Mat& diff, const cv::Mat& context, const cv::Rect& win,
                      const cv::Rect& roi, const std::vector<cv::Point>& pixels,
                      cv::Mat* slopes) const;
  // PredictSlopes' stride-s grid over `win`, bilinear between its nodes; `context` covers win.
  void InterpolateSlopes(const cv::Mat& diff, const cv::Mat& context, const cv::Rect& roi,
                         const cv::Rect& win, cv::Mat* slopes) const;
  template <typename Integrate>
  cv::Mat IntegrateInWindow(const cv::Rect& roi, const cv::Rect& window, Integrate integrate) const;

  std::shared_ptr<const SurfaceMap> map_;
  FisheyeCamera camera_;
  Mlp mlp_;
  cv::Mat reference_;
  cv::Mat visible_;
  int visible_pixels_ = 0;
  cv::Mat coarse_visible_;    // CV_8U, half size: 255 where all four pixels are visible
  cv::Mat coarse_reference_;  // reference_ at half size (2x2 means)
  ReconstructionOptions options_;
};

}  // namespace gs360
