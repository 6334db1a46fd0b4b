#pragma once
// Faults of the whole virtual rig by name, one at a time or on a schedule: what `gs360 bench
// soak`, `gs360 sim-rig --faults` and `gs360 demo --faults` inject. The kinds:
//   drop, garble          bytes from the host lost or bit-flipped (3 / 4 bytes)
//   garble-reply          bytes to the host bit-flipped (6 bytes)
//   stall                 replies held back 0.5-1.5 s
//   unplug                the USB link gone for 0.5 s (the board loses power), back as a new pty
//   reset                 a controller reset during the next dwell (at the bottom of a press)
//   alarm                 a hard-limit alarm half-way through the next move
//   lost-position         a reset alarm mid-move that also shifts the controller's position
//   power-cycle           the board restarts where it stands (MPos 0,0,0, Alarm)
//   hold                  a feed hold from the board's hold pin (or a '!' made by noise)
//   lost-reply            the next `ok` never reaches the host
//   frame-drop            1-5 camera frames never delivered
//   frame-corrupt         1-2 camera frames served damaged (garbage rows or black)
// On a virtual Marlin printer the serial faults are the same, a garbled line is refused and
// resent, reset and power-cycle reboot the board (`start`, position lost), alarm and lost-position
// halt it as kill() does, and hold does nothing (a printer has no hold input).

#include <atomic>
#include <cstdint>
#include <map>
#include <mutex>
#include <random>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include "sim/virtual_rig.h"

namespace gs360 {

enum class RigFault {
  kDrop,
  kGarble,
  kGarbleReply,
  kStall,
  kUnplug,
  kReset,
  kAlarm,
  kLostPosition,
  kPowerCycle,
  kHold,
  kLostReply,
  kFrameDrop,
  kFrameCorrupt,
};

std::string_view ToString(RigFault fault);
// Every kind, in the order above.
const std::vector<RigFault>& AllRigFaults();
// A comma-separated list of kinds ("all" for every one). Throws std::invalid_argument naming an
// unknown kind and listing the known ones, or for an empty list.
std::vector<RigFault> ParseRigFaults(const std::string& list);

// Injects one fault into `rig` now (it takes effect on the next bytes, move, dwell or frame);
// `rng` draws its size where it has one.
void InjectRigFault(VirtualRig& rig, RigFault fault, std::mt19937_64& rng);

struct RigFaultScheduleOptions {
  std::vector<RigFault> faults;  // drawn from uniformly; not empty
  double every_probes = 50.0;    // mean presses between faults (uniform in 0.5x-1.5x), >= 2
  std::uint64_t seed = 1;
  // Throws std::invalid_argument naming the field.
  void Check() const;
};

// Injects a fault every ~every_probes presses for as long as it lives, from a background thread
// that counts presses as the controller's G4 dwells (so it needs nothing from the host). Kinds
// and times are drawn from the seed.
class RigFaultSchedule {
 public:
  // Throws what options.Check() throws.
  RigFaultSchedule(VirtualRig& rig, RigFaultScheduleOptions options);
  ~RigFaultSchedule();
  RigFaultSchedule(const RigFaultSchedule&) = delete;
  RigFaultSchedule& operator=(const RigFaultSchedule&) = delete;

  // Faults injected so far, by kind name. Thread-safe.
  std::map<std::string, int> Injected() const;
  int Total() const;

 private:
  void Loop();

  VirtualRig& rig_;
  RigFaultScheduleOptions options_;
  mutable std::mutex mutex_;
  std::map<std::string, int> injected_;
  std::atomic<bool> stop_{false};
  std::thread thread_;
};

}  // namespace gs360
