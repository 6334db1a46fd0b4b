#include "recon/surface_map.h"

#include <Eigen/Dense>
#include <algorithm>
#include <atomic>
#include <bit>
#include <chrono>
#include <cmath>
#include <cstring>
#include <numbers>
#include <sstream>
#include <stdexcept>
#include <string>
#include <thread>

#include "base/byte_io.h"
#include "base/field_error.h"
#include "base/hash.h"

namespace gs360 {
namespace {

template <typename T>
void GetVector(ByteReader& r, std::vector<T>& out, std::size_t n, const char* what) {
  out.resize(n);
  r.GetArray(out.data(), n, what);
}

static_assert(std::endian::native == std::endian::little,
              "SurfaceMap serialisation assumes a little-endian host");

constexpr double kDegToRad = std::numbers::pi / 180.0;
constexpr char kMagic[8] = {'G', 'S', '3', '6', '0', 'S', 'M', 'P'};
constexpr std::uint32_t kVersion = 1;

[[noreturn]] void BadOption(const char* field, double v, const char* rule) {
  ThrowFieldError(std::string("SurfaceMapOptions.") + field, v, rule);
}

void Put3(std::vector<float>& a, std::size_t i, const Eigen::Vector3d& x) {
  a[3 * i] = static_cast<float>(x.x());
  a[3 * i + 1] = static_cast<float>(x.y());
  a[3 * i + 2] = static_cast<float>(x.z());
}

// Derivative of the unit ray with respect to (u, v): the 3x2 matrix D with J D = I (J the
// Jacobian of the projection restricted to the unit sphere) and d.D = 0. J comes from central
// differences of ProjectUnchecked along two tangent directions of the sphere (step 1e-6 rad:
// error ~1e-10 relative), which is exact to far below what the floats store.
Eigen::Matrix<double, 3, 2> RayDerivatives(const FisheyeCamera& camera, const Eigen::Vector3d& d) {
  Eigen::Vector3d e1 = d.unitOrthogonal();
  Eigen::Vector3d e2 = d.cross(e1).normalized();
  constexpr double kStep = 1e-6;
  Eigen::Matrix2d j;
  j.col(0) = (camera.ProjectUnchecked(d + kStep * e1) - camera.ProjectUnchecked(d - kStep * e1)) /
             (2.0 * kStep);
  j.col(1) = (camera.ProjectUnchecked(d + kStep * e2) - camera.ProjectUnchecked(d - kStep * e2)) /
             (2.0 * kStep);
  Eigen::Matrix<double, 3, 2> e;
  e.col(0) = e1;
  e.col(1) = e2;
  return e * j.inverse();
}

// Little-endian byte writer / reader.
}  // namespace

void SurfaceMapOptions::Check() const {
  if (!(max_view_angle_deg > 0.0) || !(max_view_angle_deg < 90.0)) {
    BadOption("max_view_angle_deg", max_view_angle_deg, "must be in (0, 90) deg");
  }
  if (!(fin_margin_px >= 0.0) || !std::isfinite(fin_margin_px)) {
    BadOption("fin_margin_px", fin_margin_px, "must be finite and >= 0");
  }
  if (threads < 1 || threads > 64) BadOption("threads", threads, "must be in 1..64");
}

SurfaceMap SurfaceMap::Build(const FisheyeCamera& camera, const Rigid3d& cam_from_sensor,
                             const Bvh& gel, const Bvh* fins, const SurfaceMapOptions& options) {
  options.Check();
  const auto start = std::chrono::steady_clock::now();
  SurfaceMap map;
  map.width_ = camera.width();
  map.height_ = camera.height();
  map.cam_from_sensor_ = cam_from_sensor;
  map.options_ = options;
  const std::size_t n =
      static_cast<std::size_t>(map.width_) * static_cast<std::size_t>(map.height_);
  map.status_.assign(n, SurfacePixel::kOutside);
  map.ray_.assign(3 * n, 0.0f);
  map.ray_du_.assign(3 * n, 0.0f);
  map.ray_dv_.assign(3 * n, 0.0f);
  map.n0_.assign(3 * n, 0.0f);
  map.t1_.assign(3 * n, 0.0f);
  map.t2_.assign(3 * n, 0.0f);
  map.rho0_.assign(n, 0.0);
  map.view_angle_.assign(n, 0.0f);

  const Rigid3d sensor_from_cam = cam_from_sensor.Inverse();
  const Eigen::Matrix3d cam_r_sensor = cam_from_sensor.RotationMatrix();
  const Eigen::Matrix3d sensor_r_cam = cam_r_sensor.transpose();
  const double cos_max_view = std::cos(options.max_view_angle_deg * kDegToRad);

  auto do_row = [&](int v) {
    for (int u = 0; u < map.width_; ++u) {
      const std::size_t i = map.Index(u, v);
      const std::optional<Eigen::Vector3d> ray = camera.PixelToRay(Eigen::Vector2d(u, v));
      if (!ray) continue;  // kOutside
      const Eigen::Vector3d d = *ray;
      const Eigen::Matrix<double, 3, 2> dd = RayDerivatives(camera, d);
      Put3(map.ray_, i, d);
      Put3(map.ray_du_, i, dd.col(0));
      Put3(map.ray_dv_, i, dd.col(1));

      Ray sensor_ray;
      sensor_ray.origin = sensor_from_cam.translation;
      sensor_ray.direction = (sensor_r_cam * d).normalized();
      const std::optional<RayHit> hit = gel.Intersect(sensor_ray);
      if (!hit) {
        map.status_[i] = SurfacePixel::kNoHit;
        continue;
      }
      const Eigen::Vector3d n0 = (cam_r_sensor * hit->normal).normalized();
      const double nd = n0.dot(d);
      const Eigen::Vector3d du = dd.col(0);
      Eigen::Vector3d t1 = du - d * (n0.dot(du) / nd);
      if (!(std::abs(nd) > 1e-12) || !t1.allFinite() || t1.norm() < 1e-300) {
        t1 = du - n0 * n0.dot(du);  // exactly grazing: fall back to the tangent projection
      }
      t1.normalize();
      const Eigen::Vector3d t2 = n0.cross(t1).normalized();
      map.rho0_[i] = hit->t;
      Put3(map.n0_, i, n0);
      Put3(map.t1_, i, t1);
      Put3(map.t2_, i, t2);
      const double c = std::min(1.0, std::abs(nd));
      map.view_angle_[i] = static_cast<float>(std::acos(c));
      if (fins != nullptr && fins->Occluded(sensor_ray, 0.0, hit->t)) {
        map.status_[i] = SurfacePixel::kFin;
      } else if (c < cos_max_view) {
        map.status_[i] = SurfacePixel::kGrazing;
      } else {
        map.status_[i] = SurfacePixel::kVisible;
      }
    }
  };

  const int threads = std::min(options.threads, std::max(1, map.height_));
  std::atomic<int> next_row{0};
  auto worker = [&]() {
    for (int v = next_row.fetch_add(1); v < map.height_; v = next_row.fetch_add(1)) do_row(v);
  };
  if (threads == 1) {
    worker();
  } else {
    std::vector<std::jthread> pool;
    pool.reserve(static_cast<std::size_t>(threads - 1));
    for (int t = 1; t < threads; ++t) pool.emplace_back(worker);
    worker();
  }

  // Dilate the fin pixels by fin_margin_px (a disc): visible / grazing pixels near a fin pixel
  // become kFin. The dilation reads a copy so that it does not cascade.
  if (fins != nullptr && options.fin_margin_px > 0.0) {
    const std::vector<SurfacePixel> before = map.status_;
    const int r = static_cast<int>(std::floor(options.fin_margin_px));
    const double r2 = options.fin_margin_px * options.fin_margin_px;
    for (int v = 0; v < map.height_; ++v) {
      for (int u = 0; u < map.width_; ++u) {
        if (before[map.Index(u, v)] != SurfacePixel::kFin) continue;
        for (int dv = -r; dv <= r; ++dv) {
          for (int du = -r; du <= r; ++du) {
            if (du * du + dv * dv > r2) continue;
            const int uu = u + du, vv = v + dv;
            if (uu < 0 || vv < 0 || uu >= map.width_ || vv >= map.height_) continue;
            SurfacePixel& s = map.status_[map.Index(uu, vv)];
            if (s == SurfacePixel::kVisible || s == SurfacePixel::kGrazing) s = SurfacePixel::kFin;
          }
        }
      }
    }
  }

  SurfaceMapStats& st = map.stats_;
  for (const SurfacePixel s : map.status_) {
    switch (s) {
      case SurfacePixel::kVisible:
        ++st.visible;
        break;
      case SurfacePixel::kFin:
        ++st.fin;
        break;
      case SurfacePixel::kGrazing:
        ++st.grazing;
        break;
      case SurfacePixel::kNoHit:
        ++st.no_hit;
        break;
      case SurfacePixel::kOutside:
        ++st.outside;
        break;
    }
  }
  st.build_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  if (st.visible == 0) {
    const Eigen::Vector3d cam_in_sensor = sensor_from_cam.translation;
    std::ostringstream os;
    os << "SurfaceMap::Build: no pixel sees the gel (camera centre in the sensor frame at ("
       << cam_in_sensor.x() << ", " << cam_in_sensor.y() << ", " << cam_in_sensor.z()
       << ") mm, rotation " << cam_from_sensor.AngleRad() * 180.0 / std::numbers::pi
       << " deg; fins " << st.fin << ", grazing " << st.grazing << ", no hit " << st.no_hit
       << " px): check the camera pose and the sensor mesh";
    throw std::runtime_error(os.str());
  }
  return map;
}

cv::Mat SurfaceMap::VisibleMask() const {
  cv::Mat m(height_, width_, CV_8U);
  for (int v = 0; v < height_; ++v) {
    auto* row = m.ptr<std::uint8_t>(v);
    for (int u = 0; u < width_; ++u) row[u] = visible(u, v) ? 255 : 0;
  }
  return m;
}

cv::Mat SurfaceMap::StatusImage() const {
  cv::Mat m(height_, width_, CV_8U);
  for (int v = 0; v < height_; ++v) {
    auto* row = m.ptr<std::uint8_t>(v);
    for (int u = 0; u < width_; ++u) row[u] = static_cast<std::uint8_t>(status(u, v));
  }
  return m;
}

Eigen::Vector3d SurfaceMap::NormalFromSlopes(int u, int v, double gx, double gy) const {
  return (normal0(u, v) + gx * t1(u, v) + gy * t2(u, v)).normalized();
}

Eigen::Vector2d SurfaceMap::SlopesFromNormal(int u, int v, const Eigen::Vector3d& n) const {
  const double nn0 = n.dot(normal0(u, v));
  if (!(nn0 > 0.0)) {
    std::ostringstream os;
    os << "SurfaceMap::SlopesFromNormal: n.n0 = " << nn0 << " at pixel (" << u << ", " << v
       << ") must be > 0";
    throw std::invalid_argument(os.str());
  }
  return {n.dot(t1(u, v)) / nn0, n.dot(t2(u, v)) / nn0};
}

std::vector<std::uint8_t> SurfaceMap::Serialize() const {
  const std::size_t n = status_.size();
  ByteWriter w(256 + n * (1 + 18 * sizeof(float) + sizeof(double) + sizeof(float)));
  w.Bytes(kMagic, sizeof(kMagic));
  w.Put<std::uint32_t>(kVersion);
  w.Put<std::int32_t>(width_);
  w.Put<std::int32_t>(height_);
  w.Put<double>(options_.max_view_angle_deg);
  w.Put<double>(options_.fin_margin_px);
  w.Put<std::int32_t>(options_.threads);
  const Eigen::Quaterniond& q = cam_from_sensor_.rotation;
  for (double x : {q.w(), q.x(), q.y(), q.z(), cam_from_sensor_.translation.x(),
                   cam_from_sensor_.translation.y(), cam_from_sensor_.translation.z()}) {
    w.Put<double>(x);
  }
  for (int c : {stats_.visible, stats_.fin, stats_.grazing, stats_.no_hit, stats_.outside}) {
    w.Put<std::int32_t>(c);
  }
  w.Put<double>(stats_.build_seconds);
  w.PutArray(status_.data(), status_.size());
  w.PutArray(ray_.data(), ray_.size());
  w.PutArray(ray_du_.data(), ray_du_.size());
  w.PutArray(ray_dv_.data(), ray_dv_.size());
  w.PutArray(n0_.data(), n0_.size());
  w.PutArray(t1_.data(), t1_.size());
  w.PutArray(t2_.data(), t2_.size());
  w.PutArray(rho0_.data(), rho0_.size());
  w.PutArray(view_angle_.data(), view_angle_.size());
  Hasher h;
  h.Add(w.bytes().data(), w.bytes().size());
  w.Put<std::uint64_t>(h.Digest());
  return std::move(w.bytes());
}

namespace {

void ReadMagicAndVersion(ByteReader& r) {
  char magic[8];
  r.Bytes(magic, sizeof(magic), "magic");
  if (std::memcmp(magic, kMagic, sizeof(kMagic)) != 0) {
    throw std::runtime_error("SurfaceMap::Deserialize: bad magic (not a gs360 surface map)");
  }
  const auto version = r.Get<std::uint32_t>("version");
  if (version != kVersion) {
    throw std::runtime_error("SurfaceMap::Deserialize: unsupported version " +
                             std::to_string(version) + " (this build reads version " +
                             std::to_string(kVersion) + ")");
  }
}

Rigid3d ReadPose(ByteReader& r) {
  double pose[7];
  for (double& x : pose) x = r.Get<double>("pose");
  Rigid3d cam_from_sensor(Eigen::Quaterniond(pose[0], pose[1], pose[2], pose[3]),
                          Eigen::Vector3d(pose[4], pose[5], pose[6]));
  // Keep the stored rotation bit-exact (the constructor normalises, which may round).
  cam_from_sensor.rotation = Eigen::Quaterniond(pose[0], pose[1], pose[2], pose[3]);
  return cam_from_sensor;
}

SurfaceMapStats ReadStats(ByteReader& r) {
  SurfaceMapStats stats;
  stats.visible = r.Get<std::int32_t>("stats");
  stats.fin = r.Get<std::int32_t>("stats");
  stats.grazing = r.Get<std::int32_t>("stats");
  stats.no_hit = r.Get<std::int32_t>("stats");
  stats.outside = r.Get<std::int32_t>("stats");
  stats.build_seconds = r.Get<double>("stats");
  return stats;
}

// The checksum after the first `body` bytes, at the reader's position.
void CheckChecksum(ByteReader& r, std::span<const std::uint8_t> bytes, std::size_t body) {
  const auto stored = r.Get<std::uint64_t>("checksum");
  Hasher h;
  h.Add(bytes.data(), body);
  if (h.Digest() != stored) {
    throw std::runtime_error("SurfaceMap::Deserialize: checksum mismatch (stored " +
                             ToHex64(stored) + ", computed " + ToHex64(h.Digest()) +
                             "): the data is corrupted");
  }
}

void CheckStatuses(const std::vector<SurfacePixel>& status) {
  for (std::size_t i = 0; i < status.size(); ++i) {
    if (static_cast<std::uint8_t>(status[i]) > static_cast<std::uint8_t>(SurfacePixel::kVisible)) {
      throw std::runtime_error("SurfaceMap::Deserialize: bad pixel status " +
                               std::to_string(static_cast<int>(status[i])) + " at index " +
                               std::to_string(i));
    }
  }
}

}  // namespace

SurfaceMap SurfaceMap::Deserialize(std::span<const std::uint8_t> bytes) {
  ByteReader r(bytes, "SurfaceMap::Deserialize");
  ReadMagicAndVersion(r);
  SurfaceMap map;
  map.width_ = r.Get<std::int32_t>("width");
  map.height_ = r.Get<std::int32_t>("height");
  if (map.width_ <= 0 || map.height_ <= 0 || map.width_ > 65536 || map.height_ > 65536) {
    throw std::runtime_error("SurfaceMap::Deserialize: bad image size " +
                             std::to_string(map.width_) + " x " + std::to_string(map.height_));
  }
  map.options_.max_view_angle_deg = r.Get<double>("options");
  map.options_.fin_margin_px = r.Get<double>("options");
  map.options_.threads = r.Get<std::int32_t>("options");
  map.cam_from_sensor_ = ReadPose(r);
  map.stats_ = ReadStats(r);

  const std::size_t n =
      static_cast<std::size_t>(map.width_) * static_cast<std::size_t>(map.height_);
  const std::size_t payload = n * (1 + 18 * sizeof(float) + sizeof(double) + sizeof(float));
  const std::size_t expected = r.pos() + payload + sizeof(std::uint64_t);
  if (bytes.size() != expected) {
    std::ostringstream os;
    os << "SurfaceMap::Deserialize: " << (bytes.size() < expected ? "truncated" : "oversized")
       << " input: " << map.width_ << " x " << map.height_ << " map needs " << expected
       << " bytes, got " << bytes.size();
    throw std::runtime_error(os.str());
  }
  GetVector(r, map.status_, n, "status");
  GetVector(r, map.ray_, 3 * n, "ray");
  GetVector(r, map.ray_du_, 3 * n, "ray_du");
  GetVector(r, map.ray_dv_, 3 * n, "ray_dv");
  GetVector(r, map.n0_, 3 * n, "n0");
  GetVector(r, map.t1_, 3 * n, "t1");
  GetVector(r, map.t2_, 3 * n, "t2");
  GetVector(r, map.rho0_, n, "rho0");
  GetVector(r, map.view_angle_, n, "view_angle");
  CheckChecksum(r, bytes, r.pos());
  try {
    map.options_.Check();
  } catch (const std::invalid_argument& e) {
    throw std::runtime_error(std::string("SurfaceMap::Deserialize: bad stored options: ") +
                             e.what());
  }
  CheckStatuses(map.status_);
  return map;
}

}  // namespace gs360
