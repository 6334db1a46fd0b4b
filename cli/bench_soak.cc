// `gs360 bench soak`: a long acquisition on the virtual rig with a fault every ~N probes (chosen
// at random, seeded, from the kinds asked for), resumed as a user would after each stop; at the
// end every probe must be captured exactly once, at its press point, and the database intact.
// Exit code 0 when that holds, 1 when it does not.

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <map>
#include <mutex>
#include <random>
#include <set>
#include <string>
#include <vector>

#include <unistd.h>

#include <nlohmann/json.hpp>

#include "cli/commands.h"
#include "cli/sim_args.h"
#include "cli/sim_bridge.h"
#include "run/run_engine.h"
#include "storage/run_database.h"

namespace gs360::cli {
namespace {

using Json = nlohmann::json;

struct BenchSoakArgs {
  int candidates = 2800;  // about 70 % are probed on the default cylinder: ~2,000 probes
  double fault_every = 50.0;
  std::string faults = "all";
  std::uint64_t seed = 1;
  std::string dir;
};

struct SoakResult {
  std::map<std::string, int> injected;
  int faults = 0, sessions = 0, recoveries = 0;
  std::int64_t captured = 0, planned_left = 0, failed_attempts = 0;
  int duplicate_frames = 0, frames = 0, off_target = 0, unverified = 0;
  std::vector<std::string> integrity;
  double seconds = 0.0;
  bool ok = false;
};

// Resumes until done (as a user would: confirming what the run asks about), at most `limit`
// sessions.
void RunToTheEnd(RunEngine& engine, std::int64_t run_id, const std::filesystem::path& db_path,
                 int limit, SoakResult* out) {
  SessionOverrides overrides;
  for (out->sessions = 0; out->sessions < limit;) {
    const RunReport report = engine.Execute(run_id, overrides);
    ++out->sessions;
    out->recoveries += report.recoveries;
    out->failed_attempts += report.failed;
    if (report.outcome == RunOutcome::kDone) return;
    overrides = {};
    overrides.confirm = RunDatabase(db_path).GetRun(run_id)->awaiting;
  }
}

void Verify(const VirtualRig& rig, const std::filesystem::path& db_path, std::int64_t run_id,
            SoakResult* out) {
  RunDatabaseOptions ro;
  ro.read_only = true;
  const RunDatabase db(db_path, ro);
  const ProbeCounts counts = db.CountProbes(run_id);
  out->captured = counts.captured;
  out->planned_left = counts.planned;
  const auto frames = db.ListFrames(run_id, FrameKind::kPress);
  out->frames = static_cast<int>(frames.size());
  std::set<std::int64_t> probes;
  for (const auto& f : frames) {
    if (!f.probe_id || !probes.insert(*f.probe_id).second) ++out->duplicate_frames;
  }
  out->integrity = db.IntegrityCheck();
  const CaptureTruth truth = CheckCapturesAgainstTruth(rig, db, run_id);
  out->off_target = truth.off_target;
  out->unverified = truth.unverified;
  out->ok = out->planned_left == 0 && out->duplicate_frames == 0 &&
            out->frames == static_cast<int>(out->captured) && out->integrity.empty() &&
            out->off_target == 0 && out->unverified == 0;
}

SoakResult Soak(const BenchSoakArgs& a, const std::filesystem::path& dir) {
  RunConfig config;
  config.name = "soak";
  config.plan.probe_count = a.candidates;
  VirtualSetup setup =
      MakeVirtualSetup(config, 0.0, a.seed, dir / "camera.sock", (dir / "ttyCNC").string(),
                       [](VirtualRigOptions& o) { o.frame_log_capacity = 1u << 19; });
  config = setup.config;
  config.engine.reconnect_timeout_s = 10.0;
  const std::filesystem::path db_path = dir / "soak.db";
  RunEngine engine(db_path);
  const std::int64_t run_id = engine.CreateRun(config);
  SoakResult out;
  std::mt19937_64 rng(a.seed);
  std::uniform_real_distribution<double> spacing(0.5 * a.fault_every, 1.5 * a.fault_every);
  std::mutex mutex;
  double next = spacing(rng);
  const std::vector<RigFault> faults = ParseRigFaults(a.faults);
  engine.SetProgressCallback([&](const RunProgress& p) {
    std::lock_guard<std::mutex> lock(mutex);
    if (static_cast<double>(p.counts.captured) < next) return;
    const RigFault fault = faults[rng() % faults.size()];
    InjectRigFault(*setup.rig, fault, rng);
    ++out.injected[std::string(ToString(fault))];
    ++out.faults;
    next = static_cast<double>(p.counts.captured) + spacing(rng);
    std::fprintf(stderr, "\rsoak: %lld probes, %d faults",
                 static_cast<long long>(p.counts.captured), out.faults);
  });
  const auto start = std::chrono::steady_clock::now();
  RunToTheEnd(engine, run_id, db_path, 1000, &out);
  out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::fprintf(stderr, "\n");
  Verify(*setup.rig, db_path, run_id, &out);
  return out;
}

int RunBenchSoak(const BenchSoakArgs& a, const CommandContext& ctx) {
  const std::filesystem::path dir = a.dir.empty() ? std::filesystem::temp_directory_path() /
                                                        ("gs360-soak-" + std::to_string(::getpid()))
                                                  : std::filesystem::path(a.dir);
  std::filesystem::create_directories(dir);
  const SoakResult r = Soak(a, dir);
  const int faults = r.faults;
  const Json result{{"captured", r.captured},
                    {"planned_left", r.planned_left},
                    {"press_frames", r.frames},
                    {"duplicate_frames", r.duplicate_frames},
                    {"off_target", r.off_target},
                    {"unverified", r.unverified},
                    {"integrity", r.integrity},
                    {"faults", faults},
                    {"faults_by_kind", r.injected},
                    {"sessions", r.sessions},
                    {"recoveries", r.recoveries},
                    {"failed_attempts", r.failed_attempts},
                    {"seconds", r.seconds},
                    {"seed", a.seed},
                    {"ok", r.ok}};
  if (ctx.json) {
    std::printf("%s\n", result.dump(2).c_str());
  } else {
    std::printf("soak: %lld probes captured in %.0f s, %d faults, %d sessions, %d recoveries\n",
                static_cast<long long>(r.captured), r.seconds, faults, r.sessions, r.recoveries);
    for (const auto& [k, v] : r.injected) std::printf("  %-14s %d\n", k.c_str(), v);
    std::printf(
        "  press frames %d, duplicates %d, left to capture %lld, off the press point %d, "
        "unverifiable %d, database %s\n",
        r.frames, r.duplicate_frames, static_cast<long long>(r.planned_left), r.off_target,
        r.unverified, r.integrity.empty() ? "intact" : r.integrity.front().c_str());
    std::printf("%s\n", r.ok ? "every probe captured exactly once, at its press point"
                             : "FAILED: see the counts above");
  }
  if (a.dir.empty()) {
    std::error_code ec;
    std::filesystem::remove_all(dir, ec);
  }
  return r.ok ? 0 : 1;
}

}  // namespace

void RegisterSoakBench(CLI::App& bench, CommandContext& ctx) {
  static BenchSoakArgs a;
  auto* cmd = bench.add_subcommand(
      "soak",
      "A long acquisition on the virtual rig with a fault every ~N probes, resumed after "
      "each stop; checks every probe is captured exactly once");
  cmd->add_option("--candidates", a.candidates,
                  "Candidate points (about 70 % are probed on the default cylinder)")
      ->check(CLI::Range(10, 100000));
  AddFaultArgs(cmd, &a.faults, &a.fault_every);
  cmd->add_option("--seed", a.seed, "Seed of the rig and of the faults' kinds and times");
  cmd->add_option("--dir", a.dir, "Keep the database and logs here (default: a temporary folder)");
  cmd->callback([&ctx] { ctx.exit_code = RunBenchSoak(a, ctx); });
}

}  // namespace gs360::cli
