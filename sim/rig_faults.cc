#include "sim/rig_faults.h"

#include <chrono>
#include <stdexcept>

namespace gs360 {

std::string_view ToString(RigFault fault) {
  switch (fault) {
    case RigFault::kDrop:
      return "drop";
    case RigFault::kGarble:
      return "garble";
    case RigFault::kGarbleReply:
      return "garble-reply";
    case RigFault::kStall:
      return "stall";
    case RigFault::kUnplug:
      return "unplug";
    case RigFault::kReset:
      return "reset";
    case RigFault::kAlarm:
      return "alarm";
    case RigFault::kLostPosition:
      return "lost-position";
    case RigFault::kPowerCycle:
      return "power-cycle";
    case RigFault::kHold:
      return "hold";
    case RigFault::kLostReply:
      return "lost-reply";
    case RigFault::kFrameDrop:
      return "frame-drop";
    case RigFault::kFrameCorrupt:
      return "frame-corrupt";
  }
  return "unknown";
}

const std::vector<RigFault>& AllRigFaults() {
  static const std::vector<RigFault> all = {
      RigFault::kDrop,        RigFault::kGarble, RigFault::kGarbleReply, RigFault::kStall,
      RigFault::kUnplug,      RigFault::kReset,  RigFault::kAlarm,       RigFault::kLostPosition,
      RigFault::kPowerCycle,  RigFault::kHold,   RigFault::kLostReply,   RigFault::kFrameDrop,
      RigFault::kFrameCorrupt};
  return all;
}

std::vector<RigFault> ParseRigFaults(const std::string& list) {
  std::vector<RigFault> out;
  std::size_t start = 0;
  while (start <= list.size()) {
    const std::size_t comma = std::min(list.find(',', start), list.size());
    const std::string name = list.substr(start, comma - start);
    start = comma + 1;
    if (name.empty()) continue;
    if (name == "all") {
      out.insert(out.end(), AllRigFaults().begin(), AllRigFaults().end());
      continue;
    }
    bool found = false;
    for (RigFault f : AllRigFaults()) {
      if (ToString(f) == name) {
        out.push_back(f);
        found = true;
      }
    }
    if (!found) {
      std::string known;
      for (RigFault f : AllRigFaults())
        known += (known.empty() ? "" : ", ") + std::string(ToString(f));
      throw std::invalid_argument("unknown fault '" + name + "'; the kinds are: " + known +
                                  " (or all)");
    }
  }
  if (out.empty()) throw std::invalid_argument("no fault kinds in '" + list + "'");
  return out;
}

void InjectRigFault(VirtualRig& rig, RigFault fault, std::mt19937_64& rng) {
  VirtualCnc& cnc = rig.cnc();
  switch (fault) {
    case RigFault::kDrop:
      return cnc.DropNextBytes(3);
    case RigFault::kGarble:
      return cnc.GarbleNextBytes(4);
    case RigFault::kGarbleReply:
      return cnc.GarbleNextBytes(6, FaultDirection::kCncToHost);
    case RigFault::kStall:
      return cnc.StallReplies(std::chrono::milliseconds(500 + static_cast<int>(rng() % 1000)));
    case RigFault::kUnplug: {
      UnplugOptions unplug;
      unplug.replug_after = std::chrono::milliseconds(500);
      return cnc.Unplug(unplug);
    }
    case RigFault::kReset:
      return cnc.ResetDuringNextDwell();
    case RigFault::kAlarm:
      return cnc.RaiseAlarmDuringNextMove(1, 0.5);  // a hard limit: the run stops, is resumed
    case RigFault::kLostPosition:
      cnc.LosePositionOnReset(true);
      return cnc.RaiseAlarmDuringNextMove(3, 0.3);
    case RigFault::kPowerCycle:
      return cnc.PowerCycle();  // boots in Alarm at MPos 0,0,0: the run asks, then homes
    case RigFault::kHold:
      return cnc.FeedHoldPin();  // the run stops; its resume ends the hold
    case RigFault::kLostReply:
      return cnc.LoseNextReply();
    case RigFault::kFrameDrop:
      return rig.DropNextFrames(1 + static_cast<int>(rng() % 5));
    case RigFault::kFrameCorrupt:
      return rig.CorruptNextFrames(1 + static_cast<int>(rng() % 2));
  }
}

void RigFaultScheduleOptions::Check() const {
  if (faults.empty()) throw std::invalid_argument("RigFaultScheduleOptions.faults is empty");
  if (!(every_probes >= 2.0)) {
    throw std::invalid_argument("RigFaultScheduleOptions.every_probes must be >= 2, got " +
                                std::to_string(every_probes));
  }
}

RigFaultSchedule::RigFaultSchedule(VirtualRig& rig, RigFaultScheduleOptions options)
    : rig_(rig), options_(std::move(options)) {
  options_.Check();
  thread_ = std::thread([this] { Loop(); });
}

RigFaultSchedule::~RigFaultSchedule() {
  stop_ = true;
  if (thread_.joinable()) thread_.join();
}

void RigFaultSchedule::Loop() {
  std::mt19937_64 rng(options_.seed);
  std::uniform_real_distribution<double> spacing(0.5 * options_.every_probes,
                                                 1.5 * options_.every_probes);
  double next = static_cast<double>(rig_.cnc().Stats().dwells) + spacing(rng);
  while (!stop_) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
    const auto dwells = static_cast<double>(rig_.cnc().Stats().dwells);
    if (dwells < next) continue;
    const RigFault fault = options_.faults[rng() % options_.faults.size()];
    InjectRigFault(rig_, fault, rng);
    {
      std::lock_guard<std::mutex> lock(mutex_);
      ++injected_[std::string(ToString(fault))];
    }
    next = dwells + spacing(rng);
  }
}

std::map<std::string, int> RigFaultSchedule::Injected() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return injected_;
}

int RigFaultSchedule::Total() const {
  int total = 0;
  for (const auto& [kind, n] : Injected()) total += n;
  return total;
}

}  // namespace gs360
