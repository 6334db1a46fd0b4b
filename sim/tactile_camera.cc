#include "sim/tactile_camera.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <sstream>
#include <stdexcept>
#include <string>
#include <thread>

#include "base/field_error.h"
#include "sim/camera_random.h"
#include "sim/ground_truth.h"

namespace gs360 {
namespace {

using Clock = std::chrono::steady_clock;

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
// Per-frame noise offsets into the Gaussian bank: the bank holds 3 * pixels + kBankOffsets samples.
constexpr std::uint64_t kBankOffsets = 1u << 20;
constexpr std::array<double, 3> kDriftWeights = {0.6, 0.3, 0.1};
// Displacement above which a visible point counts as deformed (mm).
constexpr double kDeformedThreshold = 1e-4;

[[noreturn]] void ThrowField(const std::string& field, double value, const std::string& why) {
  ThrowFieldError(field, value, why);
}

double SecondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

inline std::uint8_t Quantize(float v) {
  v = std::min(255.0f, std::max(0.0f, v));
  return static_cast<std::uint8_t>(static_cast<int>(v + 0.5f));
}

// Scale of the int16 Gaussian bank (samples are z * kBankScale).
constexpr float kBankScale = 4096.0f;

// Whole-image pass: signal * per-channel drift gain + sigma * z, quantised (B, G, R order in all
// arrays). Clamping in integers, so that the compiler vectorises the loop (float min/max are not
// if-converted under the default -ftrapping-math).
void WriteImage(int npix, const float* __restrict__ signal, const float* __restrict__ sigma,
                const float gain[3], const std::int16_t* __restrict__ z,
                std::uint8_t* __restrict__ bgr) {
  const float gb = gain[2], gg = gain[1], gr = gain[0];
  const float zs = 1.0f / kBankScale;
  auto clamp8 = [](int v) { return static_cast<std::uint8_t>(std::max(0, std::min(255, v))); };
  if (z != nullptr) {
    for (int i = 0; i < npix; ++i) {
      const int j = 3 * i;
      const int b = static_cast<int>(signal[j] * gb + sigma[j] * (z[j] * zs) + 0.5f);
      const int g = static_cast<int>(signal[j + 1] * gg + sigma[j + 1] * (z[j + 1] * zs) + 0.5f);
      const int r = static_cast<int>(signal[j + 2] * gr + sigma[j + 2] * (z[j + 2] * zs) + 0.5f);
      bgr[j] = clamp8(b);
      bgr[j + 1] = clamp8(g);
      bgr[j + 2] = clamp8(r);
    }
  } else {
    for (int i = 0; i < npix; ++i) {
      const int j = 3 * i;
      bgr[j] = clamp8(static_cast<int>(signal[j] * gb + 0.5f));
      bgr[j + 1] = clamp8(static_cast<int>(signal[j + 1] * gg + 0.5f));
      bgr[j + 2] = clamp8(static_cast<int>(signal[j + 2] * gr + 0.5f));
    }
  }
}

// Watertight ray/triangle test (Woop, Benthin, Wald 2013), double precision: the per-ray part.
struct RaySetup {
  int kx = 0, ky = 1, kz = 2;
  double sx = 0.0, sy = 0.0, sz = 1.0;
};

RaySetup MakeRaySetup(const Eigen::Vector3d& d) {
  RaySetup s;
  d.cwiseAbs().maxCoeff(&s.kz);
  s.kx = (s.kz + 1) % 3;
  s.ky = (s.kx + 1) % 3;
  if (d[s.kz] < 0.0) std::swap(s.kx, s.ky);
  s.sx = d[s.kx] / d[s.kz];
  s.sy = d[s.ky] / d[s.kz];
  s.sz = 1.0 / d[s.kz];
  return s;
}

// Hit of the ray (origin o, the direction of `s`) with triangle (v0, v1, v2) at t >= 0: t and the
// barycentrics of v1 and v2. A ray through a shared edge hits at least one of the two triangles.
inline bool HitTriangle(const RaySetup& s, const Eigen::Vector3d& o, const Eigen::Vector3d& v0,
                        const Eigen::Vector3d& v1, const Eigen::Vector3d& v2, double* t, double* b1,
                        double* b2) {
  const Eigen::Vector3d a = v0 - o, b = v1 - o, c = v2 - o;
  const double ax = a[s.kx] - s.sx * a[s.kz], ay = a[s.ky] - s.sy * a[s.kz];
  const double bx = b[s.kx] - s.sx * b[s.kz], by = b[s.ky] - s.sy * b[s.kz];
  const double cx = c[s.kx] - s.sx * c[s.kz], cy = c[s.ky] - s.sy * c[s.kz];
  const double u = cx * by - cy * bx;
  const double v = ax * cy - ay * cx;
  const double w = bx * ay - by * ax;
  if ((u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0)) return false;
  const double det = u + v + w;
  if (det == 0.0) return false;
  const double th = (u * a[s.kz] + v * b[s.kz] + w * c[s.kz]) * s.sz / det;
  if (!(th >= 0.0)) return false;
  *t = th;
  *b1 = v / det;
  *b2 = w / det;
  return true;
}

// One re-rendered pixel: R, G, B signal (DN, before drift) to B, G, R bytes, with exact
// signal-dependent noise.
inline void WritePixel(const float rgb[3], const float gain[3], const std::int16_t* z, float read2,
                       float shot_gain, std::uint8_t* bgr) {
  for (int c = 0; c < 3; ++c) {
    float v = rgb[c] * gain[c];
    if (z != nullptr) {
      v += std::sqrt(read2 + shot_gain * std::max(v, 0.0f)) * (z[2 - c] / kBankScale);
    }
    bgr[2 - c] = Quantize(v);
  }
}

}  // namespace

// Static, per-camera data: the true rays, what they hit, and the no-contact signal.
struct TactileCamera::Background {
  FisheyeCamera true_camera;
  Rigid3d cam_from_sensor;
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();  // true camera centre (sensor frame)
  std::vector<Eigen::Vector3d> dir;                  // unit ray (sensor frame) per pixel
  std::vector<std::uint8_t> kind;                    // PixelKind
  std::vector<double> t_gel;                         // distance to the gel (inf: none)
  std::vector<int> tri_gel;                          // gel triangle hit (-1: none)
  std::vector<double> t_fin;                         // distance to a fin (inf: none)
  std::vector<Eigen::Vector3f> normal0;              // gel outward normal at the hit
  std::vector<float> vignette;                       // relative illumination V(theta)
  std::vector<float> rgb;                            // R, G, B per pixel, DN before drift
  std::vector<float> signal;                         // B, G, R per pixel, DN before drift
  std::vector<float> sigma;                          // B, G, R noise sigma (DN) of `signal`
  std::vector<std::int16_t> bank;                    // standard normal samples * kBankScale
  double exposure = 1.0;                             // DN per unit of Lighting::Shade radiance
};

// The last ball position's re-rendered pixels before drift and noise, and its truth.
struct TactileCamera::PatchCache {
  Eigen::Vector3d ball = Eigen::Vector3d::Zero();  // sensor frame, compared exactly
  bool rigid = false;
  FrameTruth truth;           // its patch fields (ROI, maps, depths, contact point) are reused
  std::vector<int> pixels;    // image pixel index of each re-shaded pixel
  std::vector<float> signal;  // their R, G, B (DN before drift), 3 per pixel
  int roi_pixels = 0;

