// The virtual controller's reports (GRBL's report.c): the '?' status line with its WCO and
// override fields on their refresh counts, and the $# coordinate report.

#include <string>

#include "sim/grbl_settings.h"
#include "sim/virtual_cnc_impl.h"

namespace gs360 {
namespace {

constexpr int kWcoRefreshBusy = 30, kWcoRefreshIdle = 10;  // REPORT_WCO_REFRESH_*_COUNT
constexpr int kOvrRefreshBusy = 20, kOvrRefreshIdle = 10;  // REPORT_OVR_REFRESH_*_COUNT
constexpr double kMmPerInch = 25.4;

}  // namespace

std::string VirtualCnc::Impl::AxisValues(const Eigen::Vector3d& v) const {
  std::string s;
  for (int i = 0; i < 3; ++i) {
    if (i) s.push_back(',');
    s += settings_.report_inches ? FormatGrblFloat(v[i] / kMmPerInch, 4) : FormatGrblFloat(v[i], 3);
  }
  return s;
}

double VirtualCnc::Impl::SpindleRpm() const {
  if (gc_.modal.spindle == 0) return 0.0;
  const double rpm = gc_.spindle_speed;
  if (settings_.spindle_min_rpm >= settings_.spindle_max_rpm || rpm >= settings_.spindle_max_rpm) {
    return settings_.spindle_max_rpm;
  }
  if (rpm <= settings_.spindle_min_rpm) return rpm == 0.0 ? 0.0 : settings_.spindle_min_rpm;
  return rpm;
}

void VirtualCnc::Impl::ReportStatus() {
  std::string s = "<";
  switch (state_) {
    case GrblState::kHold:
      s += jog_cancel_ ? "Jog" : (hold_complete_ ? "Hold:0" : "Hold:1");
      break;
    case GrblState::kDoor:
      s += "Door:0";
      break;
    default:
      s += GrblStateName(state_);
      break;
  }
  Eigen::Vector3d pos = Belief();
  const Eigen::Vector3d wco = gc_.Wco();
  const bool mpos = (settings_.status_report_mask & 1) != 0;
  if (!mpos) pos -= wco;
  s += mpos ? "|MPos:" : "|WPos:";
  s += AxisValues(pos);
  if (settings_.status_report_mask & 2) {
    s += "|Bf:" + std::to_string(options_.planner_blocks - exec_.BlockCount()) + "," +
         std::to_string(options_.rx_buffer_bytes - static_cast<int>(rx_.size()));
  }
  const double rate = exec_.SpeedAt(MachineNow()) * 60.0;
  s +=
      "|FS:" +
      (settings_.report_inches ? FormatGrblFloat(rate / kMmPerInch, 1) : FormatGrblFloat(rate, 0)) +
      "," + FormatGrblFloat(SpindleRpm(), 0);
  if (options_.report_wco_and_overrides) {
    const bool busy = state_ == GrblState::kHome || state_ == GrblState::kRun ||
                      state_ == GrblState::kHold || state_ == GrblState::kJog ||
                      state_ == GrblState::kDoor;
    if (wco_counter_ > 0) {
      --wco_counter_;
    } else {
      wco_counter_ = (busy ? kWcoRefreshBusy : kWcoRefreshIdle) - 1;
      if (ovr_counter_ == 0) ovr_counter_ = 1;  // overrides on the next report
      s += "|WCO:" + AxisValues(wco);
    }
    if (ovr_counter_ > 0) {
      --ovr_counter_;
    } else {
      ovr_counter_ = (busy ? kOvrRefreshBusy : kOvrRefreshIdle) - 1;
      s += "|Ov:100,100,100";
      if (gc_.modal.spindle != 0 || gc_.modal.coolant != 0) {
        s += "|A:";
        if (gc_.modal.spindle == 1) s += "S";
        if (gc_.modal.spindle == 2) s += "C";
        if (gc_.modal.coolant & 1) s += "F";
      }
    }
  }
  s += ">\r\n";
  Emit(s);
}

// `$#`: the coordinate systems, G28 / G30, G92, the tool length offset and the last probe.
void VirtualCnc::Impl::ReportCoordinates() {
  std::string s;
  for (int i = 0; i < 6; ++i) {
    s += "[G" + std::to_string(54 + i) + ":" +
         AxisValues(coords_.wcs[static_cast<std::size_t>(i)]) + "]\r\n";
  }
  s += "[G28:" + AxisValues(coords_.g28) + "]\r\n";
  s += "[G30:" + AxisValues(coords_.g30) + "]\r\n";
  s += "[G92:" + AxisValues(gc_.coord_offset) + "]\r\n";
  s += "[TLO:" +
       (settings_.report_inches ? FormatGrblFloat(gc_.tool_length_offset / kMmPerInch, 4)
                                : FormatGrblFloat(gc_.tool_length_offset, 3)) +
       "]\r\n";
  s += "[PRB:" + AxisValues(probe_position_) + ":" + (probe_succeeded_ ? "1" : "0") + "]\r\n";
  Emit(s);
}

}  // namespace gs360
