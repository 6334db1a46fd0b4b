// `gs360 bench sweep`'s plot and recommendation, from its CSV rows (cli/bench_sweep.cc has the
// columns): error against total hours (the real rig's machine time plus the calibration), one
// panel per error figure, the target drawn in, the Pareto front marked.

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <map>
#include <string>
#include <vector>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "base/format.h"
#include "calib/stages.h"

namespace gs360::cli {
namespace {

// A row's cells: the eight key columns, then kept, machine_h, acquisition_s, calibration_s, one
// per stage, mean_mm, band50_mm, peak_mm, normal_deg, pose_mm, pose_deg, pass, total_h.
struct Point {
  std::string shape;
  int probes = 0;
  std::string label;  // the training configuration
  double hours = 0, mean = 0, band50 = 0, peak = 0;
  bool pass = false;
};

double Number(const std::vector<std::string>& row, std::size_t i) {
  if (i >= row.size() || row[i].empty()) return std::nan("");
  try {
    return std::stod(row[i]);
  } catch (const std::exception&) {
    return std::nan("");
  }
}

std::vector<Point> Points(const std::vector<std::vector<std::string>>& rows) {
  const std::size_t r = 8 + 4 + CalibrationStages().size();  // index of mean_mm
  std::vector<Point> out;
  for (const auto& row : rows) {
    if (row.size() < r + 8) continue;
    Point p;
    p.shape = row[0];
    p.probes = static_cast<int>(Number(row, 1));
    p.label = row[3] + "x" + row[4] + " " + row[5] + "ep " + row[6] + "px " + row[7];
    p.hours = Number(row, r + 7);
    p.mean = Number(row, r);
    p.band50 = Number(row, r + 1);
    p.peak = Number(row, r + 2);
    p.pass = row[r + 6] == "1";
    if (std::isfinite(p.hours) && p.hours > 0) out.push_back(p);
  }
  return out;
}

cv::Scalar ShapeColour(const std::string& shape) {
  if (shape == "cylinder") return {200, 90, 20};  // BGR
  if (shape == "cone") return {30, 140, 30};
  return {160, 40, 160};
}

struct Panel {
  cv::Rect area;
  double x_lo, x_hi;  // log10 hours
  double y_hi;        // mm (from 0)
  cv::Point At(double hours, double mm) const {
    const double fx = (std::log10(hours) - x_lo) / (x_hi - x_lo);
    const double fy = std::min(mm, y_hi) / y_hi;
    return {area.x + static_cast<int>(fx * area.width),
            area.y + area.height - static_cast<int>(fy * area.height)};
  }
};

void Text(cv::Mat& img, const std::string& s, cv::Point at, double scale = 0.45) {
  cv::putText(img, s, at, cv::FONT_HERSHEY_SIMPLEX, scale, {40, 40, 40}, 1, cv::LINE_AA);
}

void DrawPanel(cv::Mat& img, const Panel& p, const std::vector<Point>& points,
               double Point::*figure, double target, const std::string& title) {
  cv::rectangle(img, p.area, {120, 120, 120}, 1);
  Text(img, title, {p.area.x, p.area.y - 10}, 0.55);
  for (double e = std::floor(p.x_lo); e <= p.x_hi; e += 1.0) {
    for (const double m : {1.0, 2.0, 5.0}) {
      const double h = m * std::pow(10.0, e);
      if (std::log10(h) < p.x_lo || std::log10(h) > p.x_hi) continue;
      const cv::Point at = p.At(h, 0);
      cv::line(img, at, {at.x, p.area.y}, {225, 225, 225}, 1);
      Text(img, FormatFixed(h, h < 1 ? 2 : 0), {at.x - 12, at.y + 18}, 0.4);
    }
  }
  for (int k = 0; k <= 4; ++k) {
    const double mm = p.y_hi * k / 4.0;
    const cv::Point at = p.At(std::pow(10.0, p.x_lo), mm);
    Text(img, FormatFixed(mm, 3), {at.x - 48, at.y + 4}, 0.4);
  }
  Text(img, "total hours (real rig's machine time + calibration), log scale",
       {p.area.x + 40, p.area.y + p.area.height + 38}, 0.4);
  // The target.
  const cv::Point t0 = p.At(std::pow(10.0, p.x_lo), target);
  const cv::Point t1 = p.At(std::pow(10.0, p.x_hi), target);
  for (int x = t0.x; x < t1.x; x += 12) cv::line(img, {x, t0.y}, {x + 6, t0.y}, {40, 40, 220}, 2);
  Text(img, "target " + FormatFixed(target, 3) + " mm", {t1.x - 130, t0.y - 6}, 0.4);
  // Pareto front: no other point both faster and more accurate.
  std::vector<Point> sorted = points;
  std::sort(sorted.begin(), sorted.end(),
            [](const Point& a, const Point& b) { return a.hours < b.hours; });
  std::vector<cv::Point> front;
  double best = 1e300;
  for (const Point& q : sorted) {
    const double v = q.*figure;
    if (std::isfinite(v) && v < best) {
      best = v;
      front.push_back(p.At(q.hours, v));
    }
  }
  if (front.size() > 1) cv::polylines(img, front, false, {60, 60, 60}, 1, cv::LINE_AA);
  for (const Point& q : points) {
    const double v = q.*figure;
    if (!std::isfinite(v)) continue;
    const cv::Point at = p.At(q.hours, v);
    cv::circle(img, at, 5, ShapeColour(q.shape), q.pass ? cv::FILLED : 2, cv::LINE_AA);
  }
}

}  // namespace

void WriteSweepPlot(const std::vector<std::vector<std::string>>& rows,
                    const std::filesystem::path& png) {
  const std::vector<Point> points = Points(rows);
  cv::Mat img(560, 1280, CV_8UC3, cv::Scalar::all(255));
  double h_lo = 1e300, h_hi = 0, mean_hi = 0.06, peak_hi = 0.1;
  for (const Point& q : points) {
    h_lo = std::min(h_lo, q.hours);
    h_hi = std::max(h_hi, q.hours);
    if (std::isfinite(q.mean)) mean_hi = std::max(mean_hi, std::min(q.mean * 1.1, 0.3));
    if (std::isfinite(q.peak)) peak_hi = std::max(peak_hi, std::min(q.peak * 1.1, 0.5));
  }
  if (points.empty()) h_lo = 0.1, h_hi = 10;
  const double x_lo = std::log10(h_lo) - 0.1, x_hi = std::log10(std::max(h_hi, h_lo * 1.5)) + 0.1;
  DrawPanel(img, {{80, 50, 520, 400}, x_lo, x_hi, mean_hi}, points, &Point::mean, 0.030,
            "mean depth error (mm)");
  DrawPanel(img, {{720, 50, 520, 400}, x_lo, x_hi, peak_hi}, points, &Point::peak, 0.050,
            "peak indentation error (mm)");
  int x = 80;
  for (const char* shape : {"cylinder", "cone", "spline"}) {
    cv::circle(img, {x, 536}, 5, ShapeColour(shape), cv::FILLED, cv::LINE_AA);
    Text(img, shape, {x + 10, 541});
    x += 110;
  }
  Text(img, "filled: every target met; ring: a target missed; line: Pareto front", {x + 20, 541});
  std::filesystem::create_directories(std::filesystem::absolute(png).parent_path());
  if (!cv::imwrite(png.string(), img)) throw std::runtime_error("cannot write " + png.string());
}

std::string SweepRecommendation(const std::vector<std::vector<std::string>>& rows) {
  const std::vector<Point> points = Points(rows);
  // Per shape, the fastest configuration that meets every target.
  std::map<std::string, const Point*> fastest;
  for (const Point& q : points) {
    if (!q.pass) continue;
    const Point*& f = fastest[q.shape];
    if (f == nullptr || q.hours < f->hours) f = &q;
  }
  std::string s = "fastest configuration meeting every target, per shape:\n";
  std::map<std::string, bool> seen;
  for (const Point& q : points) seen[q.shape] = true;
  for (const auto& [shape, _] : seen) {
    const auto it = fastest.find(shape);
    if (it == fastest.end()) {
      s += "  " + shape + ": none of the configurations run meets every target\n";
    } else {
      s += "  " + shape + ": " + std::to_string(it->second->probes) + " probes, " +
           it->second->label + ": " + FormatFixed(it->second->hours, 2) + " h, mean " +
           FormatFixed(it->second->mean, 4) + " mm, peak " + FormatFixed(it->second->peak, 4) +
           " mm\n";
    }
  }
  return s;
}

}  // namespace gs360::cli