  bool Matches(const Eigen::Vector3d& b, bool r) const { return r == rigid && b == ball; }
  // The patch's truth fields into `to` (the frame's own fields stay).
  void CopyTruth(FrameTruth* to) const {
    to->max_depth_mm = truth.max_depth_mm;
    to->max_indentation_mm = truth.max_indentation_mm;
    to->contact_point_sensor = truth.contact_point_sensor;
    to->contact_normal_sensor = truth.contact_normal_sensor;
    to->patch_triangles = truth.patch_triangles;
    to->roi = truth.roi;  // the maps are shared, never written after the render that made them
    to->contact_mask = truth.contact_mask;
    to->deformed_mask = truth.deformed_mask;
    to->rho = truth.rho;
    to->indentation = truth.indentation;
    to->points = truth.points;
    to->normals = truth.normals;
  }
};

void SensorModelOptions::Check() const {
  if (!std::isfinite(vignetting_v2))
    ThrowField("SensorModelOptions.vignetting_v2", vignetting_v2, "must be finite");
  if (!std::isfinite(vignetting_v4))
    ThrowField("SensorModelOptions.vignetting_v4", vignetting_v4, "must be finite");
  if (1.0 + std::min(0.0, vignetting_v2) + std::min(0.0, vignetting_v4) <= 0.0) {
    ThrowField("SensorModelOptions.vignetting_v2 + vignetting_v4", vignetting_v2 + vignetting_v4,
               "would make the relative illumination <= 0 inside the field");
  }
  if (!std::isfinite(shot_gain) || shot_gain < 0.0) {
    ThrowField("SensorModelOptions.shot_gain", shot_gain, "must be finite and >= 0");
  }
  if (!std::isfinite(read_noise) || read_noise < 0.0) {
    ThrowField("SensorModelOptions.read_noise", read_noise, "must be finite and >= 0");
  }
  if (!std::isfinite(drift_amplitude) || drift_amplitude < 0.0 || drift_amplitude > 0.5) {
    ThrowField("SensorModelOptions.drift_amplitude", drift_amplitude, "must be in [0, 0.5]");
  }
  for (int k = 0; k < 3; ++k) {
    if (!std::isfinite(drift_periods_h[k]) || !(drift_periods_h[k] > 0.0)) {
      ThrowField("SensorModelOptions.drift_periods_h[" + std::to_string(k) + "]",
                 drift_periods_h[k], "must be finite and > 0");
    }
    if (!std::isfinite(ambient_dn[k]) || ambient_dn[k] < 0.0 || ambient_dn[k] > 255.0) {
      ThrowField("SensorModelOptions.ambient_dn[" + std::to_string(k) + "]", ambient_dn[k],
                 "must be in [0, 255]");
    }
  }
  if (!(exposure_target > 0.0 && exposure_target <= 255.0)) {
    ThrowField("SensorModelOptions.exposure_target", exposure_target, "must be in (0, 255]");
  }
  if (!(fin_grey >= 0.0 && fin_grey <= 255.0)) {
    ThrowField("SensorModelOptions.fin_grey", fin_grey, "must be in [0, 255]");
  }
  if (!(fin_pattern >= 0.0 && fin_pattern <= 0.5)) {
    ThrowField("SensorModelOptions.fin_pattern", fin_pattern, "must be in [0, 0.5]");
  }
  if (!(housing_dn >= 0.0 && housing_dn <= 255.0)) {
    ThrowField("SensorModelOptions.housing_dn", housing_dn, "must be in [0, 255]");
  }
}

void TactileCameraOptions::Check() const {
  lighting.Check();
  gel.Check();
  sensor.Check();
  if (threads < 1 || threads > 64)
    ThrowField("TactileCameraOptions.threads", threads, "must be in [1, 64]");
}

TactileCamera::TactileCamera(std::shared_ptr<const SimRig> rig, const TactileCameraOptions& options)
    : rig_(std::move(rig)), options_(options) {
  if (!rig_) throw std::invalid_argument("TactileCamera: rig is null");
  options_.Check();
  lighting_ = std::make_unique<Lighting>(options_.lighting, rig_->profile(), rig_->fin_options());
  patch_builder_ = std::make_unique<GelPatchBuilder>(rig_->gel_mesh(), options_.gel);
  GelDeformationOptions rigid = GelDeformationOptions::Rigid();
  rigid.max_edge = options_.gel.max_edge;
  rigid.bulge_max_edge = options_.gel.bulge_max_edge;
  rigid_patch_builder_ = std::make_unique<GelPatchBuilder>(rig_->gel_mesh(), rigid);
  last_truth_ = std::make_unique<FrameTruth>();
  run_start_ = Clock::now();
  SimRandom rng(MixSeed(options_.sensor.seed, 0x6472696674ull));  // "drift"
  for (auto& channel : drift_phase_) {
    for (double& phase : channel) phase = rng.Uniform(0.0, 2.0 * std::numbers::pi);
  }
  const Clock::time_point start = Clock::now();
  BuildBackground();
  stats_.background_seconds = SecondsSince(start);
}

TactileCamera::~TactileCamera() = default;

void TactileCamera::SetMachinePositionSource(MachinePositionFn source) {
  position_source_ = std::move(source);
}

void TactileCamera::SetRunStart(Clock::time_point start) {
  run_start_ = start;
}

Eigen::Array3d TactileCamera::DriftGain(double run_time_s) const {
  const double hours = run_time_s / 3600.0;
  Eigen::Array3d gain;
  for (int c = 0; c < 3; ++c) {
    double s = 0.0;
    for (int k = 0; k < 3; ++k) {
      s += kDriftWeights[k] *
           std::sin(2.0 * std::numbers::pi * hours / options_.sensor.drift_periods_h[k] +
                    drift_phase_[c][k]);
    }
    gain[c] = 1.0 + options_.sensor.drift_amplitude * s;
  }
  return gain;
}

std::uint64_t TactileCamera::NoiseOffset(std::uint64_t frame_index) const {
  return MixSeed(options_.sensor.seed ^ 0x6e6f697365ull, frame_index) % kBankOffsets;  // "noise"
}

void TactileCamera::BuildBackground() {
  background_ = std::make_unique<Background>();
  Background& bg = *background_;
  const FisheyeIntrinsics& intrinsics = SimGroundTruth::TrueIntrinsics(*rig_);
  bg.true_camera = FisheyeCamera(intrinsics);
  bg.cam_from_sensor = SimGroundTruth::TrueCamFromSensor(*rig_);
  const Rigid3d sensor_from_cam = bg.cam_from_sensor.Inverse();
  bg.origin = sensor_from_cam.translation;
  width_ = intrinsics.width;
  height_ = intrinsics.height;
  const int npix = width_ * height_;
  bg.dir.assign(npix, Eigen::Vector3d::Zero());
  bg.kind.assign(npix, kOutside);
  bg.t_gel.assign(npix, kInf);
  bg.tri_gel.assign(npix, -1);
  bg.t_fin.assign(npix, kInf);
  bg.normal0.assign(npix, Eigen::Vector3f::Zero());
  bg.vignette.assign(npix, 0.0f);
  bg.rgb.assign(3 * static_cast<std::size_t>(npix), 0.0f);
  std::vector<Eigen::Array3f> radiance(npix, Eigen::Array3f::Zero());

  const SensorModelOptions& sensor = options_.sensor;
  const double max_theta = intrinsics.max_theta;
  auto work = [&](int first_row, int stride) {
    for (int v = first_row; v < height_; v += stride) {
      for (int u = 0; u < width_; ++u) {
        const int i = v * width_ + u;
        const auto ray_cam = bg.true_camera.PixelToRay(Eigen::Vector2d(u, v));
        if (!ray_cam) continue;
        const double theta = std::atan2(ray_cam->head<2>().norm(), ray_cam->z());
        const double s2 = (theta / max_theta) * (theta / max_theta);
        bg.vignette[i] = static_cast<float>(
            std::max(0.02, 1.0 + sensor.vignetting_v2 * s2 + sensor.vignetting_v4 * s2 * s2));
        Ray ray;
        ray.origin = bg.origin;
        ray.direction = sensor_from_cam.RotateDirection(*ray_cam).normalized();
        bg.dir[i] = ray.direction;
        const auto gel = rig_->gel_bvh().Intersect(ray);
        const auto fin = rig_->fin_bvh().Intersect(ray);
        if (gel) {
          bg.t_gel[i] = gel->t;
          bg.tri_gel[i] = gel->triangle;
          bg.normal0[i] = gel->normal.cast<float>();
        }
        if (fin) bg.t_fin[i] = fin->t;
        if (fin && (!gel || fin->t < gel->t)) {
          bg.kind[i] = kFin;
        } else if (gel) {
          bg.kind[i] = kGel;
          radiance[i] = lighting_->Shade(gel->point, gel->normal, -ray.direction).cast<float>();
        } else {
          bg.kind[i] = kNothing;
        }
      }
    }
  };
  const int threads = std::min(options_.threads, height_);
  std::vector<std::thread> pool;
  for (int k = 1; k < threads; ++k) pool.emplace_back(work, k, threads);
  work(0, threads);
  for (auto& t : pool) t.join();

  // Locked exposure from the no-contact image.
  std::vector<float> brightest;
  for (int i = 0; i < npix; ++i) {
    if (bg.kind[i] == kGel) brightest.push_back(radiance[i].maxCoeff() * bg.vignette[i]);
  }
  if (brightest.empty()) {
    throw std::runtime_error("TactileCamera: the true camera sees no gel (rig " + rig_->Describe() +
                             ")");
  }
  const std::size_t q =
      std::min(brightest.size() - 1,
               static_cast<std::size_t>(0.995 * static_cast<double>(brightest.size())));
  std::nth_element(brightest.begin(), brightest.begin() + q, brightest.end());
  const double max_ambient = *std::max_element(sensor.ambient_dn.begin(), sensor.ambient_dn.end());
  bg.exposure =
      std::max(1.0, sensor.exposure_target - max_ambient) / std::max(1e-30f, brightest[q]);

  for (int i = 0; i < npix; ++i) {
    float* s = &bg.rgb[3 * static_cast<std::size_t>(i)];
    const float vig = bg.vignette[i];
    switch (bg.kind[i]) {
      case kGel:
        for (int c = 0; c < 3; ++c) {
          s[c] = static_cast<float>((bg.exposure * radiance[i][c] + sensor.ambient_dn[c]) * vig);
        }
        break;
      case kFin: {
        SimRandom pixel_rng(MixSeed(sensor.seed ^ 0x66696eull, static_cast<std::uint64_t>(i)));
        const double grey = sensor.fin_grey * (1.0 + sensor.fin_pattern * pixel_rng.Normal()) * vig;
        for (int c = 0; c < 3; ++c) s[c] = static_cast<float>(grey);
        break;
      }
      case kNothing:
        for (int c = 0; c < 3; ++c) s[c] = static_cast<float>(sensor.housing_dn * vig);
        break;
      default:
        break;
    }
  }

  // Output-ordered signal and its noise sigma (shot noise at the drift-free signal: the drift
  // changes sigma by < 1%).
  bg.signal.resize(bg.rgb.size());
  bg.sigma.resize(bg.rgb.size());
  const double read2 = sensor.read_noise * sensor.read_noise;
  for (std::size_t j = 0; j < bg.rgb.size(); j += 3) {
    for (int c = 0; c < 3; ++c) {
      const double v = bg.rgb[j + c];
      bg.signal[j + 2 - c] = static_cast<float>(v);
      bg.sigma[j + 2 - c] =
          static_cast<float>(std::sqrt(read2 + sensor.shot_gain * std::max(0.0, v)));
    }
  }

  // Gaussian bank for the per-frame noise (int16: half the memory traffic of float).
  SimRandom bank_rng(MixSeed(sensor.seed, 0x62616e6bull));  // "bank"
  bg.bank.resize(3 * static_cast<std::size_t>(npix) + kBankOffsets);
  for (std::int16_t& z : bg.bank) {
    const double sample = std::clamp(bank_rng.Normal() * kBankScale, -32767.0, 32767.0);
    z = static_cast<std::int16_t>(std::lround(sample));
  }
}

cv::Mat TactileCamera::Render(Clock::time_point capture_time) {
  if (!position_source_) {
    throw std::logic_error(
        "TactileCamera::Render: no machine position source (call SetMachinePositionSource)");
  }
  const Eigen::Vector3d machine = position_source_(capture_time);
  const Eigen::Vector3d ball = rig_->BallCenterSensor(machine);
  const double run_time = std::chrono::duration<double>(capture_time - run_start_).count();
  cv::Mat image;
  RenderInto(ball, next_frame_index_++, run_time, false, &image);
  last_truth_->capture_time = capture_time;
  last_truth_->machine_position = machine;
  return image;
}

cv::Mat TactileCamera::RenderAtBall(const std::optional<Eigen::Vector3d>& ball_center_sensor,
                                    std::uint64_t frame_index, double run_time_s) {
  cv::Mat image;
  RenderInto(ball_center_sensor, frame_index, run_time_s, false, &image);
  return image;
}

cv::Mat TactileCamera::RenderReference(std::uint64_t frame_index, double run_time_s) {
  return RenderAtBall(std::nullopt, frame_index, run_time_s);
}

// The region of a frame the displaced patch changes: the patch projected through the true camera,
// the closest hit per pixel of the ROI (the projected vertices' bounding box), and the pixels and
// truth maps re-rendered there.
class TactileCamera::PatchRender {
 public:
  // `gain`, `z` and `dst` as RenderInto's whole-image pass has them; contact_p: the penetration
  // from which a pixel counts as contact.
  // Each re-shaded pixel's drift-free signal is appended to `record`.
  PatchRender(const TactileCamera& camera, const DisplacedPatch& patch, double contact_p,
              const float gain[3], const std::int16_t* z, std::uint8_t* dst, FrameTruth* truth,
              PatchCache* record)
      : camera_(camera),
        bg_(*camera.background_),
        sensor_(camera.options_.sensor),
        patch_(patch),
        contact_p_(contact_p),
        gain_(gain),
        read2_(static_cast<float>(sensor_.read_noise * sensor_.read_noise)),
        shot_(static_cast<float>(sensor_.shot_gain)),
        z_(z),
        dst_(dst),
        truth_(truth),
        record_(record) {}

