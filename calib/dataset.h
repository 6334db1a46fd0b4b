#pragma once
// Calibration stage 5, "dataset": training samples from the captured probes.
//
// For each probe whose rigid render (calib/render.h) has contact, the normalised difference of
// its press frame against the reference frame nearest in time (recon/features.h) gives, per
// pixel, the MLP's input (u, v, f_R, f_G, f_B, then the context features when the caller passes
// them: recon/features.h PixelFeatures); the render gives
// the target slopes (gx, gy). Samples: the probe's contact pixels (at most
// max_contact_samples_per_probe, a seeded random subset: neighbouring pixels are nearly
// redundant) plus non-contact pixels of the probe's ROI, about non_contact_fraction of all of
// the probe's samples (target slopes 0: they teach the model where nothing touches).
// Probes are split train / validation / test BY PROBE (ranked by a seeded hash of the plan
// index, so a probe's split does not depend on which other probes are present), never by pixel.
//
// The matrices are column-major, one sample per column: x [features, n], y [2, n], where
// features is kFeatureCount, plus kContextFeatureCount with context features.

#include <Eigen/Core>
#include <cstdint>
#include <span>
#include <vector>

#include <opencv2/core/mat.hpp>

#include "calib/render.h"

namespace gs360 {

enum class Split : std::uint8_t { kTrain = 0, kValidation = 1, kTest = 2 };

struct DatasetOptions {
  // >= 1. Capped further by max_samples: about 450 on 2,000 probes, 90 on 10,000. Raising the
  // cap from 250 lowered the validation loss and the depth error on the 2,000-probe cylinder
  // (figures in docs/benchmarks.md, "Calibration", session 5 steps).
  int max_contact_samples_per_probe = 500;
  // Budget for the whole dataset (contact and non-contact samples; 0 = none): with many probes
  // the per-probe cap drops to ContactSamplesPerProbe() so that training time stays bounded.
  // More probes with fewer pixels each beat fewer probes with more (neighbouring pixels are
  // nearly redundant). The default keeps 10,000 probes within the time target (training time
  // in docs/benchmarks.md, "Calibration").
  std::int64_t max_samples = 1'200'000;
  double non_contact_fraction = 0.25;  // [0, 0.9]
  int min_contact_pixels = 8;          // probes with fewer rendered contact pixels are left out
  double validation_fraction = 0.1;    // of the probes
  double test_fraction = 0.1;          // of the probes (held out for the validate stage)
  std::uint64_t seed = 1;
  // Pixels whose rigid penetration along the normal (calib/render.h NormalPenetration) is within
  // this of zero are left out, inside and outside the imprint: a real gel rounds the imprint's
  // edge off over a fraction of a millimetre, so there the rigid render's slopes (steepest just
  // inside, zero just outside) contradict what the camera sees, and fitting them pulls every
  // prediction toward the mean. 0 keeps every pixel. [0, 2] mm.
  double edge_exclusion_mm = 0.0;
  // A probe with fewer contact pixels than the cap (an imprint seen small: far from the camera,
  // or at a steep view angle) has its samples repeated up to this many times, not beyond the
  // cap, so that it weighs in training nearer to what it weighs in validation (one probe, one
  // peak). 1 = every pixel once. [1, 16].
  int small_probe_repeat = 2;
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("max_contact_samples_per_probe", self.max_contact_samples_per_probe);
    visit("max_samples", self.max_samples);
    visit("non_contact_fraction", self.non_contact_fraction);
    visit("min_contact_pixels", self.min_contact_pixels);
    visit("validation_fraction", self.validation_fraction);
    visit("test_fraction", self.test_fraction);
    visit("seed", self.seed);
    visit("edge_exclusion_mm", self.edge_exclusion_mm);
    visit("small_probe_repeat", self.small_probe_repeat);
  }
  void Check() const;  // throws std::invalid_argument naming the field and value
  // The contact-sample cap per probe for a dataset of `probes` probes with contact:
  // max_contact_samples_per_probe, lowered (not below 1) so that about max_samples samples result.
  int ContactSamplesPerProbe(std::size_t probes) const;
};

struct Dataset {
  Eigen::MatrixXf x;                  // [features, n] (recon/features.h PixelFeatures)
  Eigen::MatrixXf y;                  // [2, n]
  std::vector<std::int32_t> probe;    // per sample: the probe's plan index
  std::vector<std::uint8_t> contact;  // per sample: 1 = contact pixel
  std::vector<std::int32_t> probes;   // plan indices of the probes used
  std::vector<Split> probe_split;     // per entry of `probes`

  // Columns of one split.
  Eigen::MatrixXf X(Split s) const;
  Eigen::MatrixXf Y(Split s) const;
  std::vector<std::int32_t> ProbesIn(Split s) const;
  std::size_t Count(Split s) const;

  // Binary form (versioned, checksummed); Deserialize throws std::runtime_error naming the fault.
  std::vector<std::uint8_t> Serialize() const;
  static Dataset Deserialize(std::span<const std::uint8_t> bytes);
};

// Samples of one probe: `diff` is the full-image normalised difference (CV_32FC3, B G R),
// `render` the probe's rigid render. Appends to `out` (x, y, probe, contact); returns the number
// of samples added (0 when the render has fewer than min_contact_pixels). Deterministic for
// (options.seed, plan_index). `penetration`: the render roi's NormalPenetration (CV_32F,
// roi-sized), needed when options.edge_exclusion_mm > 0 (std::invalid_argument if missing or
// of the wrong size). `context`: empty, or the render roi's recon/features.h ContextFeatures;
// every call on one dataset must agree (std::invalid_argument otherwise).
std::size_t AppendProbeSamples(const cv::Mat& diff, const ProbeRender& render, int plan_index,
                               const DatasetOptions& options, Dataset* out,
                               const cv::Mat& penetration = cv::Mat(),
                               const cv::Mat& context = cv::Mat());

// Seeded split of plan indices into train / validation / test: the probes ranked by a hash of
// (plan index, seed), the first test_fraction to test, the next validation_fraction to
// validation. Independent of the list's order. Every split gets at least one probe when there
// are >= 3 probes.
std::vector<Split> SplitProbes(std::span<const std::int32_t> probes, const DatasetOptions& options);

}  // namespace gs360
