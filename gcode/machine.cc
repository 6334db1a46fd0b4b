#include "gcode/machine.h"

namespace gs360 {

std::string_view MachineFirmwareName(MachineFirmware firmware) {
  switch (firmware) {
    case MachineFirmware::kAuto:
      return "auto";
    case MachineFirmware::kGrbl:
      return "grbl";
    case MachineFirmware::kMarlin:
      return "marlin";
  }
  return "?";
}

std::optional<MachineFirmware> ParseMachineFirmware(std::string_view name) {
  for (MachineFirmware f :
       {MachineFirmware::kAuto, MachineFirmware::kGrbl, MachineFirmware::kMarlin}) {
    if (name == MachineFirmwareName(f)) return f;
  }
  return std::nullopt;
}

std::string_view MachineReplyKindName(MachineReplyKind kind) {
  switch (kind) {
    case MachineReplyKind::kOk:
      return "ok";
    case MachineReplyKind::kError:
      return "error";
    case MachineReplyKind::kReset:
      return "reset";
    case MachineReplyKind::kRefused:
      return "refused";
    case MachineReplyKind::kDisconnected:
      return "disconnected";
    case MachineReplyKind::kClosed:
      return "closed";
    case MachineReplyKind::kTimeout:
      return "timeout";
  }
  return "?";
}

std::string MachineReply::Describe() const {
  std::string s = "'" + line + "' #" + std::to_string(sequence) + ": ";
  s += MachineReplyKindName(kind);
  if (kind == MachineReplyKind::kError) {
    s += error_code != 0 ? ":" + std::to_string(error_code) : " \"" + error + "\"";
  }
  if (!detail.empty()) s += " (" + detail + ")";
  if (alarm) s += " [" + *alarm + " before the reply]";
  return s;
}

MachineReply MachineHandle::Wait(std::chrono::milliseconds timeout) const {
  if (!source_) {
    MachineReply r;
    r.kind = MachineReplyKind::kRefused;
    r.detail = "no line was sent";
    return r;
  }
  return source_->Wait(timeout);
}

}  // namespace gs360
