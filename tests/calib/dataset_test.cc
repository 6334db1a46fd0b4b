#include <catch2/catch.hpp>

#include <cmath>
#include <cstring>
#include <map>
#include <set>

#include "base/hash.h"
#include "calib/dataset.h"
#include "recon/features.h"

using namespace gs360;

namespace {
// A render with a disc of contact (slopes = position in the disc) in a 40 x 40 roi.
ProbeRender DiscRender(int contact_radius) {
  ProbeRender r;
  r.roi = cv::Rect(100, 50, 40, 40);
  r.contact = cv::Mat(r.roi.size(), CV_8U, cv::Scalar::all(0));
  r.gx = cv::Mat(r.roi.size(), CV_32F, cv::Scalar::all(0));
  r.gy = r.gx.clone();
  r.rho = cv::Mat(r.roi.size(), CV_64F, cv::Scalar::all(12.0));
  r.rho.at<double>(0, 0) = std::nan("");  // one pixel not visible
  for (int y = 0; y < 40; ++y) {
    for (int x = 0; x < 40; ++x) {
      if ((x - 20) * (x - 20) + (y - 20) * (y - 20) <= contact_radius * contact_radius) {
        r.contact.at<std::uint8_t>(y, x) = 255;
        r.gx.at<float>(y, x) = static_cast<float>(x - 20) / 10.0f;
        r.gy.at<float>(y, x) = static_cast<float>(y - 20) / 10.0f;
        ++r.contact_pixels;
      }
    }
  }
  return r;
}
}  // namespace

TEST_CASE("dataset: contact pixels capped, about 25% non-contact, targets from the render",
          "[calib][dataset]") {
  cv::Mat diff(240, 320, CV_32FC3, cv::Scalar(0.1f, 0.2f, 0.3f));
  DatasetOptions o;
  o.max_contact_samples_per_probe = 100;
  Dataset d;
  const ProbeRender r = DiscRender(12);  // ~450 contact pixels
  const std::size_t n = AppendProbeSamples(diff, r, 42, o, &d);
  int contact = 0;
  for (auto c : d.contact) contact += c;
  CHECK(contact == 100);
  CHECK(n == d.probe.size());
  CHECK(static_cast<double>(n - 100) / static_cast<double>(n) == Approx(0.25).margin(0.01));
  for (std::size_t i = 0; i < n; ++i) {
    const auto c = static_cast<Eigen::Index>(i);
    const int x = static_cast<int>(d.x(0, c)) - r.roi.x, y = static_cast<int>(d.x(1, c)) - r.roi.y;
    CHECK(d.probe[i] == 42);
    // Features are (u, v, R, G, B): the difference image is B, G, R.
    CHECK(d.x(2, c) == Approx(0.3f));
    CHECK(d.x(4, c) == Approx(0.1f));
    if (d.contact[i]) {
      CHECK(r.contact.at<std::uint8_t>(y, x) == 255);
      CHECK(d.y(0, c) == r.gx.at<float>(y, x));
    } else {
      CHECK(r.contact.at<std::uint8_t>(y, x) == 0);
      CHECK_FALSE((x == 0 && y == 0));  // the invisible pixel is never used
      CHECK(d.y(0, c) == 0.0f);
    }
  }
  // Too little contact: nothing.
  CHECK(AppendProbeSamples(diff, DiscRender(1), 43, o, &d) == 0);
  // Deterministic per (seed, probe).
  Dataset again;
  AppendProbeSamples(diff, r, 42, o, &again);
  CHECK(again.x == d.x.leftCols(again.x.cols()));
}

