#include "calib/report.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <limits>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>
#include <string_view>

#include "base/base64.h"
#include "base/format.h"

namespace gs360 {
namespace {

using Json = nlohmann::json;
constexpr double kRadToDeg = 180.0 / 3.14159265358979323846;
const char* const kBands[] = {"all",        "height:base", "height:middle",
                              "height:tip", "view:<30",    "view:30-50",
                              "view:>50",   "fins:near",   "fins:far"};
constexpr int kExamplePixels = 160;  // examples are upscaled to about this size

// ---- text helpers ----

std::string Escape(std::string_view s) {
  std::string out;
  out.reserve(s.size());
  for (char c : s) {
    switch (c) {
      case '&':
        out += "&amp;";
        break;
      case '<':
        out += "&lt;";
        break;
      case '>':
        out += "&gt;";
        break;
      case '"':
        out += "&quot;";
        break;
      case '\'':
        out += "&#39;";
        break;
      default:
        out += c;
    }
  }
  return out;
}

std::string Fixed(double v, int decimals) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), "%.*f", decimals, v);
  return buf;
}

const Json* Find(const Json& j, std::string_view key) {
  if (!j.is_object()) return nullptr;
  const auto it = j.find(key);
  return it == j.end() ? nullptr : &*it;
}

// A JSON number as text ("-" when missing, null or not a number); integers stay integers.
std::string Num(const Json* v, int decimals) {
  if (v == nullptr || !v->is_number()) return "-";
  if (v->is_number_integer()) return std::to_string(v->get<long long>());
  const double d = v->get<double>();
  return std::isfinite(d) ? Fixed(d, decimals) : "-";
}

std::string PadLeft(const std::string& s, std::size_t w) {
  return s.size() >= w ? s : std::string(w - s.size(), ' ') + s;
}
std::string PadRight(const std::string& s, std::size_t w) {
  return s.size() >= w ? s : s + std::string(w - s.size(), ' ');
}

// ---- the validation table (shared by text and HTML) ----

struct Table {
  std::string truth;
  std::vector<std::pair<std::string, std::array<std::string, 6>>> rows;  // band, cells
};
const std::array<const char*, 6> kColumnTop = {"pixels", "mean mm", "mean mm",
                                               "p95 mm", "normal",  "peak mm"};

std::vector<Table> BuildTables(const Json& validation, std::string* primary_out) {
  std::vector<Table> tables;
  const Json* results = Find(validation, "results");
  if (results == nullptr || !results->is_object()) return tables;
  std::string primary = "discontinuity";
  if (const Json* m = Find(validation, "default_method"); m != nullptr && m->is_string())
    primary = m->get<std::string>();
  const std::string secondary = primary == "poisson" ? "discontinuity" : "poisson";
  *primary_out = primary;

  std::vector<std::string> truths;
  if (const Json* t = Find(validation, "truths"); t != nullptr && t->is_array()) {
    for (const Json& name : *t)
      if (name.is_string()) truths.push_back(name.get<std::string>());
  } else {
    for (const auto& [name, unused] : results->items()) truths.push_back(name);
  }
  for (const std::string& truth : truths) {
    const Json* per_truth = Find(*results, truth);
    if (per_truth == nullptr) continue;
    const Json* a = Find(*per_truth, primary);
    const Json* b = Find(*per_truth, secondary);
    std::vector<std::string> bands(std::begin(kBands), std::end(kBands));
    for (const Json* method : {a, b}) {  // bands beyond the known ones go last
      if (method == nullptr || !method->is_object()) continue;
      for (const auto& [band, unused] : method->items())
        if (std::find(bands.begin(), bands.end(), band) == bands.end()) bands.push_back(band);
    }
    Table table{truth, {}};
    for (const std::string& band : bands) {
      const Json* ra = a != nullptr ? Find(*a, band) : nullptr;
      const Json* rb = b != nullptr ? Find(*b, band) : nullptr;
      const Json null_json;
      const Json& ja = ra != nullptr ? *ra : null_json;
      const Json& jb = rb != nullptr ? *rb : null_json;
      table.rows.push_back(
          {band,
           {Num(Find(ja, "pixels"), 0), Num(Find(ja, "mean_mm"), 4), Num(Find(jb, "mean_mm"), 4),
            Num(Find(ja, "p95_mm"), 4), Num(Find(ja, "median_normal_deg"), 2),
            Num(Find(ja, "peak_error_mm"), 4)}});
    }
    tables.push_back(std::move(table));
  }
  return tables;
}

std::string MethodShort(const std::string& m) {
  if (m == "discontinuity") return "disc.";
  if (m == "heightfield") return "hfield";
  return m.substr(0, 7);
}

std::string SummaryLine(const Json& v) {
  std::string s = "probes: " + Num(Find(v, "probes_evaluated"), 0) + " evaluated of " +
                  Num(Find(v, "probes_held_out"), 0) + " held out, " +
                  Num(Find(v, "probes_missed"), 0) + " missed; contact pixels " +
                  Num(Find(v, "contact_pixels"), 0) + " (" +
                  Num(Find(v, "contact_pixels_outside_roi"), 0) + " outside the ROI)";
  const Json* dropped = Find(v, "probes_dropped");
  if (dropped != nullptr && dropped->is_object()) {
    s += "; left out of the dataset: " + Num(Find(*dropped, "no_contact_seen"), 0) +
         " (no contact seen by the camera) and " +
         Num(Find(*dropped, "below_min_contact_pixels"), 0) + " (fewer than " +
         Num(Find(*dropped, "min_contact_pixels"), 0) + " contact pixels) of " +
         Num(Find(v, "probes_captured"), 0) + " captured";
  }
  return s;
}

