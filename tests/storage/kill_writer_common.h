#pragma once
// What storage_kill_writer commits, so that the kill test can check every stored byte.
// Probe i of a run gets a deterministic frame (from a pool), position and times; some probes fail
// once first or are skipped, and a reference frame precedes every 10th probe.

#include <cmath>
#include <cstdint>

#include <Eigen/Core>
#include <opencv2/core/mat.hpp>

#include "storage/run_database.h"
#include "tests/storage/storage_test_util.h"

namespace gs360::test {

inline constexpr int kKillPlanSize = 600;
inline constexpr double kKillT0 = 1.7e9;

inline bool KillSkips(int i) {
  return i % 29 == 7;
}
inline bool KillFailsFirst(int i) {
  return !KillSkips(i) && i % 13 == 4;
}
inline bool KillHasReference(int i) {
  return i % 10 == 0;
}

// Frames come from a small pool, encoded once, so that the writer spends its time in the
// database (where a kill is interesting) rather than making images. 320x240 colour: ~120 kB as
// PNG, about 30 overflow pages, so a torn write would show. Pool slots 0..7 are press frames,
// 8..9 reference frames.
inline constexpr int kKillPoolSize = 10;
inline int KillPressSlot(std::int64_t run_id, int i) {
  return static_cast<int>((run_id * 3 + i) % 8);
}
inline int KillReferenceSlot(int i) {
  return 8 + (i / 10) % 2;
}
inline cv::Mat KillPoolFrame(int slot) {
  return NoisyFrame(1000 + slot, 320, 240);
}
inline Eigen::Vector3d KillPosition(int i) {
  return {0.25 * i, -0.125 * i, 10.0 + std::sin(0.1 * i)};
}
inline double KillSyncTime(int i) {
  return kKillT0 + 4.0 * i + 0.5;
}
inline double KillFrameTime(int i) {
  return kKillT0 + 4.0 * i + 1.0;
}
inline double KillReferenceTime(int i) {
  return kKillT0 + 4.0 * i - 0.25;
}
// Inverse of KillReferenceTime.
inline int KillReferenceIndex(double t) {
  return static_cast<int>(std::lround((t - kKillT0 + 0.25) / 4.0));
}

inline ProbePlanEntry KillPlanEntry(int i) {
  ProbePlanEntry e;
  e.point_sensor = {std::cos(0.01 * i), std::sin(0.01 * i), 0.02 * i};
  e.normal_sensor = {std::cos(0.01 * i), std::sin(0.01 * i), 0.0};
  e.press_machine = KillPosition(i);
  e.approach_machine = e.press_machine + Eigen::Vector3d(0, 0, 3);
  e.retract_machine = e.approach_machine;
  return e;
}

}  // namespace gs360::test
