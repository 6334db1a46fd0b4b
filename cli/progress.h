#pragma once
// A one-line progress display for long runs: a bar with done / total, rate and ETA on a
// terminal (redrawn in place), a plain line every `plain_interval_s` otherwise (logs, CI).

#include <chrono>
#include <cstdio>
#include <string>

#include "run/run_engine.h"

namespace gs360::cli {

class ProgressPrinter {
 public:
  explicit ProgressPrinter(std::FILE* out = stderr, double plain_interval_s = 10.0);
  void Update(const RunProgress& p);
  void Finish();  // ends the in-place line

 private:
  std::FILE* out_;
  bool tty_;
  double plain_interval_s_;
  std::chrono::steady_clock::time_point last_plain_{};
  bool drawn_ = false;
};

}  // namespace gs360::cli