TEST_CASE("dataset: the split is by probe, seeded, with every split non-empty",
          "[calib][dataset]") {
  std::vector<std::int32_t> probes;
  for (int i = 0; i < 200; ++i) probes.push_back(i * 3);
  DatasetOptions o;
  const auto a = SplitProbes(probes, o);
  const auto b = SplitProbes(probes, o);
  CHECK(a == b);
  int counts[3] = {0, 0, 0};
  for (Split s : a) ++counts[static_cast<int>(s)];
  CHECK(counts[1] == 20);
  CHECK(counts[2] == 20);
  o.seed = 2;
  CHECK(SplitProbes(probes, o) != a);
  // A probe's split depends on the probe, not on its neighbours in the list: dropping one
  // probe (a pose change that empties one render) moves at most one probe per boundary, and
  // the order of the list does not matter at all.
  std::vector<std::int32_t> fewer = probes;
  fewer.erase(fewer.begin() + 17);
  const auto c = SplitProbes(fewer, DatasetOptions{});
  int moved = 0;
  for (std::size_t i = 0; i < fewer.size(); ++i) moved += c[i] != a[i < 17 ? i : i + 1];
  CHECK(moved <= 2);
  std::vector<std::int32_t> reversed(probes.rbegin(), probes.rend());
  const auto r = SplitProbes(reversed, DatasetOptions{});
  for (std::size_t i = 0; i < probes.size(); ++i) CHECK(r[probes.size() - 1 - i] == a[i]);
  const std::vector<std::int32_t> three = {5, 6, 7};
  const auto s3 = SplitProbes(three, DatasetOptions{});
  CHECK(std::set<Split>(s3.begin(), s3.end()).size() == 3);

  // Samples of one probe never land in two splits.
  cv::Mat diff(240, 320, CV_32FC3, cv::Scalar::all(0.05f));
  Dataset d;
  for (int p = 0; p < 30; ++p) AppendProbeSamples(diff, DiscRender(8), p, DatasetOptions{}, &d);
  for (int p = 0; p < 30; ++p) d.probes.push_back(p);
  d.probe_split = SplitProbes(d.probes, DatasetOptions{});
  const std::size_t total =
      d.Count(Split::kTrain) + d.Count(Split::kValidation) + d.Count(Split::kTest);
  CHECK(total == d.probe.size());
  const auto test = d.ProbesIn(Split::kTest);
  const Eigen::MatrixXf xt = d.X(Split::kTest);
  CHECK(static_cast<std::size_t>(xt.cols()) == d.Count(Split::kTest));
  CHECK_FALSE(test.empty());
}

TEST_CASE("dataset: binary round trip, corruption refused", "[calib][dataset]") {
  cv::Mat diff(240, 320, CV_32FC3, cv::Scalar(0.1f, -0.2f, 0.3f));
  Dataset d;
  for (int p = 0; p < 5; ++p) AppendProbeSamples(diff, DiscRender(9), p, DatasetOptions{}, &d);
  d.probes = {0, 1, 2, 3, 4};
  d.probe_split = SplitProbes(d.probes, DatasetOptions{});
  const auto bytes = d.Serialize();
  const Dataset e = Dataset::Deserialize(bytes);
  CHECK(e.x == d.x);
  CHECK(e.y == d.y);
  CHECK(e.probe == d.probe);
  CHECK(e.contact == d.contact);
  CHECK(e.probe_split == d.probe_split);
  auto bad = bytes;
  bad[bad.size() / 2] ^= 1;
  CHECK_THROWS_WITH(Dataset::Deserialize(bad), Catch::Contains("checksum"));
  std::vector<std::uint8_t> cut(bytes.begin(), bytes.begin() + 30);
  CHECK_THROWS_AS(Dataset::Deserialize(cut), std::runtime_error);
}

