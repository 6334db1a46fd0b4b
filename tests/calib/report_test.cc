#include "calib/report.h"

#include <catch2/catch.hpp>
#include <cmath>
#include <cstddef>
#include <opencv2/imgcodecs.hpp>
#include <sstream>
#include <string>
#include <vector>

namespace gs360 {
namespace {

using Json = nlohmann::json;

Json SmallValidation() {
  const Json all = {{"pixels", 1200},
                    {"probes", 40},
                    {"mean_mm", 0.0123},
                    {"p95_mm", 0.0456},
                    {"median_normal_deg", 3.21},
                    {"peak_error_mm", 0.0078}};
  const Json tip = {{"pixels", 300},
                    {"probes", 9},
                    {"mean_mm", nullptr},
                    {"p95_mm", nullptr},
                    {"median_normal_deg", nullptr},
                    {"peak_error_mm", nullptr}};
  const Json view = {{"pixels", 800},
                     {"probes", 30},
                     {"mean_mm", 0.0111},
                     {"p95_mm", 0.0333},
                     {"median_normal_deg", 2.5},
                     {"peak_error_mm", nullptr}};
  return Json{
      {"probes_held_out", 50},
      {"probes_evaluated", 40},
      {"probes_missed", 2},
      {"contact_pixels", 12345},
      {"contact_pixels_outside_roi", 7},
      {"truths", {"rigid", "physical"}},
      {"truth_description", "virtual rig <gel>"},
      {"methods", {"discontinuity", "poisson"}},
      {"default_method", "discontinuity"},
      {"results",
       {{"rigid",
         {{"discontinuity", {{"all", all}, {"height:tip", tip}, {"view:<30", view}}},
          {"poisson", {{"all", {{"pixels", 1200}, {"mean_mm", 0.0321}}}}}}},
        {"physical", {{"discontinuity", {{"all", {{"pixels", 1100}, {"mean_mm", 0.0099}}}}}}}}},
      {"ms_per_probe", {{"mlp", 1.5}}},
      {"seconds", 3.0},
      {"pose", {{"rms_px", 0.412}, {"inliers", 412}, {"outliers", 3}}}};
}

std::vector<std::string> Lines(const std::string& text) {
  std::vector<std::string> lines;
  std::istringstream in(text);
  for (std::string line; std::getline(in, line);) lines.push_back(line);
  return lines;
}

std::vector<std::string> Tokens(const std::string& line) {
  std::vector<std::string> tokens;
  std::istringstream in(line);
  for (std::string t; in >> t;) tokens.push_back(t);
  return tokens;
}

// Rows of the table whose first token is `band`, in order of appearance.
std::vector<std::vector<std::string>> Rows(const std::string& table, const std::string& band) {
  std::vector<std::vector<std::string>> rows;
  for (const std::string& line : Lines(table)) {
    const auto t = Tokens(line);
    if (!t.empty() && t[0] == band) rows.push_back(t);
  }
  return rows;
}

std::vector<unsigned char> DecodeBase64(const std::string& s) {
  const std::string alphabet = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  std::vector<unsigned char> out;
  unsigned buffer = 0;
  int bits = 0;
  for (char c : s) {
    if (c == '=') break;
    const auto pos = alphabet.find(c);
    if (pos == std::string::npos) return {};  // not base64: fails the decode below
    buffer = (buffer << 6) | static_cast<unsigned>(pos);
    bits += 6;
    if (bits >= 8) {
      bits -= 8;
      out.push_back(static_cast<unsigned char>((buffer >> bits) & 0xffu));
    }
  }
  return out;
}

// All images embedded as PNG data URIs, decoded.
std::vector<cv::Mat> DecodeImages(const std::string& html) {
  const std::string prefix = "data:image/png;base64,";
  std::vector<cv::Mat> images;
  for (auto pos = html.find(prefix); pos != std::string::npos; pos = html.find(prefix, pos)) {
    pos += prefix.size();
    const auto end = html.find('"', pos);
    REQUIRE(end != std::string::npos);
    const std::vector<unsigned char> png = DecodeBase64(html.substr(pos, end - pos));
    images.push_back(cv::imdecode(png, cv::IMREAD_COLOR));
    REQUIRE_FALSE(images.back().empty());
  }
  return images;
}

std::size_t Count(const std::string& text, const std::string& what) {
  std::size_t n = 0;
  for (auto pos = text.find(what); pos != std::string::npos; pos = text.find(what, pos + 1)) ++n;
  return n;
}

TEST_CASE("FormatValidationTable shows the numbers, '-' for nulls, the pose", "[report]") {
  const std::string table = FormatValidationTable(SmallValidation());
  for (const std::string& line : Lines(table)) CHECK(line.size() <= 100);

  const auto all = Rows(table, "all");
  REQUIRE(all.size() == 2);  // rigid, then physical
  CHECK(all[0] ==
        std::vector<std::string>{"all", "1200", "0.0123", "0.0321", "0.0456", "3.21", "0.0078"});
  CHECK(all[1] == std::vector<std::string>{"all", "1100", "0.0099", "-", "-", "-", "-"});

  const auto tip = Rows(table, "height:tip");
  REQUIRE(tip.size() == 2);
  CHECK(tip[0] == std::vector<std::string>{"height:tip", "300", "-", "-", "-", "-", "-"});
  const auto view = Rows(table, "view:<30");
  REQUIRE(view.size() == 2);
  CHECK(view[0] ==
        std::vector<std::string>{"view:<30", "800", "0.0111", "-", "0.0333", "2.50", "-"});
  // A band missing from the JSON is still a row, all '-'.
  const auto fins = Rows(table, "fins:far");
  REQUIRE(fins.size() == 2);
  CHECK(fins[0] == std::vector<std::string>{"fins:far", "-", "-", "-", "-", "-", "-"});

  // Bands in the documented order, truths in the "truths" order.
  const auto at = [&](const std::string& s) { return table.find(s); };
  CHECK(at("truth: rigid") < at("\nall "));
  CHECK(at("\nall ") < at("\nheight:base "));
  CHECK(at("\nheight:base ") < at("\nheight:tip "));
  CHECK(at("\nheight:tip ") < at("\nview:<30 "));
  CHECK(at("\nview:>50 ") < at("\nfins:near "));
  CHECK(at("\nfins:near ") < at("truth: physical"));
  CHECK(at("40 evaluated of 50 held out, 2 missed") != std::string::npos);

  const auto lines = Lines(table);
  REQUIRE(!lines.empty());
  CHECK(lines.back() == "pose: rms 0.412 px, inliers 412, outliers 3");

  Json with_error = SmallValidation();
  with_error["pose"]["error_mm"] = 0.0216;
  with_error["pose"]["error_deg"] = nullptr;
  CHECK(Lines(FormatValidationTable(with_error)).back() ==
        "pose: rms 0.412 px, inliers 412, outliers 3, error 0.022 mm - deg");
  with_error["pose"]["error_deg"] = 0.0512;
  with_error["pose"]["paper_error_mm"] = 0.0734;
  with_error["pose"]["paper_error_deg"] = 0.2123;
  with_error["pose"]["inliers"] = 1234567;
  const std::string paper = FormatValidationTable(with_error);
  CHECK(paper.find("error 0.022 mm 0.051 deg") != std::string::npos);
  CHECK(paper.find("(paper's method 0.073 mm 0.212 deg)") != std::string::npos);
  for (const std::string& line : Lines(paper)) CHECK(line.size() <= 100);
  Json no_pose = SmallValidation();
  no_pose.erase("pose");
  CHECK(FormatValidationTable(no_pose).find("pose:") == std::string::npos);
}

TEST_CASE("FormatIntrinsics: the lens, the RMS, each image or why it was rejected", "[report]") {
  const Json metrics = {
      {"source", "checkerboards"},
      {"intrinsics", {{"fx", 167.333}, {"fy", 166.826}, {"cx", 320.334}, {"cy", 242.354}}},
      {"rms_px", 0.0619},
      {"images_used", 1},
      {"images_rejected", 1},
      {"radial_coverage", 0.904},
      {"images",
       {{{"file", "board_00.png"}, {"used", true}, {"corners", 54}, {"rms_px", 0.0606}},
        {{"file", "board_01.png"}, {"used", false}, {"reason", "no board found"}}}}};
  const std::string text = FormatIntrinsics(metrics);
  CHECK_THAT(text,
             Catch::Contains("fx 167.33, fy 166.83, cx 320.33, cy 242.35 px (checkerboards)"));
  CHECK_THAT(text, Catch::Contains("RMS 0.062 px over 1 images (1 rejected)"));
  CHECK_THAT(text, Catch::Contains("board_00.png") && Catch::Contains("54 corners, RMS 0.061 px"));
  CHECK_THAT(text, Catch::Contains("board_01.png") && Catch::Contains("rejected: no board found"));
  // The nominal lens: no RMS, no images; nothing at all without intrinsics.
  const std::string nominal = FormatIntrinsics(
      {{"source", "nominal (no checkerboard images given)"}, {"intrinsics", {{"fx", 160.0}}}});
  CHECK_THAT(nominal, Catch::Contains("fx 160.00, fy -") && Catch::Contains("nominal"));
  CHECK(nominal.find("RMS") == std::string::npos);
  CHECK(FormatIntrinsics(Json::object()).empty());
  CHECK(FormatIntrinsics(Json("garbage")).empty());
}

TEST_CASE("RenderReportHtml: title, tables, curve, error map, decodable images", "[report]") {
  ReportInputs in;
  in.title = "run <3> & \"cylinder\"";
  in.validation = SmallValidation();
  in.stages = Json::array({Json{{"stage", "intrinsics"},
                                {"input_hash", "abc"},
                                {"cached", true},
                                {"seconds", 1.5},
                                {"metrics", {{"rms_px", 0.31}, {"note", "a<b"}}}},
                           Json{{"stage", "train"}, {"cached", false}, {"seconds", 20.25}}});
  for (int e = 0; e < 3; ++e) {
    TrainEpoch epoch;
    epoch.epoch = e;
    epoch.train_loss = std::pow(10.0, -e);  // 1, 0.1, 0.01: equal steps on a log axis
    epoch.val_loss = 2.0 * epoch.train_loss;
    in.curve.push_back(epoch);
  }
  in.probe_errors = {{Eigen::Vector3d(5, 0, 10), 0.02},
                     {Eigen::Vector3d(0, 5, 20), 0.5},
                     {Eigen::Vector3d(-5, 0, 25), 0.0}};
  ValidationExample ex;
  ex.plan_index = 17;
  ex.frame_roi = cv::Mat(16, 20, CV_8UC3, cv::Scalar(10, 200, 30));
  ex.truth_depth = cv::Mat(16, 20, CV_64F);
  for (int y = 0; y < 16; ++y)
    for (int x = 0; x < 20; ++x) ex.truth_depth.at<double>(y, x) = 0.5 * x / 19.0;
  ex.recon_depth = 0.5 * ex.truth_depth;
  ex.poisson_depth = cv::Mat(16, 20, CV_64F, cv::Scalar(0.0));
  in.examples.push_back(ex);
  // The plan's unprobed parts (plan/coverage.h): one band all around, one patch across +-180 deg
  // (two rectangles), one malformed entry (left out, no throw).
  in.coverage_gaps = Json::array({Json{{"z_min_mm", 0.0},
                                       {"z_max_mm", 1.5},
                                       {"azimuth_min_deg", -180.0},
                                       {"azimuth_max_deg", 180.0},
                                       {"all_around", true},
                                       {"text", "base <reach>"}},
                                  Json{{"z_min_mm", 27.0},
                                       {"z_max_mm", 29.0},
                                       {"azimuth_min_deg", 150.0},
                                       {"azimuth_max_deg", -150.0},
                                       {"all_around", false},
                                       {"text", "tip"}},
                                  Json("not an object")});

  const std::string html = RenderReportHtml(in);
  const auto count = [&](const std::string& what) {
    int n = 0;
    for (auto at = html.find(what); at != std::string::npos; at = html.find(what, at + 1)) ++n;
    return n;
  };
  CHECK(count("fill=\"url(#unprobed)\"") == 3);
  CHECK(count("<li>") == 2);
  CHECK(count("<title>not probed: tip</title>") == 2);
  CHECK(html.find("<li>base &lt;reach&gt;</li>") != std::string::npos);
  CHECK(html.find("hatched: not probed") != std::string::npos);
  CHECK(html.find("<title>run &lt;3&gt; &amp; &quot;cylinder&quot;</title>") != std::string::npos);
  CHECK(html.find("<h1>run &lt;3&gt; &amp; &quot;cylinder&quot;</h1>") != std::string::npos);
  CHECK(html.find("<3>") == std::string::npos);
  CHECK(html.find("a<b") == std::string::npos);  // metrics are escaped too
  CHECK(html.find("view:&lt;30") != std::string::npos);
  CHECK(html.find("view:<30") == std::string::npos);
  CHECK(html.find("<script") == std::string::npos);
  CHECK(html.find("://") == std::string::npos);  // self-contained: no URLs
  CHECK(html.find("<td>intrinsics</td><td>yes</td>") != std::string::npos);
  CHECK(html.find("<td>train</td><td>no</td>") != std::string::npos);
  CHECK(html.find("rms_px") != std::string::npos);
  CHECK(html.find("<td class=\"n\">0.0123</td>") != std::string::npos);
  CHECK(html.find("pose: rms 0.412 px") != std::string::npos);

  // The curve: two polylines; the train losses 1, 0.1, 0.01 are equally spaced on the log axis.
  CHECK(Count(html, "<svg") >= 2);
  REQUIRE(Count(html, "<polyline") == 2);
  const auto p0 = html.find("points=\"") + 8;
  std::istringstream points(html.substr(p0, html.find('"', p0) - p0));
  std::vector<double> xs, ys;
  for (std::string pt; points >> pt;) {
    const auto comma = pt.find(',');
    xs.push_back(std::stod(pt.substr(0, comma)));
    ys.push_back(std::stod(pt.substr(comma + 1)));
  }
  REQUIRE(ys.size() == 3);
  CHECK(xs[0] < xs[1]);
  CHECK(ys[0] < ys[1]);  // smaller loss lower on the page (larger SVG y)
  CHECK(ys[1] - ys[0] == Approx(ys[2] - ys[1]).margin(0.01));

  // The error map: one dot per probe; 0.5 mm is beyond the clamp (top colour), 0 the bottom.
  CHECK(Count(html, "<circle") == 3);
  CHECK(html.find("fill=\"#fde725\"><title>az 90.0 deg, z 20.00 mm") != std::string::npos);
  CHECK(html.find("fill=\"#440154\"><title>az 180.0 deg, z 25.00 mm") != std::string::npos);

  // The example: frame + truth + reconstruction + Poisson (no physical map), all decodable.
  CHECK(html.find("probe 17") != std::string::npos);
  CHECK(html.find("colour scale 0.000 to 0.500 mm") != std::string::npos);
  const std::vector<cv::Mat> images = DecodeImages(html);
  REQUIRE(images.size() == 4);
  for (const cv::Mat& im : images) {
    CHECK(im.cols == 160);  // 20 px upscaled 8x
    CHECK(im.rows == 128);
  }
  CHECK(images[0].at<cv::Vec3b>(64, 80) == cv::Vec3b(10, 200, 30));
  // One shared scale: the truth's 0.5 mm is the top colour, the reconstruction's 0.25 mm the
  // middle one, 0 the bottom one (BGR).
  CHECK(images[1].at<cv::Vec3b>(0, 159) == cv::Vec3b(37, 231, 253));
  CHECK(images[1].at<cv::Vec3b>(0, 0) == cv::Vec3b(84, 1, 68));
  CHECK(images[2].at<cv::Vec3b>(0, 159) == cv::Vec3b(140, 145, 33));
  CHECK(images[3].at<cv::Vec3b>(100, 100) == cv::Vec3b(84, 1, 68));

  // With a physical error map there is a fifth image.
  in.examples[0].physical_depth = cv::Mat(16, 20, CV_64F, cv::Scalar(0.01));
  CHECK(DecodeImages(RenderReportHtml(in)).size() == 5);
}

TEST_CASE("RenderReportHtml handles empty and malformed inputs", "[report]") {
  ReportInputs empty;
  std::string html;
  REQUIRE_NOTHROW(html = RenderReportHtml(empty));
  CHECK(html.find("<html") != std::string::npos);
  CHECK(html.find("</html>") != std::string::npos);
  CHECK(html.find("<svg") == std::string::npos);
  CHECK(html.find("data:image") == std::string::npos);
  CHECK(FormatValidationTable(Json()).find("(no validation results)") != std::string::npos);

  ReportInputs bad;
  bad.title = "bad";
  bad.validation = "not an object";
  bad.stages = Json{{"stage", 3}};
  TrainEpoch nan_epoch;
  nan_epoch.train_loss = std::nan("");
  nan_epoch.val_loss = -1.0;
  bad.curve = {nan_epoch};
  ValidationExample ex;
  ex.frame_roi = cv::Mat(4, 4, CV_8UC2, cv::Scalar::all(1));
  ex.truth_depth = cv::Mat(4, 4, CV_8U, cv::Scalar::all(1));
  bad.examples.push_back(ex);
  REQUIRE_NOTHROW(html = RenderReportHtml(bad));
  CHECK(html.find("<h1>bad</h1>") != std::string::npos);
  CHECK(html.find("data:image") == std::string::npos);
  CHECK(html.find("<polyline") == std::string::npos);
}

}  // namespace
}  // namespace gs360