std::string TimingLine(const Json& v) {
  const Json* ms = Find(v, "ms_per_probe");
  if (ms == nullptr || !ms->is_object() || ms->empty()) return {};
  std::string s = "ms per probe:";
  for (const auto& [name, value] : ms->items()) s += " " + name + " " + Num(&value, 2);
  return s;
}

}  // namespace

std::string FormatIntrinsics(const Json& metrics) {
  const Json* lens = Find(metrics, "intrinsics");
  if (lens == nullptr || !lens->is_object()) return {};
  const Json* source = Find(metrics, "source");
  std::string s =
      "intrinsics: fx " + Num(Find(*lens, "fx"), 2) + ", fy " + Num(Find(*lens, "fy"), 2) +
      ", cx " + Num(Find(*lens, "cx"), 2) + ", cy " + Num(Find(*lens, "cy"), 2) + " px (" +
      (source != nullptr && source->is_string() ? source->get<std::string>() : "?") + ")\n";
  if (Find(metrics, "rms_px") == nullptr) return s;
  s += "  RMS " + Num(Find(metrics, "rms_px"), 3) + " px over " +
       Num(Find(metrics, "images_used"), 0) + " images (" +
       Num(Find(metrics, "images_rejected"), 0) + " rejected), radial coverage " +
       Num(Find(metrics, "radial_coverage"), 2) + "\n";
  const Json* images = Find(metrics, "images");
  if (images == nullptr || !images->is_array()) return s;
  for (const Json& image : *images) {
    const Json* file = Find(image, "file");
    const Json* used = Find(image, "used");
    const Json* reason = Find(image, "reason");
    s += "  " + PadRight(file != nullptr && file->is_string() ? file->get<std::string>() : "?", 20);
    if (used != nullptr && used->is_boolean() && used->get<bool>()) {
      s += PadLeft(Num(Find(image, "corners"), 0), 4) + " corners, RMS " +
           Num(Find(image, "rms_px"), 3) + " px\n";
    } else {
      s += "rejected: " +
           (reason != nullptr && reason->is_string() ? reason->get<std::string>() : "?") + "\n";
    }
  }
  return s;
}