  // Sets truth->roi and the ROI's maps, re-renders its pixels; returns their count.
  int Render() {
    if (!Project()) return 0;
    FindHits();
    return Shade();
  }

 private:
  // The patch's vertices in the image and the ROI; false when the ROI is empty.
  bool Project() {
    const std::size_t nv = patch_.mesh.vertices.size();
    uv_.resize(nv);
    double u_lo = kInf, v_lo = kInf, u_hi = -kInf, v_hi = -kInf;
    for (std::size_t v = 0; v < nv; ++v) {
      uv_[v] = bg_.true_camera.ProjectUnchecked(bg_.cam_from_sensor * patch_.mesh.vertices[v]);
      u_lo = std::min(u_lo, uv_[v].x());
      u_hi = std::max(u_hi, uv_[v].x());
      v_lo = std::min(v_lo, uv_[v].y());
      v_hi = std::max(v_hi, uv_[v].y());
    }
    x0_ = std::max(0, static_cast<int>(std::floor(u_lo)) - 1);
    y0_ = std::max(0, static_cast<int>(std::floor(v_lo)) - 1);
    x1_ = std::min(camera_.width_ - 1, static_cast<int>(std::ceil(u_hi)) + 1);
    y1_ = std::min(camera_.height_ - 1, static_cast<int>(std::ceil(v_hi)) + 1);
    if (!(x1_ >= x0_ && y1_ >= y0_)) return false;
    truth_->roi = cv::Rect(x0_, y0_, x1_ - x0_ + 1, y1_ - y0_ + 1);
    rw_ = truth_->roi.width;
    return true;
  }

