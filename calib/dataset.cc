#include "calib/dataset.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <numeric>
#include <random>
#include <stdexcept>
#include <string>

#include "base/field_error.h"
#include "base/hash.h"
#include "recon/features.h"

namespace gs360 {
namespace {

constexpr char kMagic[8] = {'G', 'S', '3', '6', '0', 'D', 'S', 'T'};
constexpr std::uint32_t kVersion = 2;  // 2: the feature count is stored (1: always 5)

[[noreturn]] void Bad(const std::string& field, double value, const std::string& rule) {
  ThrowFieldError("DatasetOptions." + field, value, "must be " + rule);
}

void Put(std::vector<std::uint8_t>* out, const void* data, std::size_t size) {
  if (size == 0) return;
  const std::size_t at = out->size();
  out->resize(at + size);
  std::memcpy(out->data() + at, data, size);
}

class Reader {
 public:
  explicit Reader(std::span<const std::uint8_t> b) : b_(b) {}
  void Get(void* data, std::size_t size) {
    if (size > b_.size() - pos_) {
      throw std::runtime_error("dataset artifact truncated at byte " + std::to_string(pos_) +
                               " of " + std::to_string(b_.size()));
    }
    if (size > 0) std::memcpy(data, b_.data() + pos_, size);
    pos_ += size;
  }
  template <typename T>
  T Pod() {
    T v;
    Get(&v, sizeof(T));
    return v;
  }