namespace {

std::string PoseLine(const Json& v) {
  const Json* pose = Find(v, "pose");
  if (pose == nullptr || !pose->is_object()) return {};
  std::string s = "pose: rms " + Num(Find(*pose, "rms_px"), 3) + " px, inliers " +
                  Num(Find(*pose, "inliers"), 0) + ", outliers " + Num(Find(*pose, "outliers"), 0);
  if (Find(*pose, "error_mm") != nullptr || Find(*pose, "error_deg") != nullptr)
    s += ", error " + Num(Find(*pose, "error_mm"), 3) + " mm " + Num(Find(*pose, "error_deg"), 3) +
         " deg";
  if (Find(*pose, "paper_error_mm") != nullptr || Find(*pose, "paper_error_deg") != nullptr) {
    const std::string paper = "(paper's method " + Num(Find(*pose, "paper_error_mm"), 3) + " mm " +
                              Num(Find(*pose, "paper_error_deg"), 3) + " deg)";
    s += (s.size() + 1 + paper.size() <= 100 ? " " : "\n      ") + paper;  // <= 100 columns
  }
  return s;
}

// ---- colours, images ----

struct Rgb {
  int r, g, b;
};

// Viridis, piecewise linear through five anchors; t in [0, 1] (clamped; NaN -> grey).
Rgb Viridis(double t) {
  static constexpr double kAnchors[5][3] = {
      {68, 1, 84}, {59, 82, 139}, {33, 145, 140}, {94, 201, 98}, {253, 231, 37}};
  if (!std::isfinite(t)) return {128, 128, 128};
  t = std::clamp(t, 0.0, 1.0) * 4.0;
  const int i = std::min(3, static_cast<int>(t));
  const double f = t - i;
  auto mix = [&](int c) {
    return static_cast<int>(std::lround(kAnchors[i][c] * (1.0 - f) + kAnchors[i + 1][c] * f));
  };
  return {mix(0), mix(1), mix(2)};
}

std::string Hex(Rgb c) {
  char buf[8];
  std::snprintf(buf, sizeof(buf), "#%02x%02x%02x", c.r, c.g, c.b);
  return buf;
}

// An <img> with the image (8-bit, 1 or 3 channels) as a PNG data URI, upscaled with
// nearest-neighbour to about kExamplePixels; "" when the image cannot be encoded.
std::string ImgTag(const cv::Mat& image, const std::string& alt) {
  if (image.empty() || image.depth() != CV_8U || (image.channels() != 1 && image.channels() != 3))
    return {};
  const int factor = std::clamp(
      static_cast<int>(std::lround(double{kExamplePixels} / std::max(image.rows, image.cols))), 1,
      16);
  cv::Mat big;
  cv::resize(image, big, cv::Size(), factor, factor, cv::INTER_NEAREST);
  std::vector<unsigned char> png;
  if (!cv::imencode(".png", big, png)) return {};
  return "<img alt=\"" + Escape(alt) + "\" width=\"" + std::to_string(big.cols) + "\" height=\"" +
         std::to_string(big.rows) + "\" src=\"data:image/png;base64," + Base64Encode(png) + "\">";
}

// A CV_32F / CV_64F single-channel map as BGR false colour on [lo, hi]; empty if mistyped.
cv::Mat FalseColour(const cv::Mat& map, double lo, double hi) {
  if (map.empty() || map.channels() != 1 || (map.depth() != CV_64F && map.depth() != CV_32F))
    return {};
  cv::Mat d;
  map.convertTo(d, CV_64F);
  cv::Mat out(d.size(), CV_8UC3);
  for (int y = 0; y < d.rows; ++y)
    for (int x = 0; x < d.cols; ++x) {
      const Rgb c = Viridis((d.at<double>(y, x) - lo) / (hi - lo));
      out.at<cv::Vec3b>(y, x) =
          cv::Vec3b(static_cast<uchar>(c.b), static_cast<uchar>(c.g), static_cast<uchar>(c.r));
    }
  return out;
}

// Finite range of the maps usable by FalseColour; false when none has a finite value.
bool MapRange(const std::vector<const cv::Mat*>& maps, double* lo, double* hi) {
  *lo = std::numeric_limits<double>::infinity();
  *hi = -std::numeric_limits<double>::infinity();
  for (const cv::Mat* m : maps) {
    if (m->empty() || m->channels() != 1 || (m->depth() != CV_64F && m->depth() != CV_32F))
      continue;
    cv::Mat d;
    m->convertTo(d, CV_64F);
    for (auto it = d.begin<double>(); it != d.end<double>(); ++it)
      if (std::isfinite(*it)) *lo = std::min(*lo, *it), *hi = std::max(*hi, *it);
  }
  if (!std::isfinite(*lo)) return false;
  *lo = std::min(*lo, 0.0);
  if (*hi - *lo < 1e-6) *hi = *lo + 1e-6;
  return true;
}

// A horizontal colour bar (inline SVG) labelled lo .. hi.
std::string ColourBar(const std::string& id, double lo, double hi, const std::string& unit,
                      bool clamped_top) {
  std::ostringstream s;
  s << "<svg width=\"240\" height=\"34\" role=\"img\"><defs><linearGradient id=\"" << id << "\">";
  for (int i = 0; i <= 4; ++i)
    s << "<stop offset=\"" << i * 25 << "%\" stop-color=\"" << Hex(Viridis(i / 4.0)) << "\"/>";
  s << "</linearGradient></defs><rect x=\"10\" y=\"2\" width=\"220\" height=\"12\" fill=\"url(#"
    << id << ")\"/><text x=\"10\" y=\"28\" font-size=\"11\">" << Fixed(lo, 3)
    << "</text><text x=\"230\" y=\"28\" font-size=\"11\" text-anchor=\"end\">"
    << (clamped_top ? "&ge;" : "") << Fixed(hi, 3) << " " << Escape(unit) << "</text></svg>";
  return s.str();
}

// ---- page sections ----

std::string StageTable(const Json& stages) {
  if (!stages.is_array() || stages.empty()) return {};
  std::ostringstream s;
  s << "<h2>Stages</h2>\n<table><tr><th>stage</th><th>cached</th><th>seconds</th>"
       "<th>metrics</th></tr>\n";
  for (const Json& st : stages) {
    if (!st.is_object()) continue;
    const Json* name = Find(st, "stage");
    const Json* cached = Find(st, "cached");
    std::string metrics;
    if (const Json* m = Find(st, "metrics"); m != nullptr && m->is_object()) {
      Json few = Json::object();  // the first scalar metrics
      for (const auto& [k, v] : m->items())
        if (v.is_primitive() && few.size() < 8) few[k] = v;
      metrics = few.dump(-1, ' ', false, Json::error_handler_t::replace);
      if (metrics.size() > 240) metrics = metrics.substr(0, 237) + "...";
    }
    s << "<tr><td>" << Escape(name != nullptr && name->is_string() ? name->get<std::string>() : "?")
      << "</td><td>"
      << (cached != nullptr && cached->is_boolean() ? (cached->get<bool>() ? "yes" : "no") : "-")
      << "</td><td class=\"n\">" << Num(Find(st, "seconds"), 2) << "</td><td><code>"
      << Escape(metrics) << "</code></td></tr>\n";
  }
  s << "</table>\n";
  return s.str();
}

// "pass", "no data" (a band no held-out probe fell in) or `fail`.
std::string Verdict(const Json& target, const char* fail) {
  if (target.value("no_data", false)) return "no data";
  return target.value("pass", false) ? "pass" : fail;
}

// The accuracy targets, pass or fail, and the warnings the pipeline attached.
std::string TargetsSection(const Json& validation) {
  std::ostringstream s;
  s << "<h3>targets</h3>\n<table><tr><th>figure</th><th>value</th><th>target</th><th></th></tr>\n";
  for (const Json& t : ValidationTargets(validation)) {
    const std::string unit = t.value("unit", std::string());
    s << "<tr><td>" << Escape(t.value("name", std::string())) << " ("
      << Escape(t.value("truth", "")) << ")</td><td class=\"n\">"
      << (t["value"].is_number() ? FormatFixed(t["value"].get<double>(), 4) + " " + unit : "-")
      << "</td><td class=\"n\">&lt;= " << FormatFixed(t.value("target", 0.0), 3) << " " << unit
      << "</td><td>" << Verdict(t, "<b>FAIL</b>") << "</td></tr>\n";
  }
  s << "</table>\n";
  const Json* warnings = Find(validation, "warnings");
  if (warnings != nullptr && warnings->is_array() && !warnings->empty()) {
    s << "<h3>warnings</h3>\n<ul>\n";
    for (const Json& w : *warnings) {
      if (w.is_object()) s << "<li>" << Escape(w.value("message", std::string())) << "</li>\n";
    }
    s << "</ul>\n";
  }
  return s.str();
}

std::string ValidationSection(const Json& validation) {
  if (!validation.is_object() || validation.empty()) return {};
  std::ostringstream s;
  s << "<h2>Validation</h2>\n<p>" << Escape(SummaryLine(validation)) << "</p>\n";
  if (const Json* d = Find(validation, "truth_description");
      d != nullptr && d->is_string() && !d->get<std::string>().empty())
    s << "<p>physical truth: " << Escape(d->get<std::string>()) << "</p>\n";
  std::string primary;
  for (const Table& t : BuildTables(validation, &primary)) {
    const std::string p = MethodShort(primary);
    const std::string q = MethodShort(primary == "poisson" ? "discontinuity" : "poisson");
    s << "<h3>truth: " << Escape(t.truth) << "</h3>\n<table><tr><th>band</th><th>pixels</th>"
      << "<th>mean mm (" << Escape(p) << ")</th><th>mean mm (" << Escape(q) << ")</th>"
      << "<th>p95 mm (" << Escape(p) << ")</th><th>median normal deg (" << Escape(p)
      << ")</th><th>peak error mm (" << Escape(p) << ")</th></tr>\n";
    for (const auto& [band, cells] : t.rows) {
      s << "<tr><td>" << Escape(band) << "</td>";
      for (const std::string& c : cells) s << "<td class=\"n\">" << Escape(c) << "</td>";
      s << "</tr>\n";
    }
    s << "</table>\n";
  }
  if (const std::string pose = PoseLine(validation); !pose.empty())
    s << "<p>" << Escape(pose) << "</p>\n";
  if (const std::string timing = TimingLine(validation); !timing.empty())
    s << "<p>" << Escape(timing) << "</p>\n";
  s << TargetsSection(validation);
  return s.str();
}

std::string CurveSvg(const std::vector<TrainEpoch>& curve) {
  double lo = std::numeric_limits<double>::infinity(), hi = 0.0;
  int e0 = std::numeric_limits<int>::max(), e1 = std::numeric_limits<int>::min();
  for (const TrainEpoch& e : curve)
    for (double v : {e.train_loss, e.val_loss})
      if (std::isfinite(v) && v > 0.0) {
        lo = std::min(lo, v), hi = std::max(hi, v);
        e0 = std::min(e0, e.epoch), e1 = std::max(e1, e.epoch);
      }
  if (!std::isfinite(lo)) return {};
  const int d0 = static_cast<int>(std::floor(std::log10(lo)));
  const int d1 = std::max(d0 + 1, static_cast<int>(std::ceil(std::log10(hi))));
  if (e1 == e0) e1 = e0 + 1;
  constexpr double kW = 640, kH = 300, kL = 64, kR = 110, kT = 16, kB = 40;
  auto px = [&](double epoch) { return kL + (epoch - e0) / (e1 - e0) * (kW - kL - kR); };
  auto py = [&](double v) { return kT + (d1 - std::log10(v)) / (d1 - d0) * (kH - kT - kB); };
  std::ostringstream s;
  s << "<h2>Training curve</h2>\n<svg width=\"" << kW << "\" height=\"" << kH
    << "\" role=\"img\" font-size=\"11\">\n<rect x=\"" << kL << "\" y=\"" << kT << "\" width=\""
    << kW - kL - kR << "\" height=\"" << kH - kT - kB << "\" fill=\"none\" stroke=\"#888\"/>\n";
  const int dstep = std::max(1, (d1 - d0 + 5) / 6);
  for (int d = d0; d <= d1; d += dstep) {
    const double y = py(std::pow(10.0, d));
    s << "<line x1=\"" << kL << "\" x2=\"" << kW - kR << "\" y1=\"" << y << "\" y2=\"" << y
      << "\" stroke=\"#ddd\"/><text x=\"" << kL - 4 << "\" y=\"" << y + 4
      << "\" text-anchor=\"end\">1e" << d << "</text>\n";
  }
  const int estep = std::max(1, (e1 - e0 + 7) / 8);
  for (int e = e0; e <= e1; e += estep)
    s << "<text x=\"" << px(e) << "\" y=\"" << kH - kB + 14 << "\" text-anchor=\"middle\">" << e
      << "</text>\n";
  s << "<text x=\"" << (kL + kW - kR) / 2 << "\" y=\"" << kH - 6
    << "\" text-anchor=\"middle\">epoch</text>\n<text x=\"12\" y=\"" << (kT + kH - kB) / 2
    << "\" transform=\"rotate(-90 12 " << (kT + kH - kB) / 2
    << ")\" text-anchor=\"middle\">loss (normalised MSE, log scale)</text>\n";
  const char* const kColours[] = {"#1f77b4", "#ff7f0e"};
  const char* const kNames[] = {"train", "validation"};
  for (int series = 0; series < 2; ++series) {
    s << "<polyline fill=\"none\" stroke=\"" << kColours[series] << "\" stroke-width=\"1.5\" "
      << "points=\"";
    for (const TrainEpoch& e : curve) {
      const double v = series == 0 ? e.train_loss : e.val_loss;
      if (std::isfinite(v) && v > 0.0) s << px(e.epoch) << "," << py(v) << " ";
    }
    s << "\"/>\n<line x1=\"" << kW - kR + 10 << "\" x2=\"" << kW - kR + 30 << "\" y1=\""
      << kT + 10 + 16 * series << "\" y2=\"" << kT + 10 + 16 * series << "\" stroke=\""
      << kColours[series] << "\" stroke-width=\"2\"/><text x=\"" << kW - kR + 34 << "\" y=\""
      << kT + 14 + 16 * series << "\">" << kNames[series] << "</text>\n";
  }
  s << "</svg>\n";
  return s.str();
}

// Fields of a gap object, with a fallback for anything missing or mistyped (the report never
// throws).
double GapNumber(const Json& g, const char* key) {
  const Json* v = g.is_object() && g.contains(key) ? &g[key] : nullptr;
  return v != nullptr && v->is_number() ? v->get<double>() : 0.0;
}
std::string GapText(const Json& g) {
  return g.is_object() && g.contains("text") && g["text"].is_string() ? g["text"].get<std::string>()
                                                                      : std::string("?");
}

// The plan's unprobed parts as hatched rectangles (`px`, `py` map azimuth and height to the
// map), each with its text as a tooltip; a range across +-180 deg is drawn as two.
template <typename Px, typename Py>
std::string CoverageGapRects(const Json& gaps, Px px, Py py) {
  std::ostringstream s;
  if (!gaps.is_array()) return {};
  for (const Json& g : gaps) {
    if (!g.is_object()) continue;
    const double z0 = GapNumber(g, "z_min_mm"), z1 = GapNumber(g, "z_max_mm");
    double a0 = GapNumber(g, "azimuth_min_deg"), a1 = GapNumber(g, "azimuth_max_deg");
    if (g.is_object() && g.contains("all_around") && g["all_around"] == true) a0 = -180, a1 = 180;
    std::vector<std::pair<double, double>> spans = {{a0, a1}};
    if (a1 < a0) spans = {{a0, 180.0}, {-180.0, a1}};
    for (const auto& [lo, hi] : spans) {
      s << "<rect x=\"" << px(lo) << "\" y=\"" << py(z1) << "\" width=\"" << px(hi) - px(lo)
        << "\" height=\"" << py(z0) - py(z1)
        << "\" fill=\"url(#unprobed)\" stroke=\"#b33\" stroke-width=\"0.5\"><title>not probed: "
        << Escape(GapText(g)) << "</title></rect>\n";
    }
  }
  return s.str();
}

std::string ErrorMapSvg(const std::vector<std::pair<Eigen::Vector3d, double>>& probes,
                        double gel_height_mm, double clamp_mm, const Json& gaps) {
  if (probes.empty()) return {};
  if (!(gel_height_mm > 0.0) || !std::isfinite(gel_height_mm)) gel_height_mm = 1.0;
  if (!(clamp_mm > 0.0) || !std::isfinite(clamp_mm)) clamp_mm = 0.1;
  constexpr double kW = 720, kH = 330, kL = 50, kR = 20, kT = 16, kB = 76;
  auto px = [&](double deg) { return kL + (deg + 180.0) / 360.0 * (kW - kL - kR); };
  auto py = [&](double z) {
    return kT + (1.0 - std::clamp(z / gel_height_mm, 0.0, 1.0)) * (kH - kT - kB);
  };
  std::ostringstream s;
  s << "<h2>Error map over the sensor</h2>\n<svg width=\"" << kW << "\" height=\"" << kH
    << "\" role=\"img\" font-size=\"11\">\n<defs><linearGradient id=\"errmap\">";
  for (int i = 0; i <= 4; ++i)
    s << "<stop offset=\"" << i * 25 << "%\" stop-color=\"" << Hex(Viridis(i / 4.0)) << "\"/>";
  s << "</linearGradient><pattern id=\"unprobed\" patternUnits=\"userSpaceOnUse\" width=\"6\" "
    << "height=\"6\" patternTransform=\"rotate(45)\"><line x1=\"0\" y1=\"0\" x2=\"0\" y2=\"6\" "
    << "stroke=\"#c44\" stroke-width=\"2\"/></pattern></defs>\n<rect x=\"" << kL << "\" y=\"" << kT
    << "\" width=\"" << kW - kL - kR << "\" height=\"" << kH - kT - kB
    << "\" fill=\"#f4f4f4\" stroke=\"#888\"/>\n";
  s << CoverageGapRects(gaps, px, py);
  for (int deg = -180; deg <= 180; deg += 90)
    s << "<text x=\"" << px(deg) << "\" y=\"" << kH - kB + 14 << "\" text-anchor=\"middle\">" << deg
      << "</text>\n";
  for (int k = 0; k <= 3; ++k) {  // the height bands' boundaries
    const double z = gel_height_mm * k / 3.0, y = py(z);
    if (k > 0 && k < 3)
      s << "<line x1=\"" << kL << "\" x2=\"" << kW - kR << "\" y1=\"" << y << "\" y2=\"" << y
        << "\" stroke=\"#bbb\" stroke-dasharray=\"4 3\"/>\n";
    s << "<text x=\"" << kL - 4 << "\" y=\"" << y + 4 << "\" text-anchor=\"end\">" << Fixed(z, 1)
      << "</text>\n";
  }
  s << "<text x=\"" << (kL + kW - kR) / 2 << "\" y=\"" << kH - kB + 30
    << "\" text-anchor=\"middle\">azimuth atan2(y, x) (deg)</text>\n<text x=\"12\" y=\""
    << (kT + kH - kB) / 2 << "\" transform=\"rotate(-90 12 " << (kT + kH - kB) / 2
    << ")\" text-anchor=\"middle\">height z (mm)</text>\n";
  for (const auto& [p, err] : probes) {
    if (!p.allFinite()) continue;
    const double az = std::atan2(p.y(), p.x()) * kRadToDeg;
    s << "<circle cx=\"" << px(az) << "\" cy=\"" << py(p.z()) << "\" r=\"3.5\" fill=\""
      << Hex(Viridis(err / clamp_mm)) << "\"><title>az " << Fixed(az, 1) << " deg, z "
      << Fixed(p.z(), 2) << " mm: " << (std::isfinite(err) ? Fixed(err, 4) + " mm" : "no data")
      << "</title></circle>\n";
  }
  const double ly = kH - 30;
  s << "<rect x=\"" << kL << "\" y=\"" << ly << "\" width=\"240\" height=\"12\" "
    << "fill=\"url(#errmap)\"/><text x=\"" << kL << "\" y=\"" << ly + 26 << "\">0</text><text x=\""
    << kL + 120 << "\" y=\"" << ly + 26 << "\" text-anchor=\"middle\">" << Fixed(clamp_mm / 2, 3)
    << "</text><text x=\"" << kL + 240 << "\" y=\"" << ly + 26 << "\" text-anchor=\"end\">&ge;"
    << Fixed(clamp_mm, 3) << "</text><text x=\"" << kL + 250 << "\" y=\"" << ly + 10
    << "\">mean depth error per probe (mm); grey: no data"
    << (gaps.is_array() && !gaps.empty() ? "; hatched: not probed" : "") << "</text>\n";
  s << "</svg>\n";
  if (gaps.is_array() && !gaps.empty()) {
    s << "<p>Not probed, so the model has not learnt these parts:</p>\n<ul>\n";
    for (const Json& g : gaps) {
      if (g.is_object()) s << "<li>" << Escape(GapText(g)) << "</li>\n";
    }
    s << "</ul>\n";
  }
  return s.str();
}

std::string ExamplesSection(const std::vector<ValidationExample>& examples) {
  if (examples.empty()) return {};
  std::ostringstream s;
  s << "<h2>Examples</h2>\n";
  int index = 0;
  for (const ValidationExample& ex : examples) {
    double lo = 0.0, hi = 0.0;
    const bool has_range = MapRange(
        {&ex.truth_depth, &ex.recon_depth, &ex.poisson_depth, &ex.physical_depth}, &lo, &hi);
    s << "<div class=\"ex\"><h3>probe " << ex.plan_index << "</h3>\n";
    auto figure = [&](const std::string& img, const std::string& caption) {
      s << "<figure>" << (img.empty() ? std::string("<div class=\"na\">n/a</div>") : img)
        << "<figcaption>" << Escape(caption) << "</figcaption></figure>\n";
    };
    figure(ImgTag(ex.frame_roi, "frame"), "frame (crop)");
    const std::string recon_caption = "reconstruction (" + ex.recon_method + ")";
    const std::pair<const cv::Mat*, const char*> maps[] = {
        {&ex.truth_depth, "truth depth (rigid render)"},
        {&ex.recon_depth, recon_caption.c_str()},
        {&ex.poisson_depth, "plain Poisson"},
        {&ex.physical_depth, "|error| vs physical truth"}};
    for (const auto& [map, caption] : maps) {
      if (map->empty() && map == &ex.physical_depth) continue;
      figure(has_range ? ImgTag(FalseColour(*map, lo, hi), caption) : std::string(), caption);
    }
    if (has_range)
      s << "<p>colour scale " << Fixed(lo, 3) << " to " << Fixed(hi, 3) << " mm (shared) "
        << ColourBar("ex" + std::to_string(index), lo, hi, "mm", false) << "</p>\n";
    s << "</div>\n";
    ++index;
  }
  return s.str();
}

}  // namespace