  // Closest patch hit per ROI pixel, starting from what hides the patch there: a fin, or gel the
  // patch does not replace. Each refined triangle is tested against the pixels inside its
  // projected bounding box (the triangles are about a pixel in size) with the exact watertight
  // ray test: a z-buffer with ray-traced depths, no BVH to build.
  void FindHits() {
    const int rh = truth_->roi.height;
    best_t_.assign(static_cast<std::size_t>(rw_) * rh, -1.0);
    best_tri_.assign(best_t_.size(), -1);
    best_b1_.resize(best_t_.size());
    best_b2_.resize(best_t_.size());
    setup_.resize(best_t_.size());
    for (int y = y0_; y <= y1_; ++y) {
      for (int x = x0_; x <= x1_; ++x) {
        const int i = y * camera_.width_ + x;
        const std::size_t r = static_cast<std::size_t>(y - y0_) * rw_ + (x - x0_);
        const std::uint8_t kind = bg_.kind[i];
        if (kind == kOutside) continue;  // best_t < 0: never hit
        double limit = bg_.t_fin[i];
        if (kind == kGel && patch_.replaced[bg_.tri_gel[i]] == 0)
          limit = std::min(limit, bg_.t_gel[i]);
        best_t_[r] = limit;
        setup_[r] = MakeRaySetup(bg_.dir[i]);
      }
    }
    for (int t = 0; t < patch_.mesh.NumTriangles(); ++t) TestTriangle(t);
  }

