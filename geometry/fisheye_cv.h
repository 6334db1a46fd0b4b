#pragma once
// OpenCV adapter for the fisheye model (kept out of geometry/fisheye.h): the K matrix and D
// vector used by cv::fisheye::calibrate / projectPoints / undistortPoints.
// OpenCV 4.6 caveats (checked by tests/geometry/fisheye_test.cc): cv::fisheye::projectPoints
// ignores K(0, 1) and takes the skew as its `alpha` argument (pass intrinsics.skew);
// cv::fisheye::undistortPoints ignores the skew altogether. cv::fisheye::calibrate returns
// K(0, 1) = fx * alpha, which is what FromCv expects.

#include <opencv2/core.hpp>

#include "geometry/fisheye.h"

namespace gs360 {

// K = [fx, fx * skew, cx; 0, fy, cy; 0, 0, 1]
cv::Matx33d ToCvK(const FisheyeIntrinsics& intrinsics);
// D = (k1, k2, k3, k4)
cv::Vec4d ToCvD(const FisheyeIntrinsics& intrinsics);
// Inverse of the above. skew = K(0,1) / K(0,0). Throws std::invalid_argument (via Check()) for
// an unusable K (e.g. fx <= 0) or K(1,0), K(2,0), K(2,1) not 0 or K(2,2) not 1.
FisheyeIntrinsics FromCv(const cv::Matx33d& K, const cv::Vec4d& D, int width, int height,
                         double max_theta = 1.5707963267948966);

}  // namespace gs360