std::string FormatValidationTable(const nlohmann::json& validation) {
  std::ostringstream s;
  s << SummaryLine(validation) << "\n";
  std::string primary;
  const std::vector<Table> tables = BuildTables(validation, &primary);
  const std::array<std::string, 6> bottom = {
      "",
      MethodShort(primary),
      MethodShort(primary == "poisson" ? "discontinuity" : "poisson"),
      MethodShort(primary),
      "deg " + MethodShort(primary),
      MethodShort(primary)};
  constexpr std::array<std::size_t, 6> kWidths = {9, 10, 10, 10, 12, 10};
  for (const Table& t : tables) {
    s << "\ntruth: " << t.truth << "\n" << PadRight("band", 14);
    for (std::size_t c = 0; c < 6; ++c) s << PadLeft(kColumnTop[c], kWidths[c]);
    s << "\n" << PadRight("", 14);
    for (std::size_t c = 0; c < 6; ++c) s << PadLeft(bottom[c], kWidths[c]);
    s << "\n";
    for (const auto& [band, cells] : t.rows) {
      s << PadRight(band, 14);
      for (std::size_t c = 0; c < 6; ++c) s << PadLeft(cells[c], kWidths[c]);
      s << "\n";
    }
  }
  if (tables.empty()) s << "(no validation results)\n";
  if (const std::string pose = PoseLine(validation); !pose.empty()) s << pose << "\n";
  return s.str();
}