  void TestTriangle(int t) {
    constexpr double kMargin = 0.05;  // px; the projection is not linear over a triangle
    const Eigen::Vector3i& f = patch_.mesh.triangles[t];
    const Eigen::Vector2d& a = uv_[f[0]];
    const Eigen::Vector2d& b = uv_[f[1]];
    const Eigen::Vector2d& c = uv_[f[2]];
    const int px0 =
        std::max(x0_, static_cast<int>(std::ceil(std::min({a.x(), b.x(), c.x()}) - kMargin)));
    const int px1 =
        std::min(x1_, static_cast<int>(std::floor(std::max({a.x(), b.x(), c.x()}) + kMargin)));
    const int py0 =
        std::max(y0_, static_cast<int>(std::ceil(std::min({a.y(), b.y(), c.y()}) - kMargin)));
    const int py1 =
        std::min(y1_, static_cast<int>(std::floor(std::max({a.y(), b.y(), c.y()}) + kMargin)));
    for (int y = py0; y <= py1; ++y) {
      for (int x = px0; x <= px1; ++x) {
        const std::size_t r = static_cast<std::size_t>(y - y0_) * rw_ + (x - x0_);
        if (best_t_[r] < 0.0) continue;
        double th, b1, b2;
        if (!HitTriangle(setup_[r], bg_.origin, patch_.mesh.vertices[f[0]],
                         patch_.mesh.vertices[f[1]], patch_.mesh.vertices[f[2]], &th, &b1, &b2)) {
          continue;
        }
        if (th > best_t_[r] || (th == best_t_[r] && (best_tri_[r] < 0 || t > best_tri_[r])))
          continue;
        best_t_[r] = th;
        best_tri_[r] = t;
        best_b1_[r] = b1;
        best_b2_[r] = b2;
      }
    }
  }