namespace gs360 {
namespace {

// A rigid-truth validation whose every band has pixels, at the given figures.
Json BandsValidation(double mean_mm, double wide_mm) {
  Json bands = Json::object();
  for (const char* band : kValidationBands) {
    bands[band] = {{"pixels", 500},
                   {"mean_mm", std::string(band) == "view:>50" ? wide_mm : mean_mm},
                   {"peak_error_mm", 0.02},
                   {"median_normal_deg", 1.5}};
  }
  return Json{{"truths", {"rigid"}},
              {"default_method", "heightfield"},
              {"results", {{"rigid", {{"heightfield", bands}}}}}};
}

std::vector<TrainEpoch> Curve(double train, double val) {
  return {{0, 2 * train, 2 * val, 1.0, 3e-3}, {1, train, val, 1.0, 3e-3}};
}

std::vector<std::string> Codes(const Json& warnings) {
  std::vector<std::string> codes;
  for (const Json& w : warnings) codes.push_back(w.at("code").get<std::string>());
  return codes;
}

}  // namespace

TEST_CASE("calibration warnings: targets missed, too few probes, overfitting, empty bands",
          "[report]") {
  // A good model: no warning.
  CHECK(CalibrationWarnings(BandsValidation(0.02, 0.04), Curve(0.010, 0.012), 2000).empty());

  // The 25-probe demo: misses the targets, overfits (validation 10x training).
  const Json bad = CalibrationWarnings(BandsValidation(0.16, 0.21), Curve(0.002, 0.020), 25);
  CHECK(Codes(bad) == std::vector<std::string>{"targets", "few_probes", "overfit"});
  CHECK_THAT(bad[0]["message"].get<std::string>(),
             Catch::Contains("mean depth error 0.160 (target <= 0.030 mm)") &&
                 Catch::Contains("depth error seen > 50 deg 0.210"));
  CHECK_THAT(bad[1]["message"].get<std::string>(),
             Catch::Contains("only 25 probes") && Catch::Contains("probe_count"));
  CHECK_THAT(bad[2]["message"].get<std::string>(),
             Catch::Contains("10.0 times the training loss") && Catch::Contains("--hidden"));

  // Many probes that still miss: no "few_probes"; a band nobody fell in is named.
  Json v = BandsValidation(0.04, 0.04);
  v["results"]["rigid"]["heightfield"].erase("fins:near");
  v["results"]["rigid"]["heightfield"]["height:tip"]["pixels"] = 0;
  const Json some = CalibrationWarnings(v, Curve(0.01, 0.011), 5000);
  CHECK(Codes(some) == std::vector<std::string>{"targets", "empty_band"});
  CHECK_THAT(some[1]["message"].get<std::string>(),
             Catch::Contains("height:tip, fins:near") && Catch::Contains("test_fraction"));

  // The terminal text and the HTML report carry them.
  v["warnings"] = some;
  const std::string text = FormatTargetsAndWarnings(v);
  CHECK_THAT(text, Catch::Contains("mean depth error") && Catch::Contains("FAIL") &&
                       Catch::Contains("warning: no held-out probe fell in"));
  ReportInputs ri;
  ri.validation = v;
  const std::string html = RenderReportHtml(ri);
  CHECK_THAT(html, Catch::Contains("<h3>targets</h3>") && Catch::Contains("<b>FAIL</b>") &&
                       Catch::Contains("<li>no held-out probe fell in"));
  // The summary counts the probes the dataset left out, by reason.
  v["probes_captured"] = 2000;
  v["probes_dropped"] = {
      {"no_contact_seen", 100}, {"below_min_contact_pixels", 25}, {"min_contact_pixels", 8}};
  CHECK_THAT(FormatValidationTable(v),
             Catch::Contains("left out of the dataset: 100 (no contact seen by the camera) and 25 "
                             "(fewer than 8 contact pixels) of 2000 captured"));
  // Malformed input: never throws.
  CHECK_NOTHROW(CalibrationWarnings(Json("nonsense"), {}, 0));
  CHECK_NOTHROW(FormatTargetsAndWarnings(Json{{"warnings", 3}}));
}

TEST_CASE("a band no held-out probe fell in is no data, not a failed target", "[report]") {
  // A dome seen face-on: nothing past 50 deg, the other figures within their targets.
  Json v = BandsValidation(0.02, 0.04);
  v["results"]["rigid"]["heightfield"]["view:>50"] = {{"pixels", 0}, {"mean_mm", nullptr}};
  const Json targets = ValidationTargets(v);
  REQUIRE(targets.size() == 4);
  CHECK(targets[1]["name"] == "depth error seen > 50 deg");
  CHECK(targets[1]["no_data"] == true);
  CHECK(targets[1]["pass"] == true);
  CHECK(targets[0]["no_data"] == false);
  CHECK(CalibrationWarnings(v, Curve(0.01, 0.011), 2000)[0]["code"] == "empty_band");
  const std::string text = FormatTargetsAndWarnings(v);
  CHECK_THAT(text, Catch::Contains("no data") && !Catch::Contains("FAIL"));
  ReportInputs ri;
  ri.validation = v;
  CHECK_THAT(RenderReportHtml(ri), Catch::Contains("no data") && !Catch::Contains("<b>FAIL</b>"));

  // The band absent altogether is no data too; but a validation with no pixels at all, or a
  // band with pixels and no figure, still fails.
  v["results"]["rigid"]["heightfield"].erase("view:>50");
  CHECK(ValidationTargets(v)[1]["no_data"] == true);
  v["results"]["rigid"]["heightfield"]["view:>50"] = {{"pixels", 40}, {"mean_mm", nullptr}};
  CHECK(ValidationTargets(v)[1]["pass"] == false);
  v["results"]["rigid"]["heightfield"]["all"]["pixels"] = 0;
  v["results"]["rigid"]["heightfield"].erase("view:>50");
  CHECK(ValidationTargets(v)[1]["no_data"] == false);
  CHECK(ValidationTargets(v)[1]["pass"] == false);
}

}  // namespace gs360