TEST_CASE("dataset: pixels near the rigid imprint's edge are left out when asked",
          "[calib][dataset]") {
  cv::Mat diff(240, 320, CV_32FC3, cv::Scalar(0.1f, 0.2f, 0.3f));
  const ProbeRender r = DiscRender(12);
  // Penetration: 0.1 mm per pixel from the disc's edge (+ inside, - outside).
  cv::Mat pen(r.roi.size(), CV_32F);
  for (int y = 0; y < 40; ++y)
    for (int x = 0; x < 40; ++x)
      pen.at<float>(y, x) =
          0.1f * (12.0f - std::hypot(static_cast<float>(x - 20), static_cast<float>(y - 20)));
  DatasetOptions o;
  o.max_contact_samples_per_probe = 1000;
  o.small_probe_repeat = 1;  // counts pixels, not samples
  o.edge_exclusion_mm = 0.25;
  Dataset d;
  const std::size_t n = AppendProbeSamples(diff, r, 7, o, &d, pen);
  REQUIRE(n > 0);
  int contact = 0;
  for (std::size_t i = 0; i < n; ++i) {
    const auto c = static_cast<Eigen::Index>(i);
    const int x = static_cast<int>(d.x(0, c)) - r.roi.x, y = static_cast<int>(d.x(1, c)) - r.roi.y;
    CHECK(std::abs(pen.at<float>(y, x)) >= 0.25f);
    contact += d.contact[i];
  }
  // Contact pixels at least 2.5 px inside the 12 px disc: radius <= 9.5, about 280 of ~450.
  CHECK(contact < r.contact_pixels * 3 / 4);
  CHECK(contact > r.contact_pixels / 2);
  // Without the penetration map the option is an error, not a silent no-op.
  Dataset e;
  CHECK_THROWS_AS(AppendProbeSamples(diff, r, 7, o, &e), std::invalid_argument);
  o.edge_exclusion_mm = 3.0;
  CHECK_THROWS_WITH(o.Check(), Catch::Contains("edge_exclusion_mm"));
}

TEST_CASE("dataset: context features follow the pixel's colour, and survive the round trip",
          "[calib][dataset]") {
  cv::Mat diff(240, 320, CV_32FC3);
  for (int v = 0; v < diff.rows; ++v) {
    for (int u = 0; u < diff.cols; ++u) {
      diff.at<cv::Vec3f>(v, u) = cv::Vec3f(0.001f * u, 0.002f * v, 0.003f * (u + v));
    }
  }
  const ProbeRender r = DiscRender(9);
  const cv::Mat context = ContextFeatures(diff, cv::Mat(), r.roi, {2.0});
  Dataset d;
  REQUIRE(AppendProbeSamples(diff, r, 7, DatasetOptions{}, &d, cv::Mat(), context) > 0);
  REQUIRE(d.x.rows() == kFeatureCount + kContextFeatureCount);
  for (Eigen::Index c = 0; c < d.x.cols(); ++c) {
    const int u = static_cast<int>(d.x(0, c)), v = static_cast<int>(d.x(1, c));
    const float* f = context.ptr<float>(v - r.roi.y) + (u - r.roi.x) * context.channels();
    for (int k = 0; k < kContextFeatureCount; ++k) CHECK(d.x(kFeatureCount + k, c) == f[k]);
    CHECK(d.x(5, c) == Approx(0.003).margin(1e-5));  // dR/du
    CHECK(d.x(8, c) == Approx(0.002).margin(1e-5));  // dG/dv
  }
  // One dataset, one feature layout.
  CHECK_THROWS_WITH(AppendProbeSamples(diff, r, 8, DatasetOptions{}, &d),
                    Catch::Contains("features per sample"));
  CHECK_THROWS_WITH(
      AppendProbeSamples(diff, r, 8, DatasetOptions{}, &d, cv::Mat(), cv::Mat(3, 3, CV_32FC(6))),
      Catch::Contains("roi's size"));
  d.probes = {7};
  d.probe_split = {Split::kTrain};
  const Dataset e = Dataset::Deserialize(d.Serialize());
  CHECK(e.x == d.x);

  // A version-1 artifact (before the feature count was stored: always 5 rows) still loads.
  Dataset plain;
  AppendProbeSamples(diff, r, 7, DatasetOptions{}, &plain);
  plain.probes = {7};
  plain.probe_split = {Split::kTrain};
  std::vector<std::uint8_t> v1 = plain.Serialize();
  v1.resize(v1.size() - 8);                    // drop the checksum
  v1.erase(v1.begin() + 28, v1.begin() + 32);  // magic 8, version 4, n 8, np 8, then rows
  const std::uint32_t one = 1;
  std::memcpy(v1.data() + 8, &one, 4);
  const std::uint64_t sum = Hasher().Add(v1.data(), v1.size()).Digest();
  v1.insert(v1.end(), reinterpret_cast<const std::uint8_t*>(&sum),
            reinterpret_cast<const std::uint8_t*>(&sum) + 8);
  const Dataset old = Dataset::Deserialize(v1);
  CHECK(old.x == plain.x);
  CHECK(old.probe == plain.probe);
}