Json ValidationTargets(const Json& v) {
  const Json* truths = Find(v, "truths");
  std::string truth = "rigid";
  if (truths != nullptr && truths->is_array()) {
    for (const auto& t : *truths) {
      if (t == "physical") truth = "physical";
    }
  }
  const Json* method = Find(v, "default_method");
  const std::string m = method != nullptr && method->is_string() ? method->get<std::string>()
                                                                 : std::string("heightfield");
  const auto cell = [&](const char* band, const char* key) -> const Json* {
    const Json* results = Find(v, "results");
    if (results == nullptr || !results->contains(truth)) return nullptr;
    const Json& by_method = results->at(truth);
    if (!by_method.contains(m) || !by_method.at(m).contains(band)) return nullptr;
    return Find(by_method.at(m).at(band), key);
  };
  const auto pixels = [&](const char* band) {
    const Json* n = cell(band, "pixels");
    return n != nullptr && n->is_number() ? n->get<double>() : 0.0;
  };
  // A band no held-out pixel fell in while the whole has some (a dome seen face-on has nothing
  // seen past 50 deg): the figure says nothing, which is not a failure.
  const bool validated = pixels("all") > 0.0;
  Json out = Json::array();
  const auto add = [&](const std::string& name, const Json* value, double target, const char* unit,
                       const char* band) {
    const bool known = value != nullptr && value->is_number();
    const bool no_data = !known && band != nullptr && validated && pixels(band) == 0.0;
    out.push_back({{"name", name},
                   {"truth", truth},
                   {"value", known ? *value : Json(nullptr)},
                   {"comparison", "<="},
                   {"target", target},
                   {"unit", unit},
                   {"no_data", no_data},
                   {"pass", no_data || (known && value->get<double>() <= target)}});
  };
  add("mean depth error", cell("all", "mean_mm"), 0.030, "mm", nullptr);
  add("depth error seen > 50 deg", cell("view:>50", "mean_mm"), 0.050, "mm", "view:>50");
  add("peak indentation error", cell("all", "peak_error_mm"), 0.050, "mm", nullptr);
  add("median normal error", cell("all", "median_normal_deg"), 3.0, "deg", nullptr);
  if (truth == "physical") {
    const Json* pose = Find(v, "pose");
    add("camera position", pose != nullptr ? Find(*pose, "error_mm") : nullptr, 0.05, "mm",
        nullptr);
    add("camera rotation", pose != nullptr ? Find(*pose, "error_deg") : nullptr, 0.05, "deg",
        nullptr);
  }
  return out;
}