  // The ROI's truth maps, and its pixels that see a displaced part of the patch re-rendered.
  int Shade() {
    FrameTruth& truth = *truth_;
    const cv::Size size = truth.roi.size();
    truth.contact_mask = cv::Mat::zeros(size, CV_8U);
    truth.deformed_mask = cv::Mat::zeros(size, CV_8U);
    truth.rho = cv::Mat(size, CV_64F, cv::Scalar(kNaN));
    truth.indentation = cv::Mat(size, CV_64F, cv::Scalar(kNaN));
    truth.points = cv::Mat(size, CV_64FC3, cv::Scalar::all(kNaN));
    truth.normals = cv::Mat(size, CV_64FC3, cv::Scalar::all(kNaN));
    int roi_pixels = 0;
    for (int y = y0_; y <= y1_; ++y) {
      for (int x = x0_; x <= x1_; ++x) {
        const int i = y * camera_.width_ + x;
        const std::uint8_t kind = bg_.kind[i];
        if (kind == kOutside) continue;
        ++roi_pixels;
        const int ry = y - y0_, rx = x - x0_;
        const std::size_t r = static_cast<std::size_t>(ry) * rw_ + rx;
        const bool gel_replaced = kind == kGel && patch_.replaced[bg_.tri_gel[i]] != 0;
        const int tri = best_tri_[r];
        // A hit on an undisplaced part of a replaced triangle looks like the background.
        const bool use_patch = tri >= 0 && (patch_.triangle_displaced[tri] != 0 || !gel_replaced);
        if (use_patch) {
          ShadeHit(i, ry, rx, r);
        } else if (kind == kGel) {
          // The whole-image pass already wrote the background signal.
          const Eigen::Vector3d p = bg_.origin + bg_.t_gel[i] * bg_.dir[i];
          const Eigen::Vector3d n = bg_.normal0[i].cast<double>();
          truth.rho.at<double>(ry, rx) = bg_.t_gel[i];
          truth.indentation.at<double>(ry, rx) = 0.0;
          truth.points.at<cv::Vec3d>(ry, rx) = cv::Vec3d(p.x(), p.y(), p.z());
          truth.normals.at<cv::Vec3d>(ry, rx) = cv::Vec3d(n.x(), n.y(), n.z());
        }
      }
    }
    return roi_pixels;
  }

  // Pixel i (ROI row ry, column rx, z-buffer entry r) sees the patch: shaded and its truth set.
  void ShadeHit(int i, int ry, int rx, std::size_t r) {
    FrameTruth& truth = *truth_;
    const Eigen::Vector3i& f = patch_.mesh.triangles[best_tri_[r]];
    const double b1 = best_b1_[r], b2 = best_b2_[r], b0 = 1.0 - b1 - b2;
    const double delta = b0 * patch_.displacement[f[0]] + b1 * patch_.displacement[f[1]] +
                         b2 * patch_.displacement[f[2]];
    const double pen = b0 * patch_.penetration[f[0]] + b1 * patch_.penetration[f[1]] +
                       b2 * patch_.penetration[f[2]];
    const Eigen::Vector3d point = bg_.origin + best_t_[r] * bg_.dir[i];
    const Eigen::Vector3d normal = (b0 * patch_.mesh.normals[f[0]] +
                                    b1 * patch_.mesh.normals[f[1]] + b2 * patch_.mesh.normals[f[2]])
                                       .normalized();
    const Eigen::Array3d radiance = camera_.lighting_->Shade(point, normal, -bg_.dir[i]);
    float signal[3];
    for (int c = 0; c < 3; ++c) {
      signal[c] = static_cast<float>((bg_.exposure * radiance[c] + sensor_.ambient_dn[c]) *
                                     bg_.vignette[i]);
    }
    const std::size_t j = 3 * static_cast<std::size_t>(i);
    WritePixel(signal, gain_, z_ ? z_ + j : nullptr, read2_, shot_, dst_ + j);
    record_->pixels.push_back(i);
    record_->signal.insert(record_->signal.end(), signal, signal + 3);
    truth.rho.at<double>(ry, rx) = best_t_[r];
    truth.indentation.at<double>(ry, rx) = delta;
    truth.points.at<cv::Vec3d>(ry, rx) = cv::Vec3d(point.x(), point.y(), point.z());
    truth.normals.at<cv::Vec3d>(ry, rx) = cv::Vec3d(normal.x(), normal.y(), normal.z());
    if (pen >= contact_p_) truth.contact_mask.at<std::uint8_t>(ry, rx) = 255;
    if (delta > kDeformedThreshold) truth.deformed_mask.at<std::uint8_t>(ry, rx) = 255;
  }

