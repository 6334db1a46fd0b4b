#include "recon/reconstructor.h"

#include <chrono>
#include <cmath>
#include <functional>
#include <limits>
#include <map>
#include <numbers>
#include <optional>
#include <set>
#include <stdexcept>

#include <nlohmann/json.hpp>
#include <opencv2/imgproc.hpp>

namespace gs360 {
namespace {

using Json = nlohmann::json;
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
// The screen passes a frame on to the full path when its coarse |f| reaches this fraction of the
// detection threshold: the margin covers what the full resolution adds to a small contact's peak.
constexpr double kScreenFraction = 0.75;

double Seconds(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// Strict reader of one JSON object: every key must be claimed by a field.
class ObjectReader {
 public:
  ObjectReader(const Json& json, std::string where) : json_(json), where_(std::move(where)) {
    if (!json_.is_object()) throw std::invalid_argument(where_ + ": expected an object");
  }
  template <typename T>
  void Read(const char* key, T* value) {
    seen_.insert(key);
    auto it = json_.find(key);
    if (it == json_.end()) return;
    try {
      *value = it->get<T>();
    } catch (const Json::exception&) {
      throw std::invalid_argument(where_ + "." + key + ": wrong type (" + it->dump() + ")");
    }
  }
  const Json* Child(const char* key) {
    seen_.insert(key);
    auto it = json_.find(key);
    return it == json_.end() ? nullptr : &*it;
  }
  const std::string& where() const { return where_; }
  void Finish() const {
    for (auto it = json_.begin(); it != json_.end(); ++it) {
      if (!seen_.count(it.key())) {
        throw std::invalid_argument(where_ + "." + it.key() + ": unknown field");
      }
    }
  }

 private:
  const Json& json_;
  std::string where_;
  std::set<std::string> seen_;
};

}  // namespace

void ReconstructionOptions::Check() const {
  if (mlp_stride < 1 || mlp_stride > 8) {
    throw std::invalid_argument("ReconstructionOptions.mlp_stride = " + std::to_string(mlp_stride) +
                                " must be in 1..8");
  }
  if (!(mlp_refine_slope >= 0.0)) {
    throw std::invalid_argument("ReconstructionOptions.mlp_refine_slope = " +
                                std::to_string(mlp_refine_slope) + ": must be >= 0");
  }
  difference.Check();
  detection.Check();
  gradients.Check();
  integration.Check();
}

Json ReconstructionOptionsToJson(const ReconstructionOptions& o) {
  return Json{
      {"difference",
       {{"floor_dn", o.difference.floor_dn},
        {"compensate_gain", o.difference.compensate_gain},
        {"gain_min_reference_dn", o.difference.gain_min_reference_dn},
        {"gain_stride", o.difference.gain_stride},
        {"smooth_sigma_px", o.difference.smooth_sigma_px},
        {"context_sigmas_px", o.difference.context_sigmas_px}}},
      {"detection",
       {{"blur_sigma_px", o.detection.blur_sigma_px},
        {"threshold", o.detection.threshold},
        {"min_area_px", o.detection.min_area_px},
        {"grow_fraction", o.detection.grow_fraction},
        {"grow_px", o.detection.grow_px},
        {"max_regions", o.detection.max_regions}}},
      {"gradients", {{"min_grazing_deg", o.gradients.min_grazing_deg}}},
      {"integration",
       {{"method", std::string(ToString(o.integration.method))},
        {"iterations", o.integration.iterations},
        {"sharpness", o.integration.sharpness},
        {"scale", o.integration.scale},
        {"min_weight", o.integration.min_weight},
        {"tolerance", o.integration.tolerance},
        {"height_field_iterations", o.integration.height_field.iterations},
        {"height_field_oblique_iterations", o.integration.height_field.oblique_iterations},
        {"height_field_oblique_view_angle_deg", o.integration.height_field.oblique_view_angle_deg},
        {"height_field_tolerance", o.integration.height_field.tolerance},
        {"height_field_unobserved_weight", o.integration.height_field.unobserved_weight},
        {"height_field_min_normal_dot", o.integration.height_field.min_normal_dot},
        {"height_field_min_view_angle_deg", o.integration.height_field.min_view_angle_deg},
        {"height_field_window_grow_fraction", o.integration.height_field.window_grow_fraction}}},
  };
}

ReconstructionOptions ReconstructionOptionsFromJson(const Json& json, const std::string& where) {
  ReconstructionOptions o;
  ObjectReader root(json, where);
  if (const Json* j = root.Child("difference")) {
    ObjectReader r(*j, where + ".difference");
    r.Read("floor_dn", &o.difference.floor_dn);
    r.Read("compensate_gain", &o.difference.compensate_gain);
    r.Read("gain_min_reference_dn", &o.difference.gain_min_reference_dn);
    r.Read("gain_stride", &o.difference.gain_stride);
    r.Read("smooth_sigma_px", &o.difference.smooth_sigma_px);
    // Absent: a model from before the context features (its MLP takes 5 inputs).
    if (!j->contains("context_sigmas_px")) o.difference.context_sigmas_px.clear();
    r.Read("context_sigmas_px", &o.difference.context_sigmas_px);
    r.Finish();
  }
  if (const Json* j = root.Child("detection")) {
    ObjectReader r(*j, where + ".detection");
    r.Read("blur_sigma_px", &o.detection.blur_sigma_px);
    r.Read("threshold", &o.detection.threshold);
    r.Read("min_area_px", &o.detection.min_area_px);
    r.Read("grow_fraction", &o.detection.grow_fraction);
    r.Read("grow_px", &o.detection.grow_px);
    r.Read("max_regions", &o.detection.max_regions);
    r.Finish();
  }
  if (const Json* j = root.Child("gradients")) {
    ObjectReader r(*j, where + ".gradients");
    r.Read("min_grazing_deg", &o.gradients.min_grazing_deg);
    r.Finish();
  }
  if (const Json* j = root.Child("integration")) {
    ObjectReader r(*j, where + ".integration");
    std::string method(ToString(o.integration.method));
    r.Read("method", &method);
    try {
      o.integration.method = ParseIntegrationMethod(method);
    } catch (const std::exception&) {
      throw std::invalid_argument(where + ".integration.method: unknown method \"" + method +
                                  "\" (poisson, discontinuity or heightfield)");
    }
    r.Read("iterations", &o.integration.iterations);
    r.Read("sharpness", &o.integration.sharpness);
    r.Read("scale", &o.integration.scale);
    r.Read("min_weight", &o.integration.min_weight);
    r.Read("tolerance", &o.integration.tolerance);
    r.Read("height_field_iterations", &o.integration.height_field.iterations);
    // Absent in bundles from before the split: one pass count everywhere, as then.
    if (!j->contains("height_field_oblique_iterations")) {
      o.integration.height_field.oblique_iterations = o.integration.height_field.iterations;
    }
    r.Read("height_field_oblique_iterations", &o.integration.height_field.oblique_iterations);
    r.Read("height_field_oblique_view_angle_deg",
           &o.integration.height_field.oblique_view_angle_deg);
    r.Read("height_field_tolerance", &o.integration.height_field.tolerance);
    r.Read("height_field_unobserved_weight", &o.integration.height_field.unobserved_weight);
    r.Read("height_field_min_normal_dot", &o.integration.height_field.min_normal_dot);
    r.Read("height_field_min_view_angle_deg", &o.integration.height_field.min_view_angle_deg);
    // Absent in bundles from before the window: the default window all the same (it depends on
    // nothing the training saw).
    r.Read("height_field_window_grow_fraction", &o.integration.height_field.window_grow_fraction);
    r.Finish();
  }
  root.Finish();
  try {
    o.Check();
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument(where + ": " + e.what());
  }
  return o;
}

Reconstructor::Reconstructor(std::shared_ptr<const SurfaceMap> map, const FisheyeCamera& camera,
                             Mlp mlp, cv::Mat reference, const ReconstructionOptions& options)
    : map_(std::move(map)),
      camera_(camera),
      mlp_(std::move(mlp)),
      reference_(std::move(reference)),
      options_(options) {
  options_.Check();
  if (!map_) throw std::invalid_argument("Reconstructor: no surface map");
  if (map_->width() != camera_.width() || map_->height() != camera_.height()) {
    throw std::invalid_argument("Reconstructor: surface map " + std::to_string(map_->width()) +
                                "x" + std::to_string(map_->height()) + " does not match camera " +
                                std::to_string(camera_.width()) + "x" +
                                std::to_string(camera_.height()));
  }
  if (reference_.type() != CV_8UC3 || reference_.cols != map_->width() ||
      reference_.rows != map_->height()) {
    throw std::invalid_argument("Reconstructor: the reference frame must be CV_8UC3 " +
                                std::to_string(map_->width()) + "x" +
                                std::to_string(map_->height()));
  }
  const int features = FeatureCount(options_.difference);
  if (mlp_.input_size() != features || mlp_.output_size() != 2) {
    throw std::invalid_argument(
        "Reconstructor: the MLP maps " + std::to_string(mlp_.input_size()) + " -> " +
        std::to_string(mlp_.output_size()) + ", expected " + std::to_string(features) + " -> 2 (" +
        std::to_string(options_.difference.context_sigmas_px.size()) + " context scales)");
  }
  visible_ = map_->VisibleMask();
  visible_pixels_ = cv::countNonZero(visible_);
  // The screen's half-size images: a coarse pixel counts only where all four fine ones are seen.
  cv::Mat coarse_visible;
  cv::resize(visible_, coarse_visible, cv::Size(), 0.5, 0.5, cv::INTER_AREA);
  coarse_visible_ = coarse_visible == 255;
  cv::resize(reference_, coarse_reference_, coarse_visible_.size(), 0, 0, cv::INTER_AREA);
}

std::optional<cv::Rect> Reconstructor::ScreenWindow(const cv::Mat& frame,
                                                    const cv::Mat& reference) const {
  return Screen(frame, reference, nullptr);
}

std::optional<cv::Rect> Reconstructor::Screen(const cv::Mat& frame, const cv::Mat& reference,
                                              cv::Vec3d* gain) const {
  // Half size, 2x2 means: a quarter of the pixels with half the noise. Unsmoothed and against
  // half the detection threshold, so that whatever the full path would find is seen here.
  cv::Mat small_frame, small_reference;
  cv::resize(frame, small_frame, coarse_visible_.size(), 0, 0, cv::INTER_AREA);
  if (reference.data == reference_.data) {
    small_reference = coarse_reference_;
  } else {
    cv::resize(reference, small_reference, coarse_visible_.size(), 0, 0, cv::INTER_AREA);
  }
  // The full path smooths f (smooth_sigma_px) and then |f| (blur_sigma_px) before its threshold;
  // at half size half those sigmas do the same to the noise.
  DifferenceOptions coarse = options_.difference;
  coarse.smooth_sigma_px = 0.5 * options_.difference.smooth_sigma_px;
  coarse.gain_stride = std::max(1, coarse.gain_stride / 2);
  // Its gain is the frame's: the same pixels' ratios, 2x2 means of them (a median of as many
  // samples as the full path takes), so the full path need not estimate it again.
  const cv::Mat diff =
      NormalizedDifference(small_frame, small_reference, coarse_visible_, coarse, gain);
  cv::Mat magnitude(diff.size(), CV_32F);
  for (int y = 0; y < diff.rows; ++y) {
    const cv::Vec3f* in = diff.ptr<cv::Vec3f>(y);
    float* out = magnitude.ptr<float>(y);
    for (int x = 0; x < diff.cols; ++x) out[x] = std::sqrt(in[x].dot(in[x]));
  }
  const double sigma = 0.5 * options_.detection.blur_sigma_px;
  if (sigma > 0.0) cv::GaussianBlur(magnitude, magnitude, cv::Size(), sigma);
  const cv::Mat changed =
      magnitude > static_cast<float>(kScreenFraction * options_.detection.threshold);
  const cv::Rect box = cv::boundingRect(changed);
  if (box.empty()) return std::nullopt;
  // The window the full path must see: the change, grown by more than DetectContactRegions
  // grows a blob into its roi (grow_fraction, grow_px) plus the context features' reach (3 sigma
  // of the largest scale) beyond that roi, so that inside it both paths compute the same.
  const cv::Rect change(2 * box.x, 2 * box.y, 2 * box.width, 2 * box.height);
  double reach = 0.0;
  for (double s : options_.difference.context_sigmas_px) reach = std::max(reach, 3.0 * s);
  const int margin = static_cast<int>(
      std::ceil((options_.detection.grow_fraction + 0.05) * std::max(change.width, change.height) +
                options_.detection.grow_px + reach + 4.0 * options_.detection.blur_sigma_px + 4.0));
  const cv::Rect window(change.x - margin, change.y - margin, change.width + 2 * margin,
                        change.height + 2 * margin);
  return window & cv::Rect(0, 0, frame.cols, frame.rows);
}

bool Reconstructor::MayTouch(const cv::Mat& frame, const cv::Mat& reference) const {
  return ScreenWindow(frame, reference).has_value();
}

DetectedContacts Reconstructor::Detect(const cv::Mat& frame, const cv::Mat& reference) const {
  DetectedContacts out;
  const cv::Rect image(0, 0, frame.cols, frame.rows);
  out.window = image;
  if (options_.screen) {
    const auto window = Screen(frame, reference, &out.gain);
    if (!window) {
      out.window = cv::Rect();
      return out;
    }
    out.window = *window;
  }
  if (out.window == image) {
    out.difference = Difference(frame, reference, &out.gain);
  } else {
    // Only the screen narrows the window: its gain (the whole image's) and the difference here.
    out.difference = cv::Mat(frame.size(), CV_32FC3, cv::Scalar::all(0));
    const cv::Rect& w = out.window;
    NormalizedDifference(frame(w), reference(w), visible_(w), options_.difference, nullptr,
                         &out.gain)
        .copyTo(out.difference(w));
  }
  out.regions = DetectContactRegions(out.difference(out.window), options_.detection);
  for (ContactRegion& r : out.regions) {
    r.blob += out.window.tl();
    r.roi += out.window.tl();
  }
  return out;
}

cv::Mat Reconstructor::Difference(const cv::Mat& frame, const cv::Mat& reference,
                                  cv::Vec3d* gain) const {
  return NormalizedDifference(frame, reference, visible_, options_.difference, gain);
}

namespace {

// Grid lines of a stride-s grid over [0, n): 0, s, 2s, ... and n - 1.
std::vector<int> GridLines(int n, int s) {
  std::vector<int> lines;
  for (int i = 0; i < n; i += s) lines.push_back(i);
  if (lines.back() != n - 1) lines.push_back(n - 1);
  return lines;
}

}  // namespace

void Reconstructor::EvaluateSlopes(const cv::Mat& diff, const cv::Mat& context, const cv::Rect& win,
                                   const cv::Rect& roi, const std::vector<cv::Point>& pixels,
                                   cv::Mat* slopes) const {
  if (pixels.empty()) return;
  Eigen::MatrixXf x(FeatureCount(options_.difference), static_cast<Eigen::Index>(pixels.size()));
  for (std::size_t i = 0; i < pixels.size(); ++i) {
    PixelFeatures(diff, context, win.tl(), pixels[i].x, pixels[i].y,
                  x.col(static_cast<Eigen::Index>(i)).data());
  }
  const Eigen::MatrixXf y = mlp_.Forward(x);
  for (std::size_t i = 0; i < pixels.size(); ++i) {
    const auto c = static_cast<Eigen::Index>(i);
    slopes->at<cv::Vec2f>(pixels[i].y - roi.y, pixels[i].x - roi.x) = cv::Vec2f(y(0, c), y(1, c));
  }
}

cv::Mat Reconstructor::PredictSlopes(const cv::Mat& diff, const cv::Rect& roi) const {
  return PredictSlopes(diff, roi, roi);
}

cv::Mat Reconstructor::PredictSlopes(const cv::Mat& diff, const cv::Rect& roi,
                                     const cv::Rect& window) const {
  cv::Mat slopes(roi.size(), CV_32FC2, cv::Scalar::all(0));
  const cv::Rect win = window & roi;
  if (win.empty()) return slopes;
  // Context features only where the MLP runs (each smooths its own margin around the window).
  const cv::Mat context =
      ContextFeatures(diff, visible_, win, options_.difference.context_sigmas_px);
  // A window one pixel wide or tall has no grid cells to interpolate in.
  if (options_.mlp_stride == 1 || win.width < 2 || win.height < 2) {
    std::vector<cv::Point> pixels;
    pixels.reserve(win.area());
    for (int v = win.y; v < win.y + win.height; ++v) {
      for (int u = win.x; u < win.x + win.width; ++u) {
        if (map_->visible(u, v)) pixels.emplace_back(u, v);
      }
    }
    EvaluateSlopes(diff, context, win, roi, pixels, &slopes);
    return slopes;
  }
  InterpolateSlopes(diff, context, roi, win, &slopes);
  return slopes;
}

// Slopes are smooth over a few pixels: the MLP on a stride-s grid over `win` (its visible
// nodes), the pixels between by bilinear weights over the nodes evaluated. The MLP again for
// every pixel of a cell whose nodes disagree by more than ReconstructionOptions::
// mlp_refine_slope (the imprint's rim, where a slope jumps), and where too few of a pixel's
// nodes are visible (at a fin's or the view's edge). Grid positions below are relative to win;
// slopes is roi-sized.
void Reconstructor::InterpolateSlopes(const cv::Mat& diff, const cv::Mat& context,
                                      const cv::Rect& roi, const cv::Rect& win,
                                      cv::Mat* slopes_out) const {
  cv::Mat& slopes = *slopes_out;
  const int ox = win.x - roi.x, oy = win.y - roi.y;
  const std::vector<int> xs = GridLines(win.width, options_.mlp_stride);
  const std::vector<int> ys = GridLines(win.height, options_.mlp_stride);
  auto visible = [&](int x, int y) { return map_->visible(win.x + x, win.y + y); };
  auto at = [&](int x, int y) -> cv::Vec2f& { return slopes.at<cv::Vec2f>(oy + y, ox + x); };
  std::vector<cv::Point> nodes;
  for (int y : ys) {
    for (int x : xs) {
      if (visible(x, y)) nodes.emplace_back(win.x + x, win.y + y);
    }
  }
  EvaluateSlopes(diff, context, win, roi, nodes, &slopes);
  // Pixels to evaluate directly: every pixel of a cell whose visible nodes disagree.
  cv::Mat direct_mask(win.size(), CV_8U, cv::Scalar::all(0));
  const float refine = static_cast<float>(options_.mlp_refine_slope);
  for (std::size_t j = 0; j + 1 < ys.size(); ++j) {
    for (std::size_t i = 0; i + 1 < xs.size(); ++i) {
      float lo[2] = {1e30f, 1e30f}, hi[2] = {-1e30f, -1e30f};
      for (const int y : {ys[j], ys[j + 1]}) {
        for (const int x : {xs[i], xs[i + 1]}) {
          if (!visible(x, y)) continue;
          for (int c = 0; c < 2; ++c)
            lo[c] = std::min(lo[c], at(x, y)[c]), hi[c] = std::max(hi[c], at(x, y)[c]);
        }
      }
      if (hi[0] - lo[0] > refine || hi[1] - lo[1] > refine) {
        direct_mask(cv::Rect(xs[i], ys[j], xs[i + 1] - xs[i] + 1, ys[j + 1] - ys[j] + 1)) = 255;
      }
    }
  }
  std::vector<cv::Point> direct;
  std::size_t j = 0;
  for (int y = 0; y < win.height; ++y) {
    while (j + 2 < ys.size() && y >= ys[j + 1]) ++j;
    const float fy = static_cast<float>(y - ys[j]) / static_cast<float>(ys[j + 1] - ys[j]);
    std::size_t i = 0;
    for (int x = 0; x < win.width; ++x) {
      while (i + 2 < xs.size() && x >= xs[i + 1]) ++i;
      const bool node = (x == xs[i] || x == xs[i + 1]) && (y == ys[j] || y == ys[j + 1]);
      if (node || !visible(x, y)) continue;
      if (direct_mask.at<std::uint8_t>(y, x)) {
        direct.emplace_back(win.x + x, win.y + y);
        continue;
      }
      const float fx = static_cast<float>(x - xs[i]) / static_cast<float>(xs[i + 1] - xs[i]);
      const int cx[2] = {xs[i], xs[i + 1]}, cy[2] = {ys[j], ys[j + 1]};
      const float wx[2] = {1.0f - fx, fx}, wy[2] = {1.0f - fy, fy};
      cv::Vec2f sum(0.0f, 0.0f);
      float weight = 0.0f;
      for (int b = 0; b < 2; ++b) {
        for (int a = 0; a < 2; ++a) {
          if (!visible(cx[a], cy[b])) continue;
          sum += wx[a] * wy[b] * at(cx[a], cy[b]);
          weight += wx[a] * wy[b];
        }
      }
      if (weight > 0.75f) {
        at(x, y) = sum / weight;
      } else {
        direct.emplace_back(win.x + x, win.y + y);
      }
    }
  }
  EvaluateSlopes(diff, context, win, roi, direct, &slopes);
}

cv::Rect HeightFieldWindow(const ContactRegion& region, const ContactDetectionOptions& detection,
                           const HeightFieldOptions& height_field) {
  const double f = height_field.window_grow_fraction;
  if (f >= detection.grow_fraction) return region.roi;
  const cv::Rect& b = region.blob;
  const int gx = detection.grow_px + static_cast<int>(std::ceil(f * b.width));
  const int gy = detection.grow_px + static_cast<int>(std::ceil(f * b.height));
  const cv::Rect window =
      cv::Rect(b.x - gx, b.y - gy, b.width + 2 * gx, b.height + 2 * gy) & region.roi;
  // The height field needs 3 x 3 at least: else the whole region.
  return window.width >= 3 && window.height >= 3 ? window : region.roi;
}

double ImprintViewAngleDeg(const SurfaceMap& map, const cv::Rect& roi, const cv::Mat& slopes) {
  double sum = 0.0, sum_all = 0.0;
  int n = 0, n_all = 0;
  for (int y = 0; y < roi.height; ++y) {
    for (int x = 0; x < roi.width; ++x) {
      const int u = roi.x + x, v = roi.y + y;
      if (!map.visible(u, v)) continue;
      const cv::Vec2f g = slopes.at<cv::Vec2f>(y, x);
      const double a = map.view_angle(u, v);
      sum_all += a, ++n_all;
      if (g[0] * g[0] + g[1] * g[1] > 0.09f) sum += a, ++n;
    }
  }
  const double mean = n > 0 ? sum / n : n_all > 0 ? sum_all / n_all : 0.0;
  return mean * 180.0 / std::numbers::pi;
}

// rho over roi from an integration over `window` (inside roi, in image pixels): `integrate`
// gets the window and the same rectangle relative to roi, and returns rho over the window; beyond
// it the undeformed gel (NaN where invisible).
template <typename Integrate>
cv::Mat Reconstructor::IntegrateInWindow(const cv::Rect& roi, const cv::Rect& window,
                                         Integrate integrate) const {
  if (window == roi) return integrate(roi, cv::Rect(cv::Point(0, 0), roi.size()));
  cv::Mat rho(roi.size(), CV_64F, cv::Scalar::all(kNaN));
  for (int y = 0; y < roi.height; ++y) {
    for (int x = 0; x < roi.width; ++x) {
      if (map_->visible(roi.x + x, roi.y + y))
        rho.at<double>(y, x) = map_->rho0(roi.x + x, roi.y + y);
    }
  }
  const cv::Rect inside(window.x - roi.x, window.y - roi.y, window.width, window.height);
  integrate(window, inside).copyTo(rho(inside));
  return rho;
}

RegionReconstruction Reconstructor::IntegrateSlopes(const cv::Mat& slopes,
                                                    const ContactRegion& region,
                                                    const IntegrationOptions& integration) const {
  const cv::Rect& roi = region.roi;
  if (slopes.type() != CV_32FC2 || slopes.size() != roi.size()) {
    throw std::invalid_argument("IntegrateSlopes: slopes must be CV_32FC2 of the roi's size");
  }
  RegionReconstruction out;
  out.region = region;
  out.slopes = slopes;
  out.normals = cv::Mat(roi.size(), CV_64FC3, cv::Scalar::all(kNaN));
  for (int y = 0; y < roi.height; ++y) {
    for (int x = 0; x < roi.width; ++x) {
      const int u = roi.x + x, v = roi.y + y;
      if (!map_->visible(u, v)) continue;
      const cv::Vec2f g = slopes.at<cv::Vec2f>(y, x);
      const Eigen::Vector3d n = map_->NormalFromSlopes(u, v, g[0], g[1]);
      out.normals.at<cv::Vec3d>(y, x) = cv::Vec3d(n.x(), n.y(), n.z());
    }
  }
  const auto t0 = std::chrono::steady_clock::now();
  const LogDepthGradients grads =
      ComputeLogDepthGradients(*map_, roi, out.normals, options_.gradients);
  bool height_field = integration.method == IntegrationMethod::kHeightField;
  const double imprint_view_deg = height_field ? ImprintViewAngleDeg(*map_, roi, slopes) : 0.0;
  if (height_field) {
    height_field = imprint_view_deg >= integration.height_field.min_view_angle_deg;
  }
  if (height_field) {
    // Start from plain Poisson's indentation (about 1 ms): right where the view is steep, and
    // of the right size elsewhere, so the passes only have to correct the shifts.
    IntegrationOptions poisson = integration;
    poisson.method = IntegrationMethod::kPoisson;
    const cv::Mat h0 = IndentationFromRho(*map_, roi, IntegrateLogDepth(*map_, grads, poisson).rho);
    HeightFieldOptions passes = integration.height_field;
    passes.iterations = passes.Passes(imprint_view_deg);
    out.rho = IntegrateInWindow(
        roi, HeightFieldWindow(region, options_.detection, integration.height_field),
        [&](const cv::Rect& window, const cv::Rect& inside) {
          return IntegrateHeightField(*map_, camera_, window, out.normals(inside), passes,
                                      h0(inside))
              .rho;
        });
  } else {
    IntegrationOptions along_rays = integration;
    if (along_rays.method == IntegrationMethod::kHeightField) {
      along_rays.method = IntegrationMethod::kDiscontinuityAware;
    }
    out.rho = IntegrateLogDepth(*map_, grads, along_rays).rho;
  }
  out.integration_seconds = Seconds(t0);
  out.indentation = NormalIndentation(*map_, camera_, roi, out.rho);
  for (int y = 0; y < roi.height; ++y) {
    for (int x = 0; x < roi.width; ++x) {
      const double depth = out.indentation.at<double>(y, x);
      if (std::isfinite(depth)) out.peak_indentation_mm = std::max(out.peak_indentation_mm, depth);
    }
  }
  return out;
}

cv::Rect Reconstructor::SlopesWindow(const ContactRegion& region,
                                     const IntegrationOptions& integration) const {
  // The height field uses no slope beyond its window (it takes the gel there as undeformed).
  return integration.method == IntegrationMethod::kHeightField
             ? HeightFieldWindow(region, options_.detection, integration.height_field)
             : region.roi;
}

RegionReconstruction Reconstructor::ReconstructRegion(const cv::Mat& diff,
                                                      const ContactRegion& region,
                                                      const IntegrationOptions& integration) const {
  const auto t0 = std::chrono::steady_clock::now();
  cv::Mat slopes = PredictSlopes(diff, region.roi, SlopesWindow(region, integration));
  const double mlp_seconds = Seconds(t0);
  RegionReconstruction out = IntegrateSlopes(slopes, region, integration);
  out.mlp_seconds = mlp_seconds;
  return out;
}

namespace {

// LED drift moves a channel's gain by a few percent over hours. A frame at half or twice the
// reference's brightness is not a tactile frame against it (a black or saturated frame, the LEDs
// off, the exposure changed), and dividing by its gain would make it look like no contact.
std::string GainProblem(const cv::Vec3d& gain) {
  constexpr double kMinGain = 0.5;
  constexpr double kMaxGain = 2.0;
  static const char* const kChannel[] = {"blue", "green", "red"};
  for (int c = 0; c < 3; ++c) {
    if (gain[c] >= kMinGain && gain[c] <= kMaxGain) continue;
    const std::string what = "the frame's " + std::string(kChannel[c]) + " brightness ";
    return (std::isfinite(gain[c]) ? what + "is " + std::to_string(std::lround(100.0 * gain[c])) +
                                         " % of the reference's (outside 50-200 %)"
                                   : what + "cannot be compared with the reference's") +
           ": a black or saturated frame, the LEDs off or the exposure changed (recapture the "
           "reference)";
  }
  return "";
}

}  // namespace

FrameReconstruction Reconstructor::Reconstruct(const cv::Mat& frame) const {
  return Reconstruct(frame, reference_);
}

FrameReconstruction Reconstructor::Reconstruct(const cv::Mat& frame,
                                               const cv::Mat& reference) const {
  const auto t0 = std::chrono::steady_clock::now();
  FrameReconstruction out;
  const DetectedContacts detected = Detect(frame, reference);
  out.gain = detected.gain;
  out.problem = GainProblem(out.gain);
  if (!out.problem.empty()) {
    out.seconds = Seconds(t0);
    return out;
  }
  // Contacts change a small part of the image (a dense press, about 3 %): a frame changed over
  // much of it is no tactile frame against this reference, and its "regions" would be
  // reconstructed into a phantom the size of the finger.
  constexpr double kMaxChangedFraction = 0.3;
  int changed = 0;
  for (const ContactRegion& region : detected.regions) changed += region.area_px;
  out.changed_fraction = visible_pixels_ > 0 ? static_cast<double>(changed) / visible_pixels_ : 0;
  if (out.changed_fraction > kMaxChangedFraction) {
    out.problem = "the frame differs from the reference over " + std::to_string(changed) +
                  " pixels, more than " +
                  std::to_string(static_cast<int>(100.0 * kMaxChangedFraction)) + " % of the " +
                  std::to_string(visible_pixels_) +
                  " the camera sees on the gel and more than any contact: a saturated, black or "
                  "corrupt frame, changed lighting or a moved camera (recapture the reference)";
    out.seconds = Seconds(t0);
    return out;
  }
  for (const ContactRegion& region : detected.regions) {
    if (region.roi.width < 3 || region.roi.height < 3) continue;
    out.regions.push_back(ReconstructRegion(detected.difference, region, options_.integration));
  }
  out.seconds = Seconds(t0);
  return out;
}

std::vector<Eigen::Vector3f> Reconstructor::PointCloud(const FrameReconstruction& reconstruction,
                                                       double min_indentation_mm) const {
  const Rigid3d sensor_from_cam = map_->cam_from_sensor().Inverse();
  std::vector<Eigen::Vector3f> points;
  for (const RegionReconstruction& r : reconstruction.regions) {
    const cv::Rect& roi = r.region.roi;
    for (int y = 0; y < roi.height; ++y) {
      for (int x = 0; x < roi.width; ++x) {
        const double depth = r.indentation.at<double>(y, x);
        if (!(depth > min_indentation_mm)) continue;
        const Eigen::Vector3d x_cam = r.rho.at<double>(y, x) * map_->ray(roi.x + x, roi.y + y);
        points.push_back((sensor_from_cam * x_cam).cast<float>());
      }
    }
  }
  return points;
}

}  // namespace gs360