 private:
  std::span<const std::uint8_t> b_;
  std::size_t pos_ = 0;
};

}  // namespace

void DatasetOptions::Check() const {
  if (max_contact_samples_per_probe < 1) {
    Bad("max_contact_samples_per_probe", max_contact_samples_per_probe, ">= 1");
  }
  if (!(non_contact_fraction >= 0.0 && non_contact_fraction <= 0.9)) {
    Bad("non_contact_fraction", non_contact_fraction, "in [0, 0.9]");
  }
  if (max_samples < 0) Bad("max_samples", static_cast<double>(max_samples), ">= 0");
  if (min_contact_pixels < 1) Bad("min_contact_pixels", min_contact_pixels, ">= 1");
  if (!(validation_fraction > 0.0 && validation_fraction < 0.5)) {
    Bad("validation_fraction", validation_fraction, "in (0, 0.5)");
  }
  if (!(test_fraction > 0.0 && test_fraction < 0.5))
    Bad("test_fraction", test_fraction, "in (0, 0.5)");
  if (!(edge_exclusion_mm >= 0.0 && edge_exclusion_mm <= 2.0)) {
    Bad("edge_exclusion_mm", edge_exclusion_mm, "in [0, 2] mm");
  }
  if (small_probe_repeat < 1 || small_probe_repeat > 16) {
    Bad("small_probe_repeat", small_probe_repeat, "in [1, 16]");
  }
}

int DatasetOptions::ContactSamplesPerProbe(std::size_t probes) const {
  if (max_samples == 0 || probes == 0) return max_contact_samples_per_probe;
  // Non-contact samples come on top: non_contact_fraction of each probe's samples.
  const double contact_budget = static_cast<double>(max_samples) * (1.0 - non_contact_fraction);
  const double per_probe = std::floor(contact_budget / static_cast<double>(probes));
  return static_cast<int>(
      std::clamp(per_probe, 1.0, static_cast<double>(max_contact_samples_per_probe)));
}

std::vector<Split> SplitProbes(std::span<const std::int32_t> probes,
                               const DatasetOptions& options) {
  options.Check();
  const std::size_t n = probes.size();
  // Rank the probes by a hash of (plan index, seed) rather than shuffling the list: a probe's
  // split then depends on the probe, not on which other probes made it into the list, so one
  // probe more or less (a pose change that moves one render's contact mask) moves at most one
  // probe across each boundary instead of redrawing the whole test set.
  auto key = [&](std::size_t i) {
    std::uint64_t z = options.seed * 0x9e3779b97f4a7c15ULL ^
                      (static_cast<std::uint64_t>(static_cast<std::uint32_t>(probes[i])) + 0x5eed);
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;  // splitmix64 finaliser
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
    return z ^ (z >> 31);
  };
  std::vector<std::pair<std::uint64_t, std::size_t>> ranked(n);
  for (std::size_t i = 0; i < n; ++i) ranked[i] = {key(i), i};
  std::sort(ranked.begin(), ranked.end());
  std::vector<std::size_t> order(n);
  for (std::size_t k = 0; k < n; ++k) order[k] = ranked[k].second;
  std::size_t n_test = static_cast<std::size_t>(std::llround(options.test_fraction * n));
  std::size_t n_val = static_cast<std::size_t>(std::llround(options.validation_fraction * n));
  if (n >= 3) {
    n_test = std::max<std::size_t>(n_test, 1);
    n_val = std::max<std::size_t>(n_val, 1);
  }
  std::vector<Split> split(n, Split::kTrain);
  for (std::size_t k = 0; k < n; ++k) {
    if (k < n_test) {
      split[order[k]] = Split::kTest;
    } else if (k < n_test + n_val) {
      split[order[k]] = Split::kValidation;
    }
  }
  return split;
}

namespace {
// Cycles through `pts` (already in random order) until it holds `n` points; empty stays empty.
void Repeat(std::vector<cv::Point>* pts, std::size_t n) {
  const std::size_t have = pts->size();
  for (std::size_t i = 0; have > 0 && pts->size() < n; ++i) pts->push_back((*pts)[i % have]);
}
}  // namespace

std::size_t AppendProbeSamples(const cv::Mat& diff, const ProbeRender& render, int plan_index,
                               const DatasetOptions& options, Dataset* out,
                               const cv::Mat& penetration, const cv::Mat& context) {
  if (render.contact_pixels < options.min_contact_pixels || render.roi.empty()) return 0;
  if (diff.type() != CV_32FC3)
    throw std::invalid_argument("AppendProbeSamples: diff must be CV_32FC3");
  const bool exclude_edge = options.edge_exclusion_mm > 0.0;
  if (exclude_edge && (penetration.type() != CV_32F || penetration.size() != render.roi.size())) {
    throw std::invalid_argument(
        "AppendProbeSamples: edge_exclusion_mm > 0 needs the roi's penetration map (CV_32F)");
  }
  if (!context.empty() && (context.depth() != CV_32F || context.size() != render.roi.size())) {
    throw std::invalid_argument(
        "AppendProbeSamples: context features must be CV_32F of the roi's size");
  }
  const int rows = kFeatureCount + (context.empty() ? 0 : context.channels());
  if (out->x.cols() > 0 && out->x.rows() != rows) {
    throw std::invalid_argument("AppendProbeSamples: " + std::to_string(rows) +
                                " features per sample, the dataset has " +
                                std::to_string(out->x.rows()));
  }
  const float edge = static_cast<float>(options.edge_exclusion_mm);
  std::vector<cv::Point> contact, other;
  for (int y = 0; y < render.roi.height; ++y) {
    for (int x = 0; x < render.roi.width; ++x) {
      if (std::isnan(render.rho.at<double>(y, x))) continue;  // not visible
      if (exclude_edge && std::abs(penetration.at<float>(y, x)) < edge) continue;
      (render.contact.at<std::uint8_t>(y, x) ? contact : other).emplace_back(x, y);
    }
  }
  std::mt19937_64 rng(options.seed * 0x9E3779B97F4A7C15ULL +
                      static_cast<std::uint64_t>(plan_index));
  auto take = [&rng](std::vector<cv::Point>& pts, std::size_t k) {
    k = std::min(k, pts.size());
    for (std::size_t i = 0; i < k; ++i) {
      const std::size_t j = i + static_cast<std::size_t>(rng() % (pts.size() - i));
      std::swap(pts[i], pts[j]);
    }
    pts.resize(k);
  };
  const std::size_t cap = static_cast<std::size_t>(options.max_contact_samples_per_probe);
  const std::size_t seen = std::min(cap, contact.size());
  const std::size_t wanted =
      std::min(cap, seen * static_cast<std::size_t>(options.small_probe_repeat));
  take(contact, seen);
  Repeat(&contact, wanted);
  const double f = options.non_contact_fraction;
  const std::size_t other_wanted =
      static_cast<std::size_t>(std::llround(f / (1.0 - f) * static_cast<double>(contact.size())));
  take(other, other_wanted);
  Repeat(&other, other_wanted);

  const Eigen::Index start = out->x.cols();
  const Eigen::Index count = static_cast<Eigen::Index>(contact.size() + other.size());
  out->x.conservativeResize(rows, start + count);
  out->y.conservativeResize(2, start + count);
  Eigen::Index c = start;
  for (int pass = 0; pass < 2; ++pass) {
    for (const cv::Point& p : pass == 0 ? contact : other) {
      const int u = render.roi.x + p.x, v = render.roi.y + p.y;
      PixelFeatures(diff, context, render.roi.tl(), u, v, out->x.col(c).data());
      out->y(0, c) = pass == 0 ? render.gx.at<float>(p) : 0.0f;
      out->y(1, c) = pass == 0 ? render.gy.at<float>(p) : 0.0f;
      out->probe.push_back(plan_index);
      out->contact.push_back(pass == 0 ? 1 : 0);
      ++c;
    }
  }
  return static_cast<std::size_t>(count);
}

namespace {
Eigen::MatrixXf Columns(const Eigen::MatrixXf& m, const Dataset& d, Split s) {
  std::vector<std::int32_t> want = d.ProbesIn(s);
  std::sort(want.begin(), want.end());
  std::vector<Eigen::Index> cols;
  for (std::size_t i = 0; i < d.probe.size(); ++i) {
    if (std::binary_search(want.begin(), want.end(), d.probe[i])) {
      cols.push_back(static_cast<Eigen::Index>(i));
    }
  }
  Eigen::MatrixXf out(m.rows(), static_cast<Eigen::Index>(cols.size()));
  for (std::size_t k = 0; k < cols.size(); ++k)
    out.col(static_cast<Eigen::Index>(k)) = m.col(cols[k]);
  return out;
}
}  // namespace

Eigen::MatrixXf Dataset::X(Split s) const {
  return Columns(x, *this, s);
}
Eigen::MatrixXf Dataset::Y(Split s) const {
  return Columns(y, *this, s);
}

std::vector<std::int32_t> Dataset::ProbesIn(Split s) const {
  std::vector<std::int32_t> out;
  for (std::size_t i = 0; i < probes.size(); ++i) {
    if (probe_split[i] == s) out.push_back(probes[i]);
  }
  return out;
}

std::size_t Dataset::Count(Split s) const {
  return static_cast<std::size_t>(Columns(y, *this, s).cols());
}

std::vector<std::uint8_t> Dataset::Serialize() const {
  std::vector<std::uint8_t> b;
  Put(&b, kMagic, sizeof(kMagic));
  Put(&b, &kVersion, sizeof(kVersion));
  const std::uint64_t n = static_cast<std::uint64_t>(x.cols());
  const std::uint64_t np = probes.size();
  const std::uint32_t rows = static_cast<std::uint32_t>(x.rows());
  Put(&b, &n, sizeof(n));
  Put(&b, &np, sizeof(np));
  Put(&b, &rows, sizeof(rows));
  Put(&b, x.data(), sizeof(float) * x.size());
  Put(&b, y.data(), sizeof(float) * y.size());
  Put(&b, probe.data(), sizeof(std::int32_t) * probe.size());
  Put(&b, contact.data(), contact.size());
  Put(&b, probes.data(), sizeof(std::int32_t) * probes.size());
  Put(&b, probe_split.data(), probe_split.size());
  const std::uint64_t sum = Hasher().Add(b.data(), b.size()).Digest();
  Put(&b, &sum, sizeof(sum));
  return b;
}

Dataset Dataset::Deserialize(std::span<const std::uint8_t> bytes) {
  if (bytes.size() < sizeof(kMagic) + 8 || std::memcmp(bytes.data(), kMagic, sizeof(kMagic)) != 0) {
    throw std::runtime_error("not a gs360 dataset artifact (bad magic)");
  }
  std::uint64_t stored;
  std::memcpy(&stored, bytes.data() + bytes.size() - 8, 8);
  if (Hasher().Add(bytes.data(), bytes.size() - 8).Digest() != stored) {
    throw std::runtime_error("dataset artifact checksum mismatch (corrupt)");
  }
  Reader r(bytes.first(bytes.size() - 8));
  char magic[8];
  r.Get(magic, 8);
  const auto version = r.Pod<std::uint32_t>();
  if (version != 1 && version != kVersion) {
    throw std::runtime_error("dataset artifact version " + std::to_string(version) +
                             " is not supported (expected " + std::to_string(kVersion) + ")");
  }
  const auto n = r.Pod<std::uint64_t>();
  const auto np = r.Pod<std::uint64_t>();
  const std::uint32_t rows = version >= 2 ? r.Pod<std::uint32_t>() : kFeatureCount;
  if (n > (1ull << 34) || np > (1ull << 31) || rows < kFeatureCount || rows > 64)
    throw std::runtime_error("dataset artifact sizes are absurd");
  Dataset d;
  d.x.resize(static_cast<Eigen::Index>(rows), static_cast<Eigen::Index>(n));
  d.y.resize(2, static_cast<Eigen::Index>(n));
  r.Get(d.x.data(), sizeof(float) * d.x.size());
  r.Get(d.y.data(), sizeof(float) * d.y.size());
  d.probe.resize(n);
  r.Get(d.probe.data(), sizeof(std::int32_t) * n);
  d.contact.resize(n);
  r.Get(d.contact.data(), n);
  d.probes.resize(np);
  r.Get(d.probes.data(), sizeof(std::int32_t) * np);
  d.probe_split.resize(np);
  r.Get(d.probe_split.data(), np);
  return d;
}

}  // namespace gs360
