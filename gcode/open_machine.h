#pragma once
// The Machine for `[machine] firmware` (gcode/machine.h): GRBL's or Marlin's, or, for "auto",
// the one whose firmware answers at the port.

#include <chrono>
#include <memory>
#include <string>

#include "gcode/grbl_client.h"
#include "gcode/machine.h"
#include "gcode/marlin_machine.h"
#include "gcode/transport.h"

namespace gs360 {

// Which firmware is behind `transport`, from what it says once opened: a GRBL welcome, status or
// alarm, or Marlin's "start" and echoes (Klipper's "//" and "!!" lines too); when it says nothing
// within `wait`, it is asked "M115" (Marlin and Klipper answer FIRMWARE_NAME or ok, GRBL
// error:20; that answer is read away). Throws std::runtime_error naming the port when neither
// answers.
struct FirmwareDetection {
  MachineFirmware firmware = MachineFirmware::kGrbl;
  std::string replay;  // what the controller said unasked: for the machine's handshake to read
};
FirmwareDetection DetectFirmware(Transport& transport, std::chrono::milliseconds wait);

struct OpenMachineOptions {
  TransportOptions transport;
  GrblClientOptions grbl;
  MarlinMachineOptions marlin;
  std::chrono::milliseconds detect_wait{2500};
};

// The machine at `uri` (not yet connected). For kAuto the port is opened to detect the firmware
// and kept open for the first Connect() (which reads again what it said); `detected` gets the
// firmware used. Throws
// TransportError when the port cannot be opened for detection, std::runtime_error when nothing
// answers.
std::unique_ptr<Machine> OpenMachine(MachineFirmware firmware, const std::string& uri,
                                     const OpenMachineOptions& options,
                                     MachineFirmware* detected = nullptr);

}  // namespace gs360
