#pragma once
// What the model sees of a tactile frame: the normalised colour difference against a no-contact
// reference frame, and the regions where something touches the gel.
//
// Normalised difference, per pixel and channel c (B, G, R as stored by OpenCV):
//   f_c = (I_c - g_c R_c) / (g_c R_c + floor_dn)
// with I the frame, R the reference (both 8-bit), and g_c a per-channel gain that absorbs the
// slow LED drift between the two frames: the median of I_c / R_c over valid pixels whose
// reference is bright enough (contacts cover a small part of the image, so the median is the
// background's ratio). The ratio form also cancels vignetting and the LEDs' fall-off with
// distance, which differ across the image by 10x; floor_dn keeps dark pixels (the tip in red and
// green) from dividing noise by nothing.
//
// The MLP's input for pixel (u, v) is (u, v, f_R, f_G, f_B): kFeatureCount = 5, in that order.
// With DifferenceOptions::context_sigmas_px, six context features per scale follow
// (FeatureCount()): the image gradient of f smoothed at that scale,
// (df_R/du, df_R/dv, df_G/du, df_G/dv, df_B/du, df_B/dv), scales in the order given.
// Why: near the sensor's tip the LEDs light the gel symmetrically, so a pixel's colour says how
// much the gel tilts but hardly which way; which way the colour change grows across the image
// (outward from an imprint's centre) says it.

#include <opencv2/core/mat.hpp>
#include <vector>

namespace gs360 {

constexpr int kFeatureCount = 5;         // u, v, f_R, f_G, f_B
constexpr int kContextFeatureCount = 6;  // per scale: d/du, d/dv of f_R, f_G, f_B

struct DifferenceOptions {
  double floor_dn = 30.0;               // added to the denominator (DN, > 0)
  bool compensate_gain = true;          // estimate g_c from the frame; otherwise g = 1
  double gain_min_reference_dn = 40.0;  // pixels used for the gain: reference above this
  int gain_stride = 4;                  // sample every n-th pixel in u and v for the median
  // Gaussian smoothing of f over valid pixels (normalised convolution, so masked pixels do not
  // pull their neighbours toward 0); 0 = none. Shot and read noise are per pixel, the imprint's
  // colour changes spread over many pixels.
  double smooth_sigma_px = 1.0;
  // Scales (px) of the context features (the gradient of f smoothed by a Gaussian of each sigma,
  // over valid pixels); empty = no context features. Each in (0, 20], at most 4. Three octaves
  // from the imprint's edge to its size: they cut the MLP's validation loss and depth error
  // markedly (figures in docs/benchmarks.md, "Calibration", session 5 steps).
  std::vector<double> context_sigmas_px = {1.5, 4.0, 10.0};
  // Throws std::invalid_argument naming the field and its value.
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("floor_dn", self.floor_dn);
    visit("compensate_gain", self.compensate_gain);
    visit("gain_min_reference_dn", self.gain_min_reference_dn);
    visit("gain_stride", self.gain_stride);
    visit("smooth_sigma_px", self.smooth_sigma_px);
    visit("context_sigmas_px", self.context_sigmas_px);
  }
  void Check() const;
};

// frame, reference: CV_8UC3 of one size; valid: empty or CV_8U of that size (non-zero = use).
// Returns CV_32FC3 (B, G, R order like the input); 0 outside `valid`. Throws
// std::invalid_argument for mismatched inputs.
// `gain_in`, when given, is used instead of estimating g from these images (a window of a frame
// whose gain was estimated over all of it: EstimateGain).
cv::Mat NormalizedDifference(const cv::Mat& frame, const cv::Mat& reference, const cv::Mat& valid,
                             const DifferenceOptions& options = {}, cv::Vec3d* gain_out = nullptr,
                             const cv::Vec3d* gain_in = nullptr);
// The per-channel gain g of NormalizedDifference (1 without compensate_gain). Same inputs.
cv::Vec3d EstimateGain(const cv::Mat& frame, const cv::Mat& reference, const cv::Mat& valid,
                       const DifferenceOptions& options = {});

// The MLP's input size for these options: kFeatureCount + kContextFeatureCount per context scale.
int FeatureCount(const DifferenceOptions& options);

// Context features over `roi` (inside the image): CV_32FC(6 * sigmas_px.size()), roi-sized; per
// scale, the central difference of f smoothed by a Gaussian of that sigma (normalised
// convolution over `valid`, so the fins and the image circle's edge do not read as a change), in
// units of f per pixel, channel order as documented above (R first). diff: CV_32FC3 (B G R);
// valid: empty or CV_8U of the image size. Reads the image within about 3 sigma of the roi.
// Empty sigmas: an empty Mat. Throws std::invalid_argument for mismatched inputs or a sigma
// outside (0, 20].
cv::Mat ContextFeatures(const cv::Mat& diff, const cv::Mat& valid, const cv::Rect& roi,
                        const std::vector<double>& sigmas_px);

// Writes pixel (u, v)'s MLP input to out[0 .. kFeatureCount + context.channels()): u, v, f_R,
// f_G, f_B, then the context features. context: empty or ContextFeatures() of a roi that holds
// (u, v), whose top-left corner is `roi_origin`.
void PixelFeatures(const cv::Mat& diff, const cv::Mat& context, cv::Point roi_origin, int u, int v,
                   float* out);

struct ContactDetectionOptions {
  double blur_sigma_px = 1.5;   // smoothing of the difference magnitude
  double threshold = 0.06;      // |f| (norm over channels) above this is a change
  int min_area_px = 12;         // smaller blobs are noise
  double grow_fraction = 0.35;  // ROI = blob box grown by this fraction of its size per side
  int grow_px = 6;              // plus this many pixels per side
  int max_regions = 16;         // largest first
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("blur_sigma_px", self.blur_sigma_px);
    visit("threshold", self.threshold);
    visit("min_area_px", self.min_area_px);
    visit("grow_fraction", self.grow_fraction);
    visit("grow_px", self.grow_px);
    visit("max_regions", self.max_regions);
  }
  void Check() const;
};

struct ContactRegion {
  cv::Rect blob;  // the changed pixels' bounding box
  cv::Rect roi;   // the region to reconstruct (blob grown, clipped to the image)
  int area_px = 0;
  double peak = 0.0;  // largest smoothed |f|
};

// Regions of change in a normalised difference (CV_32FC3), largest first; empty = no contact.
std::vector<ContactRegion> DetectContactRegions(const cv::Mat& normalized_difference,
                                                const ContactDetectionOptions& options = {});

}  // namespace gs360