std::string FormatTargetsAndWarnings(const Json& validation) {
  std::string s = "targets:\n";
  for (const Json& t : ValidationTargets(validation)) {
    const std::string unit = t.value("unit", std::string());
    s += "  " + PadRight(t.value("name", std::string()), 28) +
         PadLeft(t["value"].is_number() ? FormatFixed(t["value"].get<double>(), 4) : "-", 10) +
         " " + PadRight(unit, 4) + " (target <= " + FormatFixed(t.value("target", 0.0), 3) + " " +
         unit + ", " + t.value("truth", std::string()) + " truth)  " + Verdict(t, "FAIL") + "\n";
  }
  const Json* warnings = Find(validation, "warnings");
  if (warnings != nullptr && warnings->is_array()) {
    for (const Json& w : *warnings) {
      if (w.is_object()) s += "warning: " + w.value("message", std::string()) + "\n";
    }
  }
  return s;
}

Json CalibrationWarnings(const Json& validation, const std::vector<TrainEpoch>& curve,
                         std::size_t probes) {
  Json out = Json::array();
  const auto warn = [&](const char* code, const std::string& message) {
    out.push_back({{"code", code}, {"message", message}});
  };
  std::string missed;
  for (const Json& t : ValidationTargets(validation)) {
    if (t.value("pass", false)) continue;
    if (!missed.empty()) missed += "; ";
    missed += t.value("name", std::string()) + " " +
              (t["value"].is_number() ? FormatFixed(t["value"].get<double>(), 3) : "unknown") +
              " (target <= " + FormatFixed(t.value("target", 0.0), 3) + " " +
              t.value("unit", std::string()) + ")";
  }
  if (!missed.empty()) {
    warn("targets", "the model misses accuracy targets: " + missed +
                        ". It is usable, but not as accurate as the rig can give.");
    if (probes < kFewProbes) {
      warn("few_probes", "only " + std::to_string(probes) +
                             " probes trained the model: too few for the targets (on the virtual "
                             "rig about 2,000 meet every one). Run more probes ([plan] "
                             "probe_count), resume the run or start a longer one, and calibrate "
                             "again.");
    }
  }
  const TrainEpoch* best = nullptr;
  for (const TrainEpoch& e : curve) {
    if (std::isfinite(e.val_loss) && (best == nullptr || e.val_loss < best->val_loss)) best = &e;
  }
  if (best != nullptr && best->train_loss > 0.0 &&
      best->val_loss > kOverfitRatio * best->train_loss) {
    warn("overfit", "the network overfits: at its best epoch (" + std::to_string(best->epoch) +
                        ") the validation loss " + FormatFixed(best->val_loss, 4) + " is " +
                        FormatFixed(best->val_loss / best->train_loss, 1) +
                        " times the training loss " + FormatFixed(best->train_loss, 4) +
                        ". It learnt the training probes rather than the sensor: more probes, or "
                        "a smaller network (--hidden), help.");
  }
  const Json* results = Find(validation, "results");
  const Json* method = Find(validation, "default_method");
  const std::string m = method != nullptr && method->is_string() ? method->get<std::string>()
                                                                 : std::string("heightfield");
  const std::string truth = ValidationTargets(validation).empty()
                                ? std::string("rigid")
                                : ValidationTargets(validation)[0].value("truth", "rigid");
  if (results != nullptr && results->is_object() && results->contains(truth) &&
      results->at(truth).contains(m)) {
    const Json& bands = results->at(truth).at(m);
    std::string empty;
    for (const char* band : kValidationBands) {
      const Json* pixels = bands.contains(band) ? Find(bands.at(band), "pixels") : nullptr;
      if (pixels != nullptr && pixels->is_number() && pixels->get<double>() > 0) continue;
      empty += empty.empty() ? band : std::string(", ") + band;
    }
    if (!empty.empty()) {
      warn("empty_band", "no held-out probe fell in " + empty +
                             ": the validation says nothing there. More probes (or a larger "
                             "dataset.test_fraction) put some there.");
    }
  }
  return out;
}

