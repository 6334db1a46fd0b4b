// `gs360 bench stress`: the numerical stress suite (stress/stress.h) as a table, Markdown or
// JSON. The frame cases run through a model calibrated on the virtual rig (cached like
// `bench recon`'s). Exit code 0 when every case passes, 1 when one fails.

#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "cli/commands.h"
#include "cli/sim_model.h"
#include "recon/model_bundle.h"
#include "stress/stress.h"

namespace gs360::cli {
namespace {

struct BenchStressArgs {
  std::string model;
  std::string cache;
  std::vector<std::string> only;
  std::uint64_t seed = 1;
  bool markdown = false;
};

std::shared_ptr<const ModelBundle> LoadModel(const BenchStressArgs& a, bool quiet) {
  std::filesystem::path path = a.model;
  if (path.empty()) {
    const SimModelOptions options;  // small: the frame cases test robustness, not accuracy
    const auto dir = SimModelCacheDir(a.cache, "bench-stress-model");
    if (!quiet)
      std::fprintf(stderr, "model: calibrating on the virtual rig in %s (cached)\n", dir.c_str());
    path = MakeSimModel(dir, options);
  }
  return std::make_shared<const ModelBundle>(ReadModelBundle(path));
}

// Whether the cases `only` selects include one that runs frames through a model (the frame,
// integration and MLP stages, or a case of theirs named alone).
bool NeedsModel(const std::vector<std::string>& only) {
  if (only.empty()) return true;
  for (const StressCase& c : StressCases()) {
    if (c.stage != "frames" && c.stage != "integration" && c.stage != "mlp") continue;
    for (const std::string& name : only) {
      if (name == c.stage || name == c.name) return true;
    }
  }
  return false;
}

// The first name in `only` that is neither a stage nor a case, or "" when all are known.
std::string UnknownName(const std::vector<std::string>& only) {
  const std::vector<StressCase> cases = StressCases();
  for (const std::string& name : only) {
    bool known = false;
    for (const StressCase& c : cases) known = known || name == c.stage || name == c.name;
    if (!known) return name;
  }
  return {};
}

int RunBenchStress(const BenchStressArgs& a, const CommandContext& ctx) {
  if (const std::string unknown = UnknownName(a.only); !unknown.empty()) {
    std::fprintf(stderr,
                 "gs360 bench stress: --only: no stage or case is named '%s' (stages: pose, "
                 "intrinsics, frames, integration, geometry, mlp; cases: as the table names "
                 "them)\n",
                 unknown.c_str());
    return 2;
  }
  StressContext context;
  context.seed = a.seed;
  if (NeedsModel(a.only)) context.model = LoadModel(a, ctx.json);
  const bool table = !ctx.json && !a.markdown;
  if (table) std::printf("%-12s %-64s %6s %8s\n", "stage", "case", "result", "seconds");
  const auto outcomes = RunStress(context, a.only, [&](const StressOutcome& o) {
    if (!table) return;
    std::printf("%-12s %-64s %6s %8.2f\n", o.stage.c_str(), o.name.c_str(),
                !o.passed ? "FAIL"
                : o.limit ? "limit"
                          : "pass",
                o.seconds);
    std::printf("    %s\n", o.observed.c_str());
    std::fflush(stdout);
  });
  int failed = 0;
  for (const StressOutcome& o : outcomes) failed += o.passed ? 0 : 1;
  if (ctx.json) {
    std::printf("%s\n", StressOutcomesToJson(outcomes).dump(2).c_str());
  } else if (a.markdown) {
    std::printf("%s", StressOutcomesToMarkdown(outcomes).c_str());
  } else {
    std::printf("%zu case%s: %zu passed, %d failed\n", outcomes.size(),
                outcomes.size() == 1 ? "" : "s", outcomes.size() - failed, failed);
  }
  return failed == 0 ? 0 : 1;
}

}  // namespace

void RegisterStressBench(CLI::App& bench, CommandContext& ctx) {
  static BenchStressArgs a;
  auto* cmd = bench.add_subcommand(
      "stress", "Numerical stages at their edges: each case's tolerance or error, and the outcome");
  cmd->add_option("--only", a.only, "Only these stages or cases (comma-separated)")->delimiter(',');
  cmd->add_option("--seed", a.seed, "Seed of the cases' random draws");
  cmd->add_option("--model", a.model,
                  "A model bundle for the frame cases; default: one calibrated on the virtual rig");
  cmd->add_option("--cache", a.cache, "Where the default model is kept (~/.cache/gs360)");
  cmd->add_flag("--markdown", a.markdown,
                "Print the outcomes as a Markdown table (docs/stress.md)");
  cmd->callback([&ctx] { ctx.exit_code = RunBenchStress(a, ctx); });
}

}  // namespace gs360::cli
