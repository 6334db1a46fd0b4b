// Frames at their edges, through the run-time Reconstructor and calibration's impression finder:
// saturated, black, pure noise, heavy sensor noise, the wrong size.

#include <cmath>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "calib/impression_centroid.h"
#include "capture/impression.h"
#include "recon/contacts.h"
#include "recon/model_bundle.h"
#include "recon/reconstructor.h"
#include "stress/stress_cases.h"

namespace gs360::stress {
namespace {

const ModelBundle& Model(const StressContext& c) {
  if (!c.model) throw std::invalid_argument("no model given (StressContext.model)");
  return *c.model;
}

// What a reconstruction holds: regions, reported contacts, non-finite values at visible pixels,
// and the deepest indentation.
struct Summary {
  int regions = 0, contacts = 0, nonfinite = 0;
  double peak_mm = 0.0;
  std::string Text() const {
    return Format("%d regions, %d contacts reported, peak %.3f mm, %d non-finite depths", regions,
                  contacts, peak_mm, nonfinite);
  }
};

Summary Summarize(const Reconstructor& r, const FrameReconstruction& f) {
  Summary s;
  s.regions = static_cast<int>(f.regions.size());
  s.contacts = static_cast<int>(SummarizeContacts(r, f).size());
  for (const RegionReconstruction& region : f.regions) {
    const cv::Rect& roi = region.region.roi;
    for (int y = 0; y < roi.height; ++y) {
      for (int x = 0; x < roi.width; ++x) {
        if (!r.map().visible(roi.x + x, roi.y + y)) continue;
        const double h = region.indentation.at<double>(y, x);
        if (!std::isfinite(h)) {
          ++s.nonfinite;
        } else {
          s.peak_mm = std::max(s.peak_mm, h);
        }
      }
    }
  }
  return s;
}

// A frame that is not a tactile image at all must give no contact: the reconstruction refuses it
// (an error naming the problem) or reports nothing. A frame no camera on a working sensor gives
// (black, saturated) must be refused: "no contact" from a dead camera would mislead a robot.
StressCase Unusable(const std::string& what, std::function<cv::Mat(const cv::Mat&, int)> make,
                    bool must_refuse) {
  return {"frames", what + " frame against the model's reference",
          must_refuse ? "refused with the reason (not \"no contact\")"
                      : "refused with the reason, or no contact reported; never a non-finite depth",
          [make, must_refuse](const StressContext& c, std::string* observed) {
            const ModelBundle& m = Model(c);
            const Reconstructor r = m.MakeReconstructor(1);
            const cv::Mat frame = make(m.reference, static_cast<int>(c.seed));
            try {
              const FrameReconstruction f = r.Reconstruct(frame);
              const Summary s = Summarize(r, f);
              *observed = f.problem.empty() ? s.Text() : "refused: " + f.problem;
              if (must_refuse && f.problem.empty()) return false;
              return s.contacts == 0 && s.nonfinite == 0;
            } catch (const std::invalid_argument& e) {
              *observed = std::string("std::invalid_argument: ") + e.what();
              return true;
            }
          }};
}

cv::Mat Constant(const cv::Mat& reference, double value) {
  return cv::Mat(reference.size(), CV_8UC3, cv::Scalar::all(value));
}

cv::Mat UniformNoise(const cv::Mat& reference, int seed) {
  cv::Mat out(reference.size(), CV_8UC3);
  cv::RNG rng(static_cast<std::uint64_t>(seed));
  rng.fill(out, cv::RNG::UNIFORM, 0, 256);
  return out;
}

// The reference with Gaussian noise of sigma DN per channel (a camera at high gain).
cv::Mat Noisy(const cv::Mat& reference, int seed, double sigma) {
  cv::Mat noise(reference.size(), CV_32FC3), out;
  cv::RNG rng(static_cast<std::uint64_t>(seed));
  rng.fill(noise, cv::RNG::NORMAL, 0.0, sigma);
  cv::Mat ref32;
  reference.convertTo(ref32, CV_32FC3);
  cv::Mat sum = ref32 + noise;
  sum.convertTo(out, CV_8UC3);
  return out;
}

// Sensor noise on a frame without contact, added to the model's own reference, so that the
// difference holds exactly this noise. On the virtual rig a live frame differs from the
// reference by about 3.5 DN: the frame's 3 DN (read noise 1 DN, shot noise about 2.7 DN at
// mid-grey) and the reference's 1.7 DN (a mean of 3 frames).
StressCase Noise(double sigma, bool must_hold) {
  return {"frames", Format("no contact, sensor noise of %.0f DN per pixel", sigma),
          must_hold ? "no contact reported, no depth beyond 0.05 mm"
                    : "measured: phantom contacts (a limit); never a non-finite depth",
          [sigma, must_hold](const StressContext& c, std::string* observed) {
            const ModelBundle& m = Model(c);
            const Reconstructor r = m.MakeReconstructor(1);
            Summary worst;
            int refused = 0;
            for (int i = 0; i < 20; ++i) {
              const FrameReconstruction f =
                  r.Reconstruct(Noisy(m.reference, static_cast<int>(c.seed) + i, sigma));
              refused += f.problem.empty() ? 0 : 1;
              const Summary s = Summarize(r, f);
              worst.regions = std::max(worst.regions, s.regions);
              worst.contacts += s.contacts;
              worst.nonfinite += s.nonfinite;
              worst.peak_mm = std::max(worst.peak_mm, s.peak_mm);
            }
            *observed = Format("20 frames (%d refused): ", refused) + worst.Text();
            const bool clean = worst.contacts == 0 && worst.nonfinite == 0 && worst.peak_mm <= 0.05;
            return must_hold ? clean : worst.nonfinite == 0;
          },
          !must_hold};
}

StressCase WrongSize() {
  return {"frames", "a 320 x 240 frame for a 640 x 480 model",
          "std::invalid_argument naming the sizes",
          [](const StressContext& c, std::string* observed) {
            const Reconstructor r = Model(c).MakeReconstructor(1);
            try {
              r.Reconstruct(cv::Mat(240, 320, CV_8UC3, cv::Scalar::all(100)));
              *observed = "no error";
              return false;
            } catch (const std::invalid_argument& e) {
              *observed = e.what();
              return std::string(e.what()).find("320") != std::string::npos;
            }
          }};
}

// The impression finders (resume's, capture/impression.h, and calibration's, calib/
// impression_centroid.h) on a press frame that is not a press: each must say "no impression"
// rather than hand pose estimation a centre.
StressCase NoImpression(const std::string& what, std::function<cv::Mat(const cv::Mat&, int)> make) {
  return {"frames", "impression finders: " + what + " press frame",
          "no impression found by either (the probe is dropped, not fitted)",
          [make](const StressContext& c, std::string* observed) {
            const cv::Mat& reference = Model(c).reference;
            const cv::Mat press = make(reference, static_cast<int>(c.seed));
            const auto resume = FindImpression(press, reference);
            const auto calibration = FindImpressionRegion(press, reference);
            *observed = resume ? Format("resume's finder: an impression at (%.1f, %.1f), %d px",
                                        resume->centroid.x(), resume->centroid.y(), resume->pixels)
                               : "resume's finder: none";
            *observed += calibration ? Format(
                                           "; calibration's: an impression at (%.1f, %.1f), "
                                           "%d px",
                                           calibration->centroid.x(), calibration->centroid.y(),
                                           calibration->pixels)
                                     : "; calibration's: none";
            return !resume && !calibration;
          }};
}

}  // namespace

std::vector<StressCase> FrameCases() {
  const auto saturated = [](const cv::Mat& ref, int) { return Constant(ref, 255); };
  const auto black = [](const cv::Mat& ref, int) { return Constant(ref, 0); };
  return {Unusable("a saturated (all 255)", saturated, true),
          Unusable("a black (all 0)", black, true),
          Unusable("a uniform noise", UniformNoise, false),
          Noise(3.0, true),
          Noise(4.0, false),
          Noise(6.0, false),
          WrongSize(),
          NoImpression("a saturated", saturated),
          NoImpression("a black", black),
          NoImpression("a uniform noise", UniformNoise)};
}

}  // namespace gs360::stress
