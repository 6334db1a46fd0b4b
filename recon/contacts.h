#pragma once
// What a reconstructed frame says to a user or a robot: the indentation as an image on the
// camera's pixel grid, and one summary per contact (where, how deep, how large, whether the
// camera saw all of it).
//
// Units and frames: millimetres; positions in the SENSOR frame (the model's cam_from_sensor);
// indentation along the gel's undeformed outward normal, + into the gel
// (recon/reconstructor.h).

#include <vector>

#include <Eigen/Core>
#include <opencv2/core/mat.hpp>

#include "recon/reconstructor.h"

namespace gs360 {

struct ContactSummary {
  cv::Rect roi;  // the region's rectangle in the image (pixels)
  // Indentation-weighted centroid of the contact's surface points (sensor frame, mm).
  Eigen::Vector3d centre_sensor = Eigen::Vector3d::Zero();
  Eigen::Vector3d peak_sensor = Eigen::Vector3d::Zero();  // the deepest point (sensor frame)
  double peak_indentation_mm = 0.0;
  // Undeformed gel area whose indentation exceeds the threshold (mm^2), and its pixel count.
  double area_mm2 = 0.0;
  int pixels = 0;
  // The contact, where still more than a quarter of its peak deep, reaches pixels the camera
  // does not see (a fin, a grazing view, the image's edge): its shape and area are cut there.
  bool partial = false;
};

// One summary per region with at least one pixel deeper than `min_indentation_mm` (>= 0), in
// the regions' order.
std::vector<ContactSummary> SummarizeContacts(const Reconstructor& reconstructor,
                                              const FrameReconstruction& frame,
                                              double min_indentation_mm = 0.02);

// The indentation of every pixel (CV_32F, the map's size, mm): 0 outside the regions and where
// nothing was reconstructed.
cv::Mat IndentationImage(const Reconstructor& reconstructor, const FrameReconstruction& frame);

}  // namespace gs360
