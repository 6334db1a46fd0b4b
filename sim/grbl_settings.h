#pragma once
// GRBL 1.1 settings ($$), status codes (error:N) and alarm codes (ALARM:N) for the virtual CNC.
// Codes and setting numbers follow gnea/grbl doc/csv/*.csv and settings.c.

#include <string>

#include <Eigen/Core>

#include "sim/grbl_planner.h"

namespace gs360 {

// `error:N` codes (GRBL 1.1 report.h / doc/csv/error_codes_en_US.csv).
enum GrblStatus : int {
  kGrblOk = 0,
  kGrblExpectedCommandLetter = 1,
  kGrblBadNumberFormat = 2,
  kGrblInvalidStatement = 3,
  kGrblNegativeValue = 4,
  kGrblSettingDisabled = 5,
  kGrblSettingStepPulseMin = 6,
  kGrblSettingReadFail = 7,
  kGrblIdleError = 8,
  kGrblSystemGcLock = 9,
  kGrblSoftLimitError = 10,
  kGrblOverflow = 11,
  kGrblMaxStepRateExceeded = 12,
  kGrblCheckDoor = 13,
  kGrblLineLengthExceeded = 14,
  kGrblTravelExceeded = 15,
  kGrblInvalidJogCommand = 16,
  kGrblSettingDisabledLaser = 17,
  kGrblGcodeUnsupportedCommand = 20,
  kGrblGcodeModalGroupViolation = 21,
  kGrblGcodeUndefinedFeedRate = 22,
  kGrblGcodeCommandValueNotInteger = 23,
  kGrblGcodeAxisCommandConflict = 24,
  kGrblGcodeWordRepeated = 25,
  kGrblGcodeNoAxisWords = 26,
  kGrblGcodeInvalidLineNumber = 27,
  kGrblGcodeValueWordMissing = 28,
  kGrblGcodeUnsupportedCoordSys = 29,
  kGrblGcodeG53InvalidMotionMode = 30,
  kGrblGcodeAxisWordsExist = 31,
  kGrblGcodeNoAxisWordsInPlane = 32,
  kGrblGcodeInvalidTarget = 33,
  kGrblGcodeArcRadiusError = 34,
  kGrblGcodeNoOffsetsInPlane = 35,
  kGrblGcodeUnusedWords = 36,
  kGrblGcodeG43DynamicAxisError = 37,
  kGrblGcodeMaxValueExceeded = 38,
  // grblHAL only (grblHAL/core errors.h Status_HomingRequired): `$X` refused while the homing
  // lock is on and the machine is not homed.
  kGrblHalHomingRequired = 46,
};

// `ALARM:N` codes.
enum GrblAlarm : int {
  kGrblAlarmHardLimit = 1,
  kGrblAlarmSoftLimit = 2,
  kGrblAlarmAbortCycle = 3,
  kGrblAlarmProbeFailInitial = 4,
  kGrblAlarmProbeFailContact = 5,
  kGrblAlarmHomingFailReset = 6,
  kGrblAlarmHomingFailDoor = 7,
  kGrblAlarmHomingFailPulloff = 8,
  kGrblAlarmHomingFailApproach = 9,
  // grblHAL only (grblHAL/core alarms.h Alarm_HomingRequried): raised at boot and reset while
  // the homing lock is on and the machine is not homed.
  kGrblHalAlarmHomingRequired = 11,
};

// GRBL's printFloat(): a '-' for any negative value (so a tiny negative prints "-0.000", as on
// the firmware), then the magnitude rounded half-up to `decimals` places.
std::string FormatGrblFloat(double value, int decimals);

// The EEPROM settings. Defaults describe a typical GRBL 1.1 desktop mill (3018-class: 800
// steps/mm lead screws) with homing and soft limits enabled; GrblFirmwareDefaults() gives the
// values gnea/grbl compiles in (defaults.h DEFAULTS_GENERIC).
struct GrblSettings {
  int step_pulse_us = 10;                 // $0
  int step_idle_delay_ms = 25;            // $1
  int step_invert_mask = 0;               // $2
  int dir_invert_mask = 0;                // $3
  bool invert_step_enable = false;        // $4
  bool invert_limit_pins = false;         // $5
  bool invert_probe_pin = false;          // $6
  int status_report_mask = 1;             // $10: bit 0 MPos (else WPos), bit 1 buffer state
  double junction_deviation_mm = 0.010;   // $11
  double arc_tolerance_mm = 0.002;        // $12
  bool report_inches = false;             // $13
  bool soft_limits = true;                // $20
  bool hard_limits = false;               // $21
  bool homing_enable = true;              // $22
  int homing_dir_mask = 0;                // $23: bit set = that axis homes toward negative
  double homing_feed_mm_per_min = 100.0;  // $24 (locate)
  double homing_seek_mm_per_min = 800.0;  // $25 (search)
  int homing_debounce_ms = 250;           // $26
  double homing_pulloff_mm = 1.0;         // $27
  double spindle_max_rpm = 1000.0;        // $30
  double spindle_min_rpm = 0.0;           // $31
  bool laser_mode = false;                // $32
  Eigen::Vector3d steps_per_mm{800.0, 800.0, 800.0};           // $100-$102
  Eigen::Vector3d max_rate_mm_per_min{2000.0, 2000.0, 800.0};  // $110-$112
  Eigen::Vector3d acceleration_mm_per_s2{150.0, 150.0, 80.0};  // $120-$122
  Eigen::Vector3d max_travel_mm{300.0, 180.0, 45.0};           // $130-$132 (as $$ prints them)

  static GrblSettings GrblFirmwareDefaults();
  // A Marlin printer of the Ender-3 class in these fields (the virtual CNC's Marlin dialect reads
  // its motion from them): 80/80/400 steps/mm, 500/500/5 mm/s, 500/500/100 mm/s^2, junction
  // deviation 0.013 mm, travel 235 x 235 x 250 mm, homing at 50 then 10 mm/s.
  static GrblSettings PrinterDefaults();

  // Throws std::invalid_argument naming the field and value for a setting the firmware would
  // reject or that breaks motion (non-positive steps/mm, rate, acceleration or travel, negative
  // values, $0 < 3, soft limits without homing).
  void Check() const;

  // $110-$112, $120-$122, $11 for the planner.
  MotionLimits Limits() const;

  // The `$$` printout: one `$n=value\r\n` line per setting in GRBL's order (no final ok).
  std::string Report() const;

  // `$n=value` as settings_store_global_setting() does it: returns kGrblOk, or the status code
  // the firmware replies (4 negative value, 6 step pulse < 3 us, 10 soft limits without homing,
  // 3 unknown setting). $22=0 also clears $20, as on the firmware. Values of 0 for steps/mm,
  // rates, accelerations are rejected with error:3 here (the firmware accepts them and then
  // divides by zero).
  int Store(int parameter, double value);
};

}  // namespace gs360