TEST_CASE("dataset: the sample budget lowers the per-probe cap for large runs only",
          "[calib][dataset]") {
  DatasetOptions o;
  o.max_contact_samples_per_probe = 250;
  o.non_contact_fraction = 0.25;
  o.max_samples = 1'200'000;
  CHECK(o.ContactSamplesPerProbe(2000) == 250);     // 2,000 probes: untouched
  CHECK(o.ContactSamplesPerProbe(10000) == 90);     // 1.2M * 0.75 / 10,000
  CHECK(o.ContactSamplesPerProbe(100000000) == 1);  // never below one
  o.max_samples = 0;
  CHECK(o.ContactSamplesPerProbe(10000) == 250);
  o.max_samples = -1;
  CHECK_THROWS_WITH(o.Check(), Catch::Contains("max_samples"));
}

TEST_CASE("dataset: a small imprint's samples are repeated, up to the cap and every pixel alike",
          "[calib][dataset]") {
  cv::Mat diff(240, 320, CV_32FC3, cv::Scalar(0.1f, 0.2f, 0.3f));
  const ProbeRender small = DiscRender(5);  // 81 contact pixels
  REQUIRE(small.contact_pixels == 81);
  DatasetOptions o;
  o.max_contact_samples_per_probe = 500;
  auto contact_counts = [&](const DatasetOptions& opt, const ProbeRender& r) {
    Dataset d;
    AppendProbeSamples(diff, r, 7, opt, &d);
    std::map<std::pair<int, int>, int> seen;
    int other = 0;
    for (std::size_t i = 0; i < d.probe.size(); ++i) {
      const auto c = static_cast<Eigen::Index>(i);
      if (d.contact[i]) {
        ++seen[{static_cast<int>(d.x(0, c)), static_cast<int>(d.x(1, c))}];
      } else {
        ++other;
      }
    }
    return std::make_pair(seen, other);
  };
  o.small_probe_repeat = 1;
  const auto [once, other_once] = contact_counts(o, small);
  CHECK(once.size() == 81);
  for (const auto& [px, n] : once) CHECK(n == 1);
  o.small_probe_repeat = 4;
  const auto [four, other_four] = contact_counts(o, small);
  CHECK(four.size() == 81);
  for (const auto& [px, n] : four) CHECK(n == 4);
  // The non-contact share stays about a quarter of the probe's samples.
  CHECK(static_cast<double>(other_four) / (other_four + 4 * 81) == Approx(0.25).margin(0.01));
  CHECK(other_four > other_once);
  // Near the cap: repeated only up to it, no pixel more than once beyond the others.
  o.max_contact_samples_per_probe = 100;
  const auto [capped, other_capped] = contact_counts(o, small);
  int total = 0;
  for (const auto& [px, n] : capped) {
    total += n;
    CHECK(n >= 1);
    CHECK(n <= 2);
  }
  CHECK(total == 100);
  // A large imprint is unchanged by the option.
  DatasetOptions large = o;
  large.small_probe_repeat = 1;
  CHECK(contact_counts(o, DiscRender(12)).first == contact_counts(large, DiscRender(12)).first);
  DatasetOptions bad;
  bad.small_probe_repeat = 0;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("small_probe_repeat"));
}