  const TactileCamera& camera_;
  const Background& bg_;
  const SensorModelOptions& sensor_;
  const DisplacedPatch& patch_;
  const double contact_p_;
  const float* const gain_;
  const float read2_;
  const float shot_;
  const std::int16_t* const z_;
  std::uint8_t* const dst_;
  FrameTruth* const truth_;
  PatchCache* const record_;
  std::vector<Eigen::Vector2d> uv_;                   // per patch vertex
  int x0_ = 0, y0_ = 0, x1_ = -1, y1_ = -1, rw_ = 0;  // ROI (inclusive) and its width
  // Per ROI pixel: the closest hit's t (< 0: never hit), triangle and barycentrics, and the
  // pixel's ray.
  std::vector<double> best_t_;
  std::vector<int> best_tri_;
  std::vector<double> best_b1_, best_b2_;
  std::vector<RaySetup> setup_;
};

void TactileCamera::RenderInto(const std::optional<Eigen::Vector3d>& ball,
                               std::uint64_t frame_index, double run_time_s, bool rigid,
                               cv::Mat* out) {
  const Clock::time_point start = Clock::now();
  const Background& bg = *background_;
  const SensorModelOptions& sensor = options_.sensor;
  const int npix = width_ * height_;
  FrameTruth truth;
  truth.frame_index = frame_index;
  truth.run_time_s = run_time_s;
  truth.drift_gain = DriftGain(run_time_s);
  truth.rigid = rigid || (options_.gel.elastic_length == 0.0 && options_.gel.bulge_fraction == 0.0);
  const float gain[3] = {static_cast<float>(truth.drift_gain[0]),
                         static_cast<float>(truth.drift_gain[1]),
                         static_cast<float>(truth.drift_gain[2])};
  const std::int16_t* z = sensor.noise ? bg.bank.data() + NoiseOffset(frame_index) : nullptr;

  out->create(height_, width_, CV_8UC3);
  std::uint8_t* dst = out->ptr<std::uint8_t>();
  WriteImage(npix, bg.signal.data(), bg.sigma.data(), gain, z, dst);
  stats_.last_image_seconds = SecondsSince(start);
  stats_.last_patch_seconds = 0.0;
  stats_.last_roi_seconds = 0.0;

  int roi_pixels = 0;
  if (ball) {
    truth.has_ball = true;
    truth.ball_center_sensor = *ball;
    truth.ball_center_machine = rig_->machine_from_sensor() * *ball;
    if (patch_cache_ && patch_cache_->Matches(*ball, rigid)) {
      ReusePatch(gain, z, dst);
    } else {
      RenderPatch(*ball, rigid, gain, z, dst);
    }
    patch_cache_->CopyTruth(&truth);
    roi_pixels = patch_cache_->roi_pixels;
  }
  *last_truth_ = std::move(truth);
  ++stats_.frames;
  stats_.last_roi_pixels = roi_pixels;
  stats_.last_patch_triangles = last_truth_->patch_triangles;
  stats_.last_frame_seconds = SecondsSince(start);
}

void TactileCamera::RenderPatch(const Eigen::Vector3d& ball, bool rigid, const float gain[3],
                                const std::int16_t* z, std::uint8_t* dst) {
  auto cache = std::make_unique<PatchCache>();
  cache->ball = ball;
  cache->rigid = rigid;
  const GelPatchBuilder& builder = rigid ? *rigid_patch_builder_ : *patch_builder_;
  Clock::time_point phase = Clock::now();
  const DisplacedPatch patch = builder.Build(ball, rig_->ball_radius());
  if (!patch.Empty()) {
    stats_.last_patch_seconds = SecondsSince(phase);
    phase = Clock::now();
    FrameTruth& truth = cache->truth;
    truth.max_depth_mm = patch.max_depth;
    truth.max_indentation_mm = patch.max_displacement;
    truth.patch_triangles = patch.mesh.NumTriangles();
    truth.contact_point_sensor = patch.contact_point;
    truth.contact_normal_sensor = patch.contact_normal;
    const double contact_p = std::max(builder.options().elastic_length, 1e-9);
    cache->roi_pixels =
        PatchRender(*this, patch, contact_p, gain, z, dst, &truth, cache.get()).Render();
    stats_.last_roi_seconds = SecondsSince(phase);
  }
  patch_cache_ = std::move(cache);
}

void TactileCamera::ReusePatch(const float gain[3], const std::int16_t* z, std::uint8_t* dst) {
  const Clock::time_point start = Clock::now();
  const PatchCache& cache = *patch_cache_;
  const float read2 = static_cast<float>(options_.sensor.read_noise * options_.sensor.read_noise);
  const float shot = static_cast<float>(options_.sensor.shot_gain);
  for (std::size_t k = 0; k < cache.pixels.size(); ++k) {
    const std::size_t j = 3 * static_cast<std::size_t>(cache.pixels[k]);
    WritePixel(&cache.signal[3 * k], gain, z ? z + j : nullptr, read2, shot, dst + j);
  }
  stats_.last_roi_seconds = SecondsSince(start);
}

// ---------------------------------------------------------------------------------------------
// Ground truth (sim/ground_truth.h)

std::optional<Eigen::Vector2d> SimGroundTruth::ProjectTrue(const SimRig& rig,
                                                           const Eigen::Vector3d& x) {
  return FisheyeCamera(rig.true_intrinsics_).CamToPixel(rig.true_cam_from_sensor_ * x);
}

const FrameTruth& SimGroundTruth::LastFrame(const TactileCamera& camera) {
  if (camera.stats_.frames == 0) {
    throw std::logic_error("SimGroundTruth::LastFrame: the camera has rendered no frame yet");
  }
  return *camera.last_truth_;
}

namespace {

cv::Mat PasteRoi(cv::Mat full, const FrameTruth& truth, const cv::Mat& roi_map) {
  if (!truth.roi.empty()) roi_map.copyTo(full(truth.roi));
  return full;
}

}  // namespace

cv::Mat SimGroundTruth::ContactMask(const TactileCamera& camera) {
  const FrameTruth& truth = LastFrame(camera);
  return PasteRoi(cv::Mat::zeros(camera.height_, camera.width_, CV_8U), truth, truth.contact_mask);
}

cv::Mat SimGroundTruth::DeformedMask(const TactileCamera& camera) {
  const FrameTruth& truth = LastFrame(camera);
  return PasteRoi(cv::Mat::zeros(camera.height_, camera.width_, CV_8U), truth, truth.deformed_mask);
}

cv::Mat SimGroundTruth::Rho(const TactileCamera& camera) {
  const FrameTruth& truth = LastFrame(camera);
  return PasteRoi(BackgroundRho(camera), truth, truth.rho);
}

cv::Mat SimGroundTruth::BackgroundRho(const TactileCamera& camera) {
  const auto& bg = *camera.background_;
  cv::Mat rho(camera.height_, camera.width_, CV_64F);
  for (int i = 0; i < camera.width_ * camera.height_; ++i) {
    rho.at<double>(i / camera.width_, i % camera.width_) =
        bg.kind[i] == TactileCamera::kGel ? bg.t_gel[i] : kNaN;
  }
  return rho;
}

cv::Mat SimGroundTruth::BackgroundNormals(const TactileCamera& camera) {
  const auto& bg = *camera.background_;
  cv::Mat normals(camera.height_, camera.width_, CV_64FC3);
  for (int i = 0; i < camera.width_ * camera.height_; ++i) {
    const Eigen::Vector3f& n = bg.normal0[i];
    normals.at<cv::Vec3d>(i / camera.width_, i % camera.width_) =
        bg.kind[i] == TactileCamera::kGel ? cv::Vec3d(n.x(), n.y(), n.z())
                                          : cv::Vec3d(kNaN, kNaN, kNaN);
  }
  return normals;
}

cv::Mat SimGroundTruth::FinMask(const TactileCamera& camera) {
  const auto& bg = *camera.background_;
  cv::Mat mask(camera.height_, camera.width_, CV_8U);
  for (int i = 0; i < camera.width_ * camera.height_; ++i) {
    mask.at<std::uint8_t>(i / camera.width_, i % camera.width_) =
        bg.kind[i] == TactileCamera::kFin ? 255 : 0;
  }
  return mask;
}

cv::Mat SimGroundTruth::ImageCircleMask(const TactileCamera& camera) {
  const auto& bg = *camera.background_;
  cv::Mat mask(camera.height_, camera.width_, CV_8U);
  for (int i = 0; i < camera.width_ * camera.height_; ++i) {
    mask.at<std::uint8_t>(i / camera.width_, i % camera.width_) =
        bg.kind[i] == TactileCamera::kOutside ? 0 : 255;
  }
  return mask;
}

cv::Mat SimGroundTruth::BackgroundSignal(const TactileCamera& camera) {
  const auto& bg = *camera.background_;
  cv::Mat signal(camera.height_, camera.width_, CV_32FC3);
  std::copy(bg.rgb.begin(), bg.rgb.end(), signal.ptr<float>());
  return signal;
}

double SimGroundTruth::Exposure(const TactileCamera& camera) {
  return camera.background_->exposure;
}

cv::Mat SimGroundTruth::RenderRigidAtBall(TactileCamera& camera,
                                          const Eigen::Vector3d& ball_center_sensor,
                                          std::uint64_t frame_index, double run_time_s) {
  cv::Mat image;
  camera.RenderInto(ball_center_sensor, frame_index, run_time_s, true, &image);
  return image;
}

}  // namespace gs360
