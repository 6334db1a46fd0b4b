#include "sim/grbl_settings.h"

#include <cmath>
#include <cstdint>
#include <sstream>
#include <stdexcept>

namespace gs360 {

std::string FormatGrblFloat(double value, int decimals) {
  std::string out;
  if (value < 0.0) {
    out.push_back('-');
    value = -value;
  }
  double scale = 1.0;
  for (int i = 0; i < decimals; ++i) scale *= 10.0;
  const auto scaled = static_cast<std::uint64_t>(std::floor(value * scale + 0.5));
  const std::uint64_t divisor = static_cast<std::uint64_t>(scale);
  out += std::to_string(scaled / divisor);
  if (decimals > 0) {
    std::string frac = std::to_string(scaled % divisor);
    out.push_back('.');
    out.append(static_cast<std::size_t>(decimals) - frac.size(), '0');
    out += frac;
  }
  return out;
}

GrblSettings GrblSettings::GrblFirmwareDefaults() {
  GrblSettings s;
  s.soft_limits = false;
  s.homing_enable = false;
  s.homing_feed_mm_per_min = 25.0;
  s.homing_seek_mm_per_min = 500.0;
  s.steps_per_mm = Eigen::Vector3d(250.0, 250.0, 250.0);
  s.max_rate_mm_per_min = Eigen::Vector3d(500.0, 500.0, 500.0);
  s.acceleration_mm_per_s2 = Eigen::Vector3d(10.0, 10.0, 10.0);
  s.max_travel_mm = Eigen::Vector3d(200.0, 200.0, 200.0);
  return s;
}

GrblSettings GrblSettings::PrinterDefaults() {
  GrblSettings s;
  s.junction_deviation_mm = 0.013;  // Marlin's JUNCTION_DEVIATION_MM
  s.homing_seek_mm_per_min = 3000.0;
  s.homing_feed_mm_per_min = 600.0;
  s.steps_per_mm = Eigen::Vector3d(80.0, 80.0, 400.0);
  s.max_rate_mm_per_min = Eigen::Vector3d(30000.0, 30000.0, 300.0);
  s.acceleration_mm_per_s2 = Eigen::Vector3d(500.0, 500.0, 100.0);
  s.max_travel_mm = Eigen::Vector3d(235.0, 235.0, 250.0);
  return s;
}

namespace {

void Require(bool ok, const std::string& field, double value, const char* what) {
  if (ok) return;
  std::ostringstream os;
  os << "GrblSettings." << field << " " << what << ", got " << value;
  throw std::invalid_argument(os.str());
}

}  // namespace

void GrblSettings::Check() const {
  Require(step_pulse_us >= 3, "step_pulse_us ($0)", step_pulse_us, "must be >= 3");
  Require(step_idle_delay_ms >= 0, "step_idle_delay_ms ($1)", step_idle_delay_ms, "must be >= 0");
  Require(status_report_mask >= 0 && status_report_mask <= 255, "status_report_mask ($10)",
          status_report_mask, "must be in 0..255");
  Require(junction_deviation_mm >= 0.0, "junction_deviation_mm ($11)", junction_deviation_mm,
          "must be >= 0");
  Require(arc_tolerance_mm > 0.0, "arc_tolerance_mm ($12)", arc_tolerance_mm, "must be > 0");
  Require(!soft_limits || homing_enable, "soft_limits ($20)", soft_limits,
          "needs homing_enable ($22)");
  Require(homing_feed_mm_per_min > 0.0, "homing_feed_mm_per_min ($24)", homing_feed_mm_per_min,
          "must be > 0");
  Require(homing_seek_mm_per_min > 0.0, "homing_seek_mm_per_min ($25)", homing_seek_mm_per_min,
          "must be > 0");
  Require(homing_debounce_ms >= 0, "homing_debounce_ms ($26)", homing_debounce_ms, "must be >= 0");
  Require(homing_pulloff_mm >= 0.0, "homing_pulloff_mm ($27)", homing_pulloff_mm, "must be >= 0");
  static const char* kAxis = "xyz";
  for (int i = 0; i < 3; ++i) {
    const std::string a(1, kAxis[i]);
    Require(steps_per_mm[i] > 0.0, "steps_per_mm." + a, steps_per_mm[i], "must be > 0");
    Require(max_rate_mm_per_min[i] > 0.0, "max_rate_mm_per_min." + a, max_rate_mm_per_min[i],
            "must be > 0");
    Require(acceleration_mm_per_s2[i] > 0.0, "acceleration_mm_per_s2." + a,
            acceleration_mm_per_s2[i], "must be > 0");
    Require(max_travel_mm[i] > 0.0, "max_travel_mm." + a, max_travel_mm[i], "must be > 0");
  }
}

MotionLimits GrblSettings::Limits() const {
  MotionLimits l;
  l.max_rate_mm_per_min = max_rate_mm_per_min;
  l.acceleration_mm_per_s2 = acceleration_mm_per_s2;
  l.junction_deviation_mm = junction_deviation_mm;
  return l;
}

std::string GrblSettings::Report() const {
  std::ostringstream os;
  auto i = [&](int n, int v) { os << '$' << n << '=' << v << "\r\n"; };
  auto f = [&](int n, double v) { os << '$' << n << '=' << FormatGrblFloat(v, 3) << "\r\n"; };
  i(0, step_pulse_us);
  i(1, step_idle_delay_ms);
  i(2, step_invert_mask);
  i(3, dir_invert_mask);
  i(4, invert_step_enable);
  i(5, invert_limit_pins);
  i(6, invert_probe_pin);
  i(10, status_report_mask);
  f(11, junction_deviation_mm);
  f(12, arc_tolerance_mm);
  i(13, report_inches);
  i(20, soft_limits);
  i(21, hard_limits);
  i(22, homing_enable);
  i(23, homing_dir_mask);
  f(24, homing_feed_mm_per_min);
  f(25, homing_seek_mm_per_min);
  i(26, homing_debounce_ms);
  f(27, homing_pulloff_mm);
  os << "$30=" << FormatGrblFloat(spindle_max_rpm, 0) << "\r\n";
  os << "$31=" << FormatGrblFloat(spindle_min_rpm, 0) << "\r\n";
  i(32, laser_mode);
  for (int a = 0; a < 3; ++a) f(100 + a, steps_per_mm[a]);
  for (int a = 0; a < 3; ++a) f(110 + a, max_rate_mm_per_min[a]);
  for (int a = 0; a < 3; ++a) f(120 + a, acceleration_mm_per_s2[a]);
  for (int a = 0; a < 3; ++a) f(130 + a, max_travel_mm[a]);
  return os.str();
}

namespace {

// $100-$132: steps, rates, accelerations and travels per axis.
int StoreAxisSetting(GrblSettings& s, int parameter, double value) {
  const int group = (parameter - 100) / 10;
  const int axis = (parameter - 100) % 10;
  if (group > 3 || axis > 2) return kGrblInvalidStatement;
  if (value == 0.0) return kGrblInvalidStatement;  // would break motion; see header
  switch (group) {
    case 0:
      s.steps_per_mm[axis] = value;
      break;
    case 1:
      s.max_rate_mm_per_min[axis] = value;
      break;
    case 2:
      s.acceleration_mm_per_s2[axis] = value;
      break;
    default:
      s.max_travel_mm[axis] = value;
      break;
  }
  return kGrblOk;
}

// $0-$13: step pulses, signal inversions, reports, arcs.
int StoreSignalSetting(GrblSettings& s, int parameter, double value, int int_value) {
  switch (parameter) {
    case 0:
      if (int_value < 3) return kGrblSettingStepPulseMin;
      s.step_pulse_us = int_value;
      break;
    case 1:
      s.step_idle_delay_ms = int_value;
      break;
    case 2:
      s.step_invert_mask = int_value;
      break;
    case 3:
      s.dir_invert_mask = int_value;
      break;
    case 4:
      s.invert_step_enable = int_value != 0;
      break;
    case 5:
      s.invert_limit_pins = int_value != 0;
      break;
    case 6:
      s.invert_probe_pin = int_value != 0;
      break;
    case 10:
      s.status_report_mask = int_value;
      break;
    case 11:
      s.junction_deviation_mm = value;
      break;
    case 12:
      if (value == 0.0) return kGrblInvalidStatement;
      s.arc_tolerance_mm = value;
      break;
    case 13:
      s.report_inches = int_value != 0;
      break;
    default:
      return kGrblInvalidStatement;
  }
  return kGrblOk;
}

// $20-$32: limits, homing, spindle.
int StoreHomingSetting(GrblSettings& s, int parameter, double value, int int_value) {
  switch (parameter) {
    case 20:
      if (int_value != 0) {
        if (!s.homing_enable) return kGrblSoftLimitError;
        s.soft_limits = true;
      } else {
        s.soft_limits = false;
      }
      break;
    case 21:
      s.hard_limits = int_value != 0;
      break;
    case 22:
      s.homing_enable = int_value != 0;
      if (!s.homing_enable) s.soft_limits = false;
      break;
    case 23:
      s.homing_dir_mask = int_value;
      break;
    case 24:
      if (value == 0.0) return kGrblInvalidStatement;
      s.homing_feed_mm_per_min = value;
      break;
    case 25:
      if (value == 0.0) return kGrblInvalidStatement;
      s.homing_seek_mm_per_min = value;
      break;
    case 26:
      s.homing_debounce_ms = int_value;
      break;
    case 27:
      s.homing_pulloff_mm = value;
      break;
    case 30:
      s.spindle_max_rpm = value;
      break;
    case 31:
      s.spindle_min_rpm = value;
      break;
    case 32:
      s.laser_mode = int_value != 0;
      break;
    default:
      return kGrblInvalidStatement;
  }
  return kGrblOk;
}

}  // namespace

int GrblSettings::Store(int parameter, double value) {
  if (value < 0.0) return kGrblNegativeValue;
  if (parameter >= 100) return StoreAxisSetting(*this, parameter, value);
  // GRBL stores integer settings as uint8_t(trunc(value)).
  const int int_value =
      static_cast<int>(static_cast<std::uint8_t>(static_cast<long>(std::trunc(value)) & 0xFF));
  if (parameter < 20) return StoreSignalSetting(*this, parameter, value, int_value);
  return StoreHomingSetting(*this, parameter, value, int_value);
}

}  // namespace gs360
