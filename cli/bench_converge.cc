// `gs360 bench converge`: what `--until-converged` saves against the fixed default, per shape, on
// the virtual rig. Each shape's default plan is acquired once (instant motion, in rounds), then
// calibrated at every round's end in turn, exactly as gs360d's checkpoints do (the probes below
// the round's end, judged on the run's own held-out probes, no ground truth), until the stop rule
// (daemon/convergence.h Judge) says converged. The machine goes on while a checkpoint
// calibrates: on the real rig that is the checkpoint's calibration time over the plan's machine
// time per probe, which decides how many probes a live run presses before it stops. The model a
// live run keeps (the converged checkpoint's) and the whole run's (the fixed default) are then
// validated against the simulator's physical truth.
//
// A live run on the virtual rig runs its machine at a time scale: its calibrations, on the same
// two cores as the simulator, then lag by several rounds, which a real rig's do not. This replay
// takes the machine's time from the planner instead.

#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>

#include <nlohmann/json.hpp>

#include "base/format.h"
#include "calib/report.h"
#include "cli/commands.h"
#include "cli/sim_bridge.h"
#include "cli/sim_truth.h"
#include "daemon/convergence.h"
#include "run/calibration_inputs.h"
#include "run/run_engine.h"

namespace gs360::cli {
namespace {

using Json = nlohmann::json;

struct ConvergeArgs {
  std::vector<std::string> shapes = {"cylinder", "cone", "spline"};
  int candidates = PlanOptions{}.probe_count;
  int round = kDefaultConvergeRound;
  double min_improvement = ConvergeConfig{}.min_improvement;
  std::uint64_t seed = 1;
  std::string work;         // default: a temp folder, removed afterwards
  std::FILE* log = stdout;  // progress (stderr with --json)
};

// One shape's outcome.
struct ShapeResult {
  std::string shape;
  int plan_probes = 0;
  double plan_machine_s = 0.0;
  std::vector<Checkpoint> curve;
  bool converged = false;
  int stop_limit = 0;  // the converged checkpoint's plan index limit (0: none)
  int pressed = 0;     // probes a live run presses before it stops
  double pressed_machine_s = 0.0;
  Json fixed_targets, converged_targets;  // physical truth
};

double Total(const CalibrationResult& r) {
  double s = 0.0;
  for (const StageReport& stage : r.stages) s += stage.seconds;
  return s;
}

// The calibration of the probes below `limit` (0: all), judged as gs360d does or, with `truth`,
// against it.
CalibrationResult Calibrate(RunDatabase& db, std::int64_t run_id, const CalibrationInputs& inputs,
                            int limit, const std::filesystem::path& export_dir,
                            const ValidationTruth* truth) {
  CalibrationOptions options;
  options.plan_index_limit = limit;
  options.export_dir = export_dir;
  return RunCalibration(db, run_id, inputs, options, truth);
}

// Calibrates round after round until the stop rule says converged; fills the curve and the
// stop point.
void Replay(RunDatabase& db, std::int64_t run_id, const CalibrationInputs& inputs,
            const ConvergeArgs& a, const std::filesystem::path& dir, ShapeResult* r) {
  ConvergeConfig rule;
  rule.min_improvement = a.min_improvement;
  const double s_per_probe = r->plan_machine_s / std::max(1, r->plan_probes);
  for (int limit = a.round; limit < r->plan_probes + a.round; limit += a.round) {
    const int bound = std::min(limit, r->plan_probes);
    // As gs360d: a round's end within half a round of the plan's is left to the whole run.
    if (bound < r->plan_probes && r->plan_probes - bound < a.round / 2) continue;
    const CalibrationResult c = Calibrate(db, run_id, inputs, bound, dir / "model", nullptr);
    Checkpoint cp;
    cp.plan_index_limit = bound;
    cp.probes = c.validation.value("probes_captured", std::int64_t{0});
    cp.state = "done";
    cp.targets = ValidationTargets(c.validation);
    cp.seconds = Total(c);
    r->curve.push_back(cp);
    std::fprintf(a.log, "  checkpoint at %lld probes: mean %.4f mm, > 50 deg %.4f mm, %s, %.0f s\n",
                 static_cast<long long>(cp.probes), cp.Value("mean depth error").value_or(NAN),
                 cp.Value("depth error seen > 50 deg").value_or(NAN),
                 cp.TargetsMet() ? "every target met" : "a target missed", cp.seconds);
    std::fflush(a.log);
    const Verdict v = Judge(r->curve, rule);
    if (v.converged && bound < r->plan_probes) {
      r->converged = true;
      r->stop_limit = bound;
      // The machine went on while this checkpoint calibrated.
      const int lag = static_cast<int>(std::ceil(cp.seconds / s_per_probe));
      r->pressed = std::min(r->plan_probes, bound + lag);
      std::fprintf(a.log, "  %s; a live run presses %d more probes meanwhile\n", v.reason.c_str(),
                   lag);
      return;
    }
  }
  r->pressed = r->plan_probes;
}

ShapeResult RunShape(const std::string& shape, const ConvergeArgs& a,
                     const std::filesystem::path& dir) {
  std::filesystem::create_directories(dir);
  RunConfig config;
  config.name = "converge-" + shape;
  config.rig.shape.shape = ParseSensorShape(shape);
  config.plan.probe_count = a.candidates;
  config.plan.seed = a.seed;
  config.plan.checkpoint_probes = a.round;
  config.converge.enabled = true;
  VirtualSetup setup = MakeVirtualSetup(config, 0.0, a.seed);
  WriteSimCheckerboards(*setup.rig->rig(), dir / "checkerboards", 16, a.seed);
  RunEngine engine(dir / "run.db");
  ProbePlan plan;
  const std::int64_t run_id = engine.CreateRun(setup.config, &plan);
  ShapeResult r;
  r.shape = shape;
  r.plan_probes = static_cast<int>(plan.probes.size());
  r.plan_machine_s = plan.estimate.Total();
  std::fprintf(a.log, "%s: %d probes in rounds of %d, %s of machine time\n", shape.c_str(),
               r.plan_probes, a.round, FormatDuration(r.plan_machine_s).c_str());
  ExecuteOnVirtualRig(engine, run_id, setup.config, "acquisition " + shape);
  RunDatabase db(dir / "run.db");
  const CalibrationInputs inputs = CalibrationInputsFor(db, run_id, dir / "checkerboards");
  Replay(db, run_id, inputs, a, dir, &r);
  const std::vector<PlannedProbe> pressed(plan.probes.begin(), plan.probes.begin() + r.pressed);
  r.pressed_machine_s = EstimatePlan(pressed, {plan.start_machine}, setup.config.plan).Total();
  const SimValidationTruth truth(setup.rig->rig(), setup.rig->options().camera.gel);
  r.fixed_targets =
      ValidationTargets(Calibrate(db, run_id, inputs, 0, dir / "model", &truth).validation);
  r.converged_targets =
      r.converged
          ? ValidationTargets(
                Calibrate(db, run_id, inputs, r.stop_limit, dir / "model", &truth).validation)
          : r.fixed_targets;
  return r;
}

std::string Figures(const Json& targets) {
  std::string out;
  bool all = true;
  for (const Json& t : targets) {
    all = all && t.value("pass", false);
    const std::string name = t.value("name", std::string());
    if (name == "mean depth error" || name == "depth error seen > 50 deg" ||
        name == "peak indentation error") {
      out += (t["value"].is_number() ? FormatFixed(t["value"].get<double>(), 4) : "-") + " | ";
    }
  }
  return out + (all ? "yes" : "no");
}

Json ResultJson(const ShapeResult& r) {
  Json curve = Json::array();
  for (const Checkpoint& c : r.curve) curve.push_back(c.ToJson());
  return {{"shape", r.shape},
          {"plan_probes", r.plan_probes},
          {"plan_machine_s", r.plan_machine_s},
          {"converged", r.converged},
          {"stop_probes", r.stop_limit},
          {"pressed", r.pressed},
          {"pressed_machine_s", r.pressed_machine_s},
          {"checkpoints", curve},
          {"fixed_targets", r.fixed_targets},
          {"converged_targets", r.converged_targets}};
}

void PrintTable(const std::vector<ShapeResult>& results) {
  std::printf(
      "\n| shape | run | probes pressed | machine time | mean mm | > 50 deg mm | peak mm | every "
      "target |\n|---|---|---|---|---|---|---|---|\n");
  for (const ShapeResult& r : results) {
    std::printf("| %s | fixed default | %d | %s | %s |\n", r.shape.c_str(), r.plan_probes,
                FormatDuration(r.plan_machine_s).c_str(), Figures(r.fixed_targets).c_str());
    const std::string how = r.converged
                                ? "until converged (stops at " + std::to_string(r.stop_limit) + ")"
                                : "until converged (never: the whole plan)";
    std::printf("| %s | %s | %d | %s (%.0f %%) | %s |\n", r.shape.c_str(), how.c_str(), r.pressed,
                FormatDuration(r.pressed_machine_s).c_str(),
                100.0 * r.pressed_machine_s / std::max(1.0, r.plan_machine_s),
                Figures(r.converged_targets).c_str());
  }
}

}  // namespace

void RegisterConvergeBench(CLI::App& bench, CommandContext& ctx) {
  static ConvergeArgs a;
  auto* cmd = bench.add_subcommand(
      "converge",
      "What --until-converged saves: each shape's default plan calibrated round after round "
      "until the stop rule holds, against the fixed default, validated against the truth");
  cmd->add_option("--shapes", a.shapes, "Sensor shapes")
      ->check(CLI::IsMember({"cylinder", "cone", "spline"}))
      ->capture_default_str();
  cmd->add_option("--candidates", a.candidates, "Candidate points (the default plan's)")
      ->check(CLI::Range(50, 100000))
      ->capture_default_str();
  cmd->add_option("--round", a.round, "Probes per round")
      ->check(CLI::Range(20, 10000))
      ->capture_default_str();
  cmd->add_option("--min-improvement", a.min_improvement, "The stop rule's flat improvement")
      ->check(CLI::Range(0.0, 0.99))
      ->capture_default_str();
  cmd->add_option("--seed", a.seed, "Seed (sampling, hidden camera, noise)")->capture_default_str();
  cmd->add_option("--work", a.work, "Where the acquisitions go (default: a temp folder, removed)");
  cmd->callback([&ctx] {
    a.log = ctx.json ? stderr : stdout;
    const bool temp = a.work.empty();
    const std::filesystem::path work = temp ? std::filesystem::temp_directory_path() /
                                                  ("gs360-converge-" + std::to_string(::getpid()))
                                            : std::filesystem::path(a.work);
    std::vector<ShapeResult> results;
    for (const std::string& shape : a.shapes) results.push_back(RunShape(shape, a, work / shape));
    if (temp) std::filesystem::remove_all(work);
    if (ctx.json) {
      Json out = Json::array();
      for (const ShapeResult& r : results) out.push_back(ResultJson(r));
      std::printf("%s\n", Json{{"shapes", out}}.dump(1).c_str());
    } else {
      PrintTable(results);
    }
  });
}

}  // namespace gs360::cli
