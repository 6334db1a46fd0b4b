#include "geometry/fisheye_cv.h"

#include <stdexcept>
#include <string>

namespace gs360 {

cv::Matx33d ToCvK(const FisheyeIntrinsics& in) {
  return cv::Matx33d(in.fx, in.fx * in.skew, in.cx, 0.0, in.fy, in.cy, 0.0, 0.0, 1.0);
}

cv::Vec4d ToCvD(const FisheyeIntrinsics& in) {
  return cv::Vec4d(in.k[0], in.k[1], in.k[2], in.k[3]);
}

FisheyeIntrinsics FromCv(const cv::Matx33d& K, const cv::Vec4d& D, int width, int height,
                         double max_theta) {
  if (K(1, 0) != 0.0 || K(2, 0) != 0.0 || K(2, 1) != 0.0 || K(2, 2) != 1.0) {
    throw std::invalid_argument(
        "FromCv: K must have the form [fx, s, cx; 0, fy, cy; 0, 0, 1], got last rows [" +
        std::to_string(K(1, 0)) + ", ...; " + std::to_string(K(2, 0)) + ", " +
        std::to_string(K(2, 1)) + ", " + std::to_string(K(2, 2)) + "]");
  }
  FisheyeIntrinsics in;
  in.width = width;
  in.height = height;
  in.fx = K(0, 0);
  in.fy = K(1, 1);
  in.cx = K(0, 2);
  in.cy = K(1, 2);
  in.skew = K(0, 0) != 0.0 ? K(0, 1) / K(0, 0) : 0.0;
  in.k = {D[0], D[1], D[2], D[3]};
  in.max_theta = max_theta;
  in.Check();
  return in;
}

}  // namespace gs360
