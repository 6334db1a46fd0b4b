#include "cli/progress.h"

#include <unistd.h>

#include <cmath>

#include "base/format.h"

namespace gs360::cli {

ProgressPrinter::ProgressPrinter(std::FILE* out, double plain_interval_s)
    : out_(out), tty_(::isatty(::fileno(out)) != 0), plain_interval_s_(plain_interval_s) {}

void ProgressPrinter::Update(const RunProgress& p) {
  const auto total = p.counts.total;
  const auto done = p.counts.captured + p.counts.skipped;
  const double frac = total > 0 ? static_cast<double>(done) / static_cast<double>(total) : 0.0;
  char line[256];
  if (tty_) {
    constexpr int kWidth = 30;
    const int fill = static_cast<int>(frac * kWidth);
    std::string bar(static_cast<std::size_t>(fill), '=');
    if (fill < kWidth) bar += '>';
    bar.resize(kWidth, ' ');
    std::snprintf(line, sizeof line, "\r[%s] %lld/%lld %3.0f%%  failed %lld  %.0f/h  ETA %s  %-12s",
                  bar.c_str(), static_cast<long long>(done), static_cast<long long>(total),
                  100.0 * frac, static_cast<long long>(p.counts.failed), p.probes_per_hour,
                  FormatDuration(p.eta_s).c_str(), p.phase.c_str());
    std::fputs(line, out_);
    std::fflush(out_);
    drawn_ = true;
    return;
  }
  const auto now = std::chrono::steady_clock::now();
  if (std::chrono::duration<double>(now - last_plain_).count() < plain_interval_s_) return;
  last_plain_ = now;
  std::snprintf(line, sizeof line,
                "progress: %lld/%lld (%.0f%%), failed %lld, %.0f probes/h, ETA %s, %s\n",
                static_cast<long long>(done), static_cast<long long>(total), 100.0 * frac,
                static_cast<long long>(p.counts.failed), p.probes_per_hour,
                FormatDuration(p.eta_s).c_str(), p.phase.c_str());
  std::fputs(line, out_);
  std::fflush(out_);
}

void ProgressPrinter::Finish() {
  if (drawn_) std::fputs("\n", out_);
  drawn_ = false;
}

}  // namespace gs360::cli