Json ConvergencePoints(const Json& earlier, const Json& validation, std::size_t probes) {
  Json points = Json::array();
  if (earlier.is_array()) {
    for (const Json& p : earlier) {
      if (p.is_object()) points.push_back(p);
    }
  }
  Json own{{"probes", probes}, {"this", true}, {"mean_mm", nullptr}, {"band50_mm", nullptr}};
  bool met = true;
  for (const Json& t : ValidationTargets(validation)) {
    met = met && t.value("pass", false);
    const std::string name = t.value("name", std::string());
    if (name == "mean depth error") own["mean_mm"] = t["value"];
    if (name == "depth error seen > 50 deg") own["band50_mm"] = t["value"];
  }
  own["targets_met"] = met;
  points.push_back(own);
  return points;
}

namespace {

// Validation["convergence"]: mean and > 50 deg errors against probes, the targets drawn in, and
// a table of the points.
std::string ConvergenceSection(const Json& validation) {
  const Json* points = Find(validation, "convergence");
  if (points == nullptr || !points->is_array() || points->empty()) return {};
  double max_probes = 1.0, max_error = 0.06;
  for (const Json& p : *points) {
    if (!p.is_object()) return {};
    max_probes = std::max(max_probes, p.value("probes", 0.0));
    for (const char* key : {"mean_mm", "band50_mm"}) {
      if (p.contains(key) && p[key].is_number())
        max_error = std::max(max_error, p[key].get<double>());
    }
  }
  max_error = std::min(max_error * 1.1, 0.5);
  constexpr double kW = 640, kH = 260, kL = 64, kR = 150, kT = 16, kB = 40;
  auto px = [&](double n) { return kL + n / max_probes * (kW - kL - kR); };
  auto py = [&](double v) {
    return kT + (1.0 - std::min(v, max_error) / max_error) * (kH - kT - kB);
  };
  std::ostringstream s;
  s << "<h2>Error against probes (the run's checkpoints)</h2>\n<svg width=\"" << kW
    << "\" height=\"" << kH << "\" role=\"img\" font-size=\"11\">\n<rect x=\"" << kL << "\" y=\""
    << kT << "\" width=\"" << kW - kL - kR << "\" height=\"" << kH - kT - kB
    << "\" fill=\"none\" stroke=\"#888\"/>\n";
  const char* const kColours[] = {"#1f77b4", "#d62728"};
  const char* const kKeys[] = {"mean_mm", "band50_mm"};
  const char* const kNames[] = {"mean (target 0.030)", "> 50 deg (target 0.050)"};
  const double kTargets[] = {0.030, 0.050};
  for (int series = 0; series < 2; ++series) {
    const double y = py(kTargets[series]);
    s << "<line x1=\"" << kL << "\" x2=\"" << kW - kR << "\" y1=\"" << y << "\" y2=\"" << y
      << "\" stroke=\"" << kColours[series] << "\" stroke-dasharray=\"4 3\"/>\n";
    s << "<polyline fill=\"none\" stroke=\"" << kColours[series]
      << "\" stroke-width=\"1.5\" points=\"";
    for (const Json& p : *points) {
      const Json* v = Find(p, kKeys[series]);
      if (v != nullptr && v->is_number()) s << px(p.value("probes", 0.0)) << "," << py(*v) << " ";
    }
    s << "\"/>\n<line x1=\"" << kW - kR + 10 << "\" x2=\"" << kW - kR + 30 << "\" y1=\""
      << kT + 10 + 16 * series << "\" y2=\"" << kT + 10 + 16 * series << "\" stroke=\""
      << kColours[series] << "\" stroke-width=\"2\"/><text x=\"" << kW - kR + 34 << "\" y=\""
      << kT + 14 + 16 * series << "\">" << kNames[series] << "</text>\n";
  }
  for (int k = 0; k <= 4; ++k) {
    const double v = max_error * k / 4.0;
    s << "<text x=\"" << kL - 4 << "\" y=\"" << py(v) + 4 << "\" text-anchor=\"end\">"
      << Fixed(v, 3) << "</text><text x=\"" << px(max_probes * k / 4.0) << "\" y=\"" << kH - kB + 14
      << "\" text-anchor=\"middle\">" << Fixed(max_probes * k / 4.0, 0) << "</text>\n";
  }
  s << "<text x=\"" << (kL + kW - kR) / 2 << "\" y=\"" << kH - 6
    << "\" text-anchor=\"middle\">probes calibrated on</text>\n<text x=\"12\" y=\""
    << (kT + kH - kB) / 2 << "\" transform=\"rotate(-90 12 " << (kT + kH - kB) / 2
    << ")\" text-anchor=\"middle\">held-out depth error (mm)</text>\n</svg>\n";
  s << "<table><tr><th>probes</th><th>mean mm</th><th>&gt; 50 deg mm</th><th>every target</th>"
       "</tr>\n";
  for (const Json& p : *points) {
    s << "<tr><td class=\"n\">" << Num(Find(p, "probes"), 0)
      << (p.value("this", false) ? " (this model)" : "") << "</td><td class=\"n\">"
      << Num(Find(p, "mean_mm"), 4) << "</td><td class=\"n\">" << Num(Find(p, "band50_mm"), 4)
      << "</td><td>" << (p.value("targets_met", false) ? "met" : "missed") << "</td></tr>\n";
  }
  s << "</table>\n";
  return s.str();
}

}  // namespace

std::string RenderReportHtml(const ReportInputs& inputs) {
  const std::string title = inputs.title.empty() ? "gs360 calibration report" : inputs.title;
  std::ostringstream s;
  s << "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>" << Escape(title)
    << "</title>\n<style>body{font-family:sans-serif;margin:1.5em;color:#222}"
       "table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;"
       "padding:2px 8px}td.n{text-align:right;font-family:monospace}"
       "code{font-size:90%}figure{display:inline-block;margin:4px;vertical-align:top}"
       "figcaption{font-size:80%;max-width:170px}img{image-rendering:pixelated}"
       ".na{width:160px;height:160px;background:#eee}</style></head>\n<body>\n<h1>"
    << Escape(title) << "</h1>\n";
  s << StageTable(inputs.stages);
  s << ValidationSection(inputs.validation);
  s << CurveSvg(inputs.curve);
  s << ConvergenceSection(inputs.validation);
  s << ErrorMapSvg(inputs.probe_errors, inputs.gel_height_mm, inputs.error_map_clamp_mm,
                   inputs.coverage_gaps);
  s << ExamplesSection(inputs.examples);
  s << "</body></html>\n";
  return s.str();
}

}  // namespace gs360
