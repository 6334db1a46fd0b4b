// `gs360 bench heldout`: rigs the project has never seen (cli/heldout_rigs.h), each through the
// default plan, the acquisition and the calibration on the virtual rig, validated against the
// simulator's physical truth. One row per rig: what was planned, captured and failed (by reason),
// the coverage gaps, the machine time, every accuracy target and the pose. Rows go to a JSON-lines
// file as each rig ends, so an interrupted benchmark resumes where it stopped; text, --json or a
// markdown table for docs/benchmarks.md at the end.

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "base/format.h"
#include "calib/report.h"
#include "capture/impression.h"
#include "cli/commands.h"
#include "cli/daemon_client.h"
#include "cli/heldout_rigs.h"
#include "cli/sim_args.h"
#include "cli/sim_bridge.h"
#include "cli/sim_truth.h"
#include "run/calibration_inputs.h"
#include "run/run_engine.h"
#include "sim/tactile_camera.h"
#include "sim/virtual_rig.h"

namespace gs360::cli {
namespace {

using Json = nlohmann::json;
using Clock = std::chrono::steady_clock;

struct HeldoutArgs {
  std::vector<std::string> seeds = {"1-10"};
  std::vector<std::string> own;  // the project's own shapes, as extra rows
  std::string out = "heldout.jsonl";
  std::string work;            // default: <out without extension>-runs
  int probes = 0;              // candidates; 0: the plan's default (sized in machine time)
  double machine_hours = 0.0;  // the plan's machine time; 0: the default
  int max_epochs = 0;
  bool markdown = false;
};

double Since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

// "1-10,15" -> 1..10, 15. Throws std::invalid_argument naming the bad item.
std::vector<std::uint64_t> ParseSeeds(const std::vector<std::string>& items) {
  std::vector<std::uint64_t> seeds;
  for (const std::string& item : items) {
    std::size_t dash = item.find('-');
    try {
      std::size_t used = 0;
      const std::uint64_t a = std::stoull(item.substr(0, dash), &used);
      std::uint64_t b = a;
      if (dash != std::string::npos) b = std::stoull(item.substr(dash + 1), &used);
      if (b < a || b - a > 100000) throw std::invalid_argument("range");
      for (std::uint64_t s = a; s <= b; ++s) seeds.push_back(s);
    } catch (const std::exception&) {
      throw std::invalid_argument("--seeds: \"" + item + "\" is not a seed or a range A-B");
    }
  }
  return seeds;
}

std::string Category(const std::string& error) {
  if (error.rfind("no impression", 0) == 0) return "impression";
  if (error.find("machine reports") != std::string::npos) return "position";
  if (error.find("frame") != std::string::npos) return "frame";
  return "other";
}

// Plans (or finds the run planned before), acquires and records the acquisition's figures.
struct Acquisition {
  std::filesystem::path db;
  std::int64_t run_id = 0;
};

Acquisition Acquire(const HeldoutRig& rig, const RunConfig& config,
                    const std::filesystem::path& dir, Json& row) {
  Acquisition a{dir / "gs360.db", 0};
  RunEngine engine(a.db);
  const std::filesystem::path state = dir / "run.json";
  Json saved = Json::object();
  if (std::ifstream in(state); in) saved = Json::parse(in, nullptr, false);
  if (saved.is_object() && saved.contains("run_id")) {
    row.update(saved["plan"]);
    a.run_id = saved["run_id"].get<std::int64_t>();
  } else {
    ProbePlan plan;
    a.run_id = engine.CreateRun(config, &plan);
    Json p = {{"candidates", plan.candidates},
              {"planned", plan.probes.size()},
              {"machine_h", plan.estimate.Total() / 3600.0},
              {"gaps", plan.coverage_gaps.size()},
              {"largest_gap",
               plan.coverage_gaps.empty() ? std::string() : plan.coverage_gaps[0].Describe()},
              {"small_imprints", plan.small_imprints.probes},
              {"small_imprints_share", plan.small_imprints.Share()},
              {"advice", PlanAdvice(plan)}};
    row.update(p);
    std::ofstream out(state);
    out << Json{{"run_id", a.run_id}, {"plan", p}}.dump() << "\n";
    if (!out.flush()) throw std::runtime_error("cannot write " + state.string());
  }
  RunDatabase db(a.db);
  if (db.GetRun(a.run_id)->state != RunState::kDone) {
    ExecuteOnVirtualRig(engine, a.run_id, config, "rig " + rig.config.filename().string());
  }
  std::map<std::string, int> failed;
  int captured = 0;
  for (const ProbeRecord& p : db.ListProbes(a.run_id)) {
    if (p.state == ProbeState::kCaptured) ++captured;
    if (p.state == ProbeState::kFailed) ++failed[Category(p.last_error)];
  }
  int failed_total = 0;
  for (const auto& [why, n] : failed) failed_total += n;
  row["captured"] = captured;
  row["failed"] = failed_total;
  row["failed_by_reason"] = failed;
  return a;
}

// The presses failed for leaving no impression, against the truth: each one's mark, the largest
// change the simulator's noise-free frame of the ball where the machine pressed makes to its
// noise-free no-contact frame (DifferenceMagnitude over 2 px, DN). "failed_no_mark" counts those
// under what calibration's impression finder takes (ImpressionOptions::min_peak_dn): a fin or the
// gel hides the spot from the true camera, or it shows too few pixels; the press check was right
// to fail those. The others had a mark it missed in the noise.
void FailedMarks(const Acquisition& a, const VirtualRig& rig, Json& row) {
  RunDatabase db(a.db);
  std::vector<ProbeRecord> failed;
  for (const ProbeRecord& p : db.ListProbes(a.run_id)) {
    if (p.state == ProbeState::kFailed && Category(p.last_error) == "impression") {
      failed.push_back(p);
    }
  }
  std::vector<double> marks;
  if (!failed.empty()) {
    TactileCameraOptions options = rig.options().camera;
    options.sensor.noise = false;
    TactileCamera camera(rig.rig(), options);
    const cv::Mat reference = camera.RenderReference(0);
    for (const ProbeRecord& p : failed) {
      const cv::Mat press =
          camera.RenderAtBall(rig.rig()->BallCenterSensor(p.plan.press_machine), 0);
      double largest = 0.0;
      cv::minMaxLoc(DifferenceMagnitude(press, reference, cv::Mat(), 2.0, "bench"), nullptr,
                    &largest);
      marks.push_back(std::round(10.0 * largest) / 10.0);
    }
  }
  std::sort(marks.begin(), marks.end());
  const double usable = ImpressionOptions{}.min_peak_dn;
  row["failed_no_mark"] =
      std::count_if(marks.begin(), marks.end(), [&](double m) { return m < usable; });
  row["failed_mark_dn"] = marks;
}

void Calibrate(const Acquisition& a, const VirtualRig& rig, const std::filesystem::path& dir,
               int max_epochs, Json& row) {
  RunDatabase db(a.db);
  CalibrationOptions options;
  if (max_epochs > 0) options.train.max_epochs = max_epochs;
  options.export_dir = dir / "model";
  const SimValidationTruth truth(rig.rig(), rig.options().camera.gel);
  const auto t0 = Clock::now();
  const CalibrationResult result = RunCalibration(
      db, a.run_id, CalibrationInputsFor(db, a.run_id, dir / "checkerboards"), options, &truth);
  row["calibration_s"] = Since(t0);
  Json targets = Json::object();
  bool pass = true;
  for (const Json& t : ValidationTargets(result.validation)) {
    targets[t.value("name", std::string())] = t;
    pass = pass && t.value("pass", false);
  }
  row["targets"] = targets;
  row["pass"] = pass;
  // The same figures against the rig's nominal geometry: what a real run (and its stop rule)
  // can judge, for the gap between the two.
  Json nominal = result.validation;
  nominal["truths"] = Json::array({"rigid"});
  Json rigid = Json::object();
  for (const Json& t : ValidationTargets(nominal)) rigid[t.value("name", std::string())] = t;
  row["rigid_targets"] = rigid;
}

// One rig, start to end; a rig that cannot be planned or acquired is a row with its error.
Json RunRig(const HeldoutRig& rig, const std::filesystem::path& work, const HeldoutArgs& args) {
  Json row = {{"rig", rig.config.stem().string()},
              {"seed", rig.seed},
              {"family", rig.family},
              {"description", rig.description},
              {"config", rig.config.string()},
              {"pass", false}};
  const auto t0 = Clock::now();
  try {
    SimArgs sim;
    std::uint64_t seed = rig.seed;
    RunConfig config = LoadHeldoutRig(rig, &sim, &seed);
    config.name = rig.config.stem().string();
    if (args.probes > 0) {
      config.plan.probe_count = args.probes;
      config.plan.machine_hours = 0.0;  // a count asked for is the count planned
    }
    if (args.machine_hours > 0.0) config.plan.machine_hours = args.machine_hours;
    const std::filesystem::path dir = work / config.name;
    std::filesystem::create_directories(dir);
    VirtualSetup setup = MakeVirtualSetup(config, 0.0, seed, {}, {},
                                          [&](VirtualRigOptions& o) { ApplySimArgs(sim, &o); });
    if (!std::filesystem::exists(dir / "checkerboards")) {
      const std::filesystem::path tmp = dir / "checkerboards.tmp";
      std::filesystem::remove_all(tmp);
      WriteSimCheckerboards(*setup.rig->rig(), tmp, 16, seed);
      std::filesystem::rename(tmp, dir / "checkerboards");
    }
    const Acquisition a = Acquire(rig, setup.config, dir, row);
    row["acquisition_s"] = Since(t0);
    FailedMarks(a, *setup.rig, row);
    Calibrate(a, *setup.rig, dir, args.max_epochs, row);
  } catch (const std::exception& e) {
    row["error"] = e.what();
  }
  row["wall_s"] = Since(t0);
  return row;
}

std::string TargetCell(const Json& row, const char* name, int digits) {
  if (!row.contains("targets") || !row["targets"].contains(name)) return "-";
  const Json& t = row["targets"][name];
  if (t.value("no_data", false)) return "no data";
  if (!t["value"].is_number()) return "-";
  return FormatFixed(t["value"].get<double>(), digits) + (t.value("pass", false) ? "" : " ✗");
}

std::string Lost(const Json& row) {
  const int failed = row.value("failed", 0);
  const int pressed = row.value("captured", 0) + failed;
  if (pressed == 0) return "-";
  std::string s = std::to_string(failed) + " (" +
                  FormatFixed(100.0 * failed / static_cast<double>(pressed), 1) + " %)";
  if (row.contains("failed_by_reason")) {
    std::string why;
    for (const auto& [reason, n] : row["failed_by_reason"].items()) {
      why += (why.empty() ? "" : ", ") + reason + " " + std::to_string(n.get<int>());
    }
    if (!why.empty()) s += " " + why;
  }
  if (const int no_mark = row.value("failed_no_mark", 0); no_mark > 0) {
    s += ", " + std::to_string(no_mark) + " with no usable mark";
  }
  return s;
}

std::string MarkdownTable(const std::vector<Json>& rows) {
  std::string s =
      "| rig | sensor | planned | captured | failed | machine | mean mm | > 50 deg mm | peak mm "
      "| normal deg | camera mm | camera deg | all targets |\n"
      "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n";
  for (const Json& r : rows) {
    s += "| " + r.value("rig", std::string()) + " | " + r.value("description", std::string()) +
         " | " + std::to_string(r.value("planned", 0)) + " of " +
         std::to_string(r.value("candidates", 0)) + " | " + std::to_string(r.value("captured", 0)) +
         " | " + Lost(r) + " | " + FormatDuration(r.value("machine_h", 0.0) * 3600.0) + " | " +
         TargetCell(r, "mean depth error", 4) + " | " +
         TargetCell(r, "depth error seen > 50 deg", 4) + " | " +
         TargetCell(r, "peak indentation error", 4) + " | " +
         TargetCell(r, "median normal error", 2) + " | " + TargetCell(r, "camera position", 4) +
         " | " + TargetCell(r, "camera rotation", 4) + " | " +
         (r.contains("error") ? "error: " + r["error"].get<std::string>()
                              : (r.value("pass", false) ? "pass" : "**miss**")) +
         " |\n";
  }
  return s;
}

std::string Summary(const std::vector<Json>& rows) {
  int pass = 0, lost_over_1pct = 0, shown_over_1pct = 0, over_hour = 0;
  double worst_lost = 0.0, worst_shown = 0.0;
  for (const Json& r : rows) {
    if (r.value("pass", false)) ++pass;
    const int failed = r.value("failed", 0);
    const int pressed = r.value("captured", 0) + failed;
    const double lost = pressed > 0 ? 100.0 * failed / pressed : 0.0;
    // Of the presses that left a usable mark: those the check should have counted.
    const int no_mark = r.value("failed_no_mark", 0);
    const double shown = pressed > no_mark ? 100.0 * (failed - no_mark) / (pressed - no_mark) : 0.0;
    worst_lost = std::max(worst_lost, lost);
    worst_shown = std::max(worst_shown, shown);
    if (lost > 1.0) ++lost_over_1pct;
    if (shown > 1.0) ++shown_over_1pct;
    if (r.value("machine_h", 0.0) > 1.0) ++over_hour;
  }
  return std::to_string(pass) + " of " + std::to_string(rows.size()) + " rigs meet every target; " +
         std::to_string(lost_over_1pct) + " lose more than 1 % of their presses (worst " +
         FormatFixed(worst_lost, 1) + " %), " + std::to_string(shown_over_1pct) +
         " more than 1 % of those that left a usable mark (worst " + FormatFixed(worst_shown, 1) +
         " %); " + std::to_string(over_hour) + " plan over 1 h of machine time\n";
}

std::map<std::string, Json> ReadRows(const std::filesystem::path& path) {
  std::map<std::string, Json> rows;
  std::ifstream in(path);
  std::string line;
  while (std::getline(in, line)) {
    // A line cut short by a kill does not parse: that rig runs again.
    const Json row = Json::parse(line, nullptr, false);
    if (row.is_object() && row.contains("rig")) rows[row["rig"].get<std::string>()] = row;
  }
  return rows;
}

int RunHeldout(const HeldoutArgs& a, const CommandContext& ctx) {
  const std::filesystem::path out = std::filesystem::absolute(a.out);
  const std::filesystem::path work = a.work.empty()
                                         ? out.parent_path() / (out.stem().string() + "-runs")
                                         : std::filesystem::path(a.work);
  std::filesystem::create_directories(work);
  std::vector<HeldoutRig> rigs;
  for (const std::uint64_t seed : ParseSeeds(a.seeds)) {
    rigs.push_back(DrawHeldoutRig(seed, work / "rigs"));
  }
  for (const std::string& shape : a.own) rigs.push_back(OwnRig(shape, 1, work / "rigs"));
  std::map<std::string, Json> done = ReadRows(out);
  std::vector<Json> rows;
  const auto t0 = Clock::now();
  int ran = 0, to_run = 0;
  for (const HeldoutRig& rig : rigs) to_run += done.count(rig.config.stem().string()) ? 0 : 1;
  for (const HeldoutRig& rig : rigs) {
    const std::string key = rig.config.stem().string();
    if (done.count(key)) {
      rows.push_back(done[key]);
      continue;
    }
    std::fprintf(
        stderr, "[%d/%d] %s: %s%s\n", ran + 1, to_run, key.c_str(), rig.description.c_str(),
        ran > 0 ? (", ETA " + FormatDuration(Since(t0) / ran * (to_run - ran))).c_str() : "");
    Json row = RunRig(rig, work, a);
    ++ran;
    std::ofstream append(out, std::ios::app);
    append << row.dump() << "\n";
    if (!append.flush()) throw std::runtime_error("cannot append to " + out.string());
    std::fprintf(stderr, "  %s\n",
                 row.contains("error")
                     ? ("error: " + row["error"].get<std::string>()).c_str()
                     : (row.value("pass", false) ? "every target met" : "misses a target"));
    rows.push_back(std::move(row));
  }
  if (ctx.json) {
    std::printf("%s\n", Json{{"rows", rows}, {"summary", Summary(rows)}}.dump(2).c_str());
  } else if (a.markdown) {
    std::printf("%s\n%s", MarkdownTable(rows).c_str(), Summary(rows).c_str());
  } else {
    for (const Json& r : rows) {
      std::printf(
          "%-14s %s\n  planned %d of %d, captured %d, failed %s, machine %s\n  %s\n",
          r.value("rig", std::string()).c_str(), r.value("description", std::string()).c_str(),
          r.value("planned", 0), r.value("candidates", 0), r.value("captured", 0), Lost(r).c_str(),
          FormatDuration(r.value("machine_h", 0.0) * 3600.0).c_str(),
          r.contains("error") ? ("error: " + r["error"].get<std::string>()).c_str()
                              : ("mean " + TargetCell(r, "mean depth error", 4) + ", > 50 deg " +
                                 TargetCell(r, "depth error seen > 50 deg", 4) + ", peak " +
                                 TargetCell(r, "peak indentation error", 4) + ", normal " +
                                 TargetCell(r, "median normal error", 2) + ", camera " +
                                 TargetCell(r, "camera position", 4) + " mm " +
                                 TargetCell(r, "camera rotation", 4) +
                                 " deg: " + (r.value("pass", false) ? "pass" : "MISS"))
                                    .c_str());
    }
    std::printf("%s", Summary(rows).c_str());
  }
  return kExitOk;
}

}  // namespace

void RegisterHeldoutBench(CLI::App& bench, CommandContext& ctx) {
  static HeldoutArgs a;
  auto* cmd = bench.add_subcommand(
      "heldout",
      "Rigs never seen (shapes, meshes, LEDs, cameras, noise drawn from a seed) through the "
      "default plan, acquisition and calibration; one row per rig against the physical truth");
  cmd->add_option("--seeds", a.seeds,
                  "Rig seeds and ranges (1-10 is the documented set, docs/benchmarks.md)")
      ->delimiter(',')
      ->capture_default_str();
  cmd->add_option("--own", a.own, "Also the project's own shapes at their defaults")
      ->delimiter(',')
      ->check(CLI::IsMember({"cylinder", "cone", "spline"}));
  cmd->add_option("--out", a.out, "Rows as JSON lines (rigs already in it are not run again)")
      ->capture_default_str();
  cmd->add_option("--work", a.work, "Rig files and runs (default: <out>-runs)");
  cmd->add_option(
         "--probes", a.probes,
         "Exactly this many candidates per plan (default: as many as fit the machine time)")
      ->check(CLI::Range(20, 20000));
  cmd->add_option("--machine-hours", a.machine_hours,
                  "Machine time each plan is sized to (default: gs360d's, 1 h)")
      ->check(CLI::Range(0.01, 100.0));
  cmd->add_option("--max-epochs", a.max_epochs, "Training epochs at most (default: the trainer's)")
      ->check(CLI::Range(1, 1000));
  cmd->add_flag("--markdown", a.markdown, "Print a markdown table (for docs/benchmarks.md)");
  cmd->callback([&ctx] { ctx.exit_code = RunHeldout(a, ctx); });
}

}  // namespace gs360::cli
