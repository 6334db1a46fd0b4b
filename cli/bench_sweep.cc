// `gs360 bench sweep`: run time against error. A grid of acquisitions on the virtual rig (shape x
// kept probes x seed) and calibrations of each (MLP width and depth, epochs, contact samples per
// probe, input features), one CSV row per calibration with the machine time the real rig would
// take (the planner's estimate at [plan.machine]'s feeds), the calibration's time per stage and
// the validation against the simulator's physical truth. Rows already in the CSV are skipped, so
// an interrupted sweep resumes; acquisitions are kept in a work folder and resumed too. A plot
// (PNG) of error against hours with the targets and the Pareto front, and a recommendation, over
// every row of the CSV (a sweep run in parts plots as one).

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "base/atomic_file.h"
#include "base/format.h"
#include "calib/report.h"
#include "cli/commands.h"
#include "cli/daemon_client.h"
#include "cli/sim_bridge.h"
#include "cli/sim_truth.h"
#include "run/calibration_inputs.h"
#include "run/run_engine.h"
#include "sim/virtual_rig.h"

namespace gs360::cli {
namespace {

using Json = nlohmann::json;
using Clock = std::chrono::steady_clock;

struct SweepArgs {
  std::string out = "sweep.csv";
  std::string work;  // default: <out without .csv>-runs
  std::string plot;  // default: <out without .csv>.png
  std::vector<std::string> shapes = {"cylinder", "cone", "spline"};
  std::vector<int> probes = {250, 500, 1000, 2000, 5000, 10000};
  std::vector<std::uint64_t> seeds = {1, 2};
  std::vector<int> widths = {128};
  std::vector<int> depths = {3};
  std::vector<int> epochs = {60};
  std::vector<int> samples = {500};
  std::vector<std::string> features = {"fourier"};
  bool dry_run = false;
};

// One calibration of the grid.
struct Config {
  std::string shape;
  int probes = 0;
  std::uint64_t seed = 1;
  int width = 0, depth = 0, epochs = 0, samples = 0;
  std::string features;

  std::string Key() const {
    return shape + "," + std::to_string(probes) + "," + std::to_string(seed) + "," +
           std::to_string(width) + "," + std::to_string(depth) + "," + std::to_string(epochs) +
           "," + std::to_string(samples) + "," + features;
  }
  std::string Acquisition() const {
    return shape + "-p" + std::to_string(probes) + "-s" + std::to_string(seed);
  }
};

const char* const kKeyColumns = "shape,probes,seed,width,depth,epochs,samples,features";
// The figures of a row, after the key columns, in this order.
const std::vector<std::string>& ResultColumns() {
  static const std::vector<std::string> columns = [] {
    std::vector<std::string> c = {"kept", "machine_h", "acquisition_s", "calibration_s"};
    for (const std::string& stage : CalibrationStages()) c.push_back("s_" + stage);
    for (const char* f : {"mean_mm", "band50_mm", "peak_mm", "normal_deg", "pose_mm", "pose_deg",
                          "pass", "total_h"}) {
      c.push_back(f);
    }
    return c;
  }();
  return columns;
}

std::vector<Config> Grid(const SweepArgs& a) {
  std::vector<Config> grid;
  for (const std::string& shape : a.shapes)
    for (const int probes : a.probes)
      for (const std::uint64_t seed : a.seeds)
        for (const int width : a.widths)
          for (const int depth : a.depths)
            for (const int epochs : a.epochs)
              for (const int samples : a.samples)
                for (const std::string& features : a.features)
                  grid.push_back({shape, probes, seed, width, depth, epochs, samples, features});
  return grid;
}

std::vector<std::string> SplitCsv(const std::string& line) {
  std::vector<std::string> out;
  std::stringstream in(line);
  std::string cell;
  while (std::getline(in, cell, ',')) out.push_back(cell);
  if (!line.empty() && line.back() == ',') out.emplace_back();
  return out;
}

// The rows of an earlier sweep, by key (the first eight cells); a header that is not this
// sweep's is an error naming the file.
std::map<std::string, std::vector<std::string>> ReadRows(const std::filesystem::path& csv) {
  std::map<std::string, std::vector<std::string>> rows;
  std::ifstream in(csv);
  if (!in) return rows;
  std::string header;
  std::getline(in, header);
  std::string expected = kKeyColumns;
  for (const std::string& c : ResultColumns()) expected += "," + c;
  if (header != expected) {
    throw std::runtime_error(csv.string() +
                             ": line 1 is not this sweep's header; move the file away or pass "
                             "another --out (expected: " +
                             expected + ")");
  }
  std::string line;
  int number = 1;
  const std::size_t cells = 8 + ResultColumns().size();
  while (std::getline(in, line)) {
    ++number;
    if (line.empty()) continue;
    std::vector<std::string> row = SplitCsv(line);
    // A row cut short by a kill is dropped: its calibration runs again.
    if (row.size() != cells) continue;
    std::string key = row[0];
    for (int i = 1; i < 8; ++i) key += "," + row[static_cast<std::size_t>(i)];
    rows[key] = std::move(row);
  }
  return rows;
}

TrainOptions TrainFor(const Config& c) {
  TrainOptions t;
  t.hidden.assign(static_cast<std::size_t>(c.depth), c.width);
  t.max_epochs = c.epochs;
  if (c.features == "plain") t.fourier = {0, 0, 1.0f};
  return t;
}

// What an acquisition keeps beside its database: the plan's figures and the compute time of
// every stage result it holds (by stage input hash), so cached stages still count.
struct Sidecar {
  std::filesystem::path path;
  Json data = Json::object();

  void Load() {
    std::ifstream in(path);
    if (in) data = Json::parse(in, nullptr, /*allow_exceptions=*/false);
    if (!data.is_object()) data = Json::object();
  }
  void Save() const { WriteFileAtomically(path, data.dump(1) + "\n"); }
};

// A virtual rig per acquisition: the same shape and seed give the same hidden truth, also after
// a restart, so an acquisition kept from an earlier sweep validates against its own rig.
struct Acquired {
  RunConfig config;
  std::unique_ptr<VirtualRig> rig;
  std::filesystem::path db;
  std::filesystem::path checkerboards;
  std::int64_t run_id = 0;
  Sidecar sidecar;
};

Acquired Acquire(const Config& c, const std::filesystem::path& work) {
  Acquired a;
  RunConfig config;
  config.name = "sweep-" + c.Acquisition();
  config.rig.shape.shape = ParseSensorShape(c.shape);
  config.plan.probe_count = c.probes;
  config.plan.count_is_kept = true;
  config.plan.seed = c.seed;
  VirtualSetup setup = MakeVirtualSetup(config, 0.0, c.seed);
  a.config = setup.config;
  a.rig = std::move(setup.rig);
  a.db = work / (c.Acquisition() + ".db");
  a.checkerboards = work / (c.Acquisition() + "-checkerboards");
  a.sidecar.path = work / (c.Acquisition() + ".json");
  a.sidecar.Load();
  if (!std::filesystem::exists(a.checkerboards)) {
    // Written aside, then renamed: a kill leaves no half folder behind.
    const std::filesystem::path tmp = a.checkerboards.string() + ".tmp";
    std::filesystem::remove_all(tmp);
    WriteSimCheckerboards(*a.rig->rig(), tmp, 16, c.seed);
    std::filesystem::rename(tmp, a.checkerboards);
  }
  RunEngine engine(a.db);
  if (a.sidecar.data.contains("run_id")) {
    a.run_id = a.sidecar.data["run_id"].get<std::int64_t>();
  } else {
    ProbePlan plan;
    a.run_id = engine.CreateRun(a.config, &plan);
    a.sidecar.data["run_id"] = a.run_id;
    a.sidecar.data["machine_s"] = plan.estimate.Total();
    a.sidecar.data["kept"] = plan.probes.size();
    a.sidecar.data["acquisition_s"] = 0.0;
    a.sidecar.Save();
  }
  RunDatabase db(a.db);
  if (db.GetRun(a.run_id)->state != RunState::kDone) {
    // The stored run uses this process's virtual rig: its pty and camera socket.
    const auto t0 = Clock::now();
    ExecuteOnVirtualRig(engine, a.run_id, a.config, "acquisition " + c.Acquisition());
    a.sidecar.data["acquisition_s"] = a.sidecar.data.value("acquisition_s", 0.0) +
                                      std::chrono::duration<double>(Clock::now() - t0).count();
    a.sidecar.Save();
  }
  return a;
}

double TargetValue(const Json& targets, const std::string& name) {
  for (const Json& t : targets) {
    if (t.value("name", "") == name && t["value"].is_number()) return t["value"].get<double>();
  }
  return std::nan("");
}

std::string Cell(double v, int digits) {
  return std::isfinite(v) ? FormatFixed(v, digits) : std::string();
}

// Calibrates one configuration on its acquisition and returns the CSV cells after the key.
std::vector<std::string> Calibrate(const Config& c, Acquired& a) {
  RunDatabase db(a.db);
  CalibrationOptions options;
  options.train = TrainFor(c);
  options.dataset.max_contact_samples_per_probe = c.samples;
  options.export_dir = a.db.parent_path() / (c.Acquisition() + "-model");
  const SimValidationTruth truth(a.rig->rig(), a.rig->options().camera.gel);
  const CalibrationResult result = RunCalibration(
      db, a.run_id, CalibrationInputsFor(db, a.run_id, a.checkerboards), options, &truth);

  Json& times = a.sidecar.data["stage_seconds"];
  if (!times.is_object()) times = Json::object();
  std::map<std::string, double> stage_s;
  double calibration_s = 0.0;
  for (const StageReport& s : result.stages) {
    if (!s.cached || !times.contains(s.input_hash)) times[s.input_hash] = s.seconds;
    stage_s[s.stage] = times[s.input_hash].get<double>();
    calibration_s += stage_s[s.stage];
  }
  a.sidecar.Save();

  const Json targets = ValidationTargets(result.validation);
  bool pass = !targets.empty();
  for (const Json& t : targets) pass = pass && t.value("pass", false);
  const double machine_h = a.sidecar.data.value("machine_s", 0.0) / 3600.0;
  std::vector<std::string> cells = {
      std::to_string(a.sidecar.data.value("kept", 0)), Cell(machine_h, 3),
      Cell(a.sidecar.data.value("acquisition_s", 0.0), 1), Cell(calibration_s, 1)};
  for (const std::string& stage : CalibrationStages()) {
    cells.push_back(stage_s.count(stage) ? Cell(stage_s[stage], 2) : "");
  }
  cells.push_back(Cell(TargetValue(targets, "mean depth error"), 4));
  cells.push_back(Cell(TargetValue(targets, "depth error seen > 50 deg"), 4));
  cells.push_back(Cell(TargetValue(targets, "peak indentation error"), 4));
  cells.push_back(Cell(TargetValue(targets, "median normal error"), 2));
  cells.push_back(Cell(TargetValue(targets, "camera position"), 4));
  cells.push_back(Cell(TargetValue(targets, "camera rotation"), 4));
  cells.push_back(pass ? "1" : "0");
  cells.push_back(Cell(machine_h + calibration_s / 3600.0, 3));
  return cells;
}

}  // namespace

// bench_sweep_plot.cc
void WriteSweepPlot(const std::vector<std::vector<std::string>>& rows,
                    const std::filesystem::path& png);
std::string SweepRecommendation(const std::vector<std::vector<std::string>>& rows);

namespace {

// A new CSV's header line (the key columns, then the results); an existing CSV is kept.
void WriteCsvHeader(const std::filesystem::path& out) {
  if (std::filesystem::exists(out)) return;
  std::ofstream header(out);
  header << kKeyColumns;
  for (const std::string& c : ResultColumns()) header << "," << c;
  header << "\n";
  if (!header.flush()) throw std::runtime_error("cannot write " + out.string());
}

// `--json`: every row of the CSV by column name, the plot and the recommendation.
void PrintSweepJson(const std::filesystem::path& out, const std::filesystem::path& plot,
                    const std::vector<std::vector<std::string>>& rows, const std::string& advice) {
  Json j = Json::array();
  std::vector<std::string> names = SplitCsv(kKeyColumns);
  for (const std::string& col : ResultColumns()) names.push_back(col);
  for (const auto& row : rows) {
    Json r = Json::object();
    for (std::size_t k = 0; k < names.size() && k < row.size(); ++k) r[names[k]] = row[k];
    j.push_back(r);
  }
  std::printf(
      "%s\n",
      Json{{"csv", out.string()}, {"plot", plot.string()}, {"rows", j}, {"recommendation", advice}}
          .dump(2)
          .c_str());
}

int RunSweep(const SweepArgs& a, const CommandContext& ctx) {
  const std::filesystem::path out = std::filesystem::absolute(a.out);
  const std::string stem = (out.parent_path() / out.stem()).string();
  const std::filesystem::path work = a.work.empty() ? stem + "-runs" : a.work;
  const std::filesystem::path plot = a.plot.empty() ? stem + ".png" : a.plot;
  std::map<std::string, std::vector<std::string>> done = ReadRows(out);
  const std::vector<Config> grid = Grid(a);
  std::vector<Config> todo;
  for (const Config& c : grid) {
    if (!done.count(c.Key())) todo.push_back(c);
  }
  std::fprintf(stderr, "sweep: %zu configurations, %zu in %s already, %zu to run (work in %s)\n",
               grid.size(), grid.size() - todo.size(), out.c_str(), todo.size(), work.c_str());
  if (a.dry_run) {
    for (const Config& c : todo) std::printf("%s\n", c.Key().c_str());
    return kExitOk;
  }
  std::filesystem::create_directories(work);
  std::filesystem::create_directories(out.parent_path());
  WriteCsvHeader(out);
  const auto t0 = Clock::now();
  std::string acquired_key;
  std::unique_ptr<Acquired> acquired;
  for (std::size_t i = 0; i < todo.size(); ++i) {
    const Config& c = todo[i];
    const double elapsed = std::chrono::duration<double>(Clock::now() - t0).count();
    std::fprintf(stderr, "[%zu/%zu] %s%s\n", i + 1, todo.size(), c.Key().c_str(),
                 i > 0 ? (", ETA " + FormatDuration(elapsed / static_cast<double>(i) *
                                                    static_cast<double>(todo.size() - i)))
                             .c_str()
                       : "");
    if (acquired_key != c.Acquisition()) {
      acquired.reset();  // its virtual rig goes before the next one starts
      acquired = std::make_unique<Acquired>(Acquire(c, work));
      acquired_key = c.Acquisition();
    }
    std::vector<std::string> row = SplitCsv(c.Key());
    for (std::string& cell : Calibrate(c, *acquired)) row.push_back(std::move(cell));
    std::ofstream append(out, std::ios::app);
    for (std::size_t k = 0; k < row.size(); ++k) append << (k ? "," : "") << row[k];
    append << "\n";
    if (!append.flush()) throw std::runtime_error("cannot append to " + out.string());
    done[c.Key()] = row;
    std::fprintf(
        stderr, "  mean %s mm, peak %s mm, machine %s h, calibration %s s: %s\n",
        row[8 + 4 + CalibrationStages().size()].c_str(),
        row[8 + 6 + CalibrationStages().size()].c_str(), row[9].c_str(), row[11].c_str(),
        row[8 + 10 + CalibrationStages().size()] == "1" ? "every target met" : "misses a target");
  }
  // The plot and the advice cover every row of the CSV, this grid's and earlier ones'.
  std::vector<std::vector<std::string>> rows;
  for (const auto& [key, row] : done) rows.push_back(row);
  WriteSweepPlot(rows, plot);
  const std::string advice = SweepRecommendation(rows);
  if (ctx.json) {
    PrintSweepJson(out, plot, rows, advice);
  } else {
    std::printf("sweep: %zu rows in %s, plot %s\n%s", rows.size(), out.c_str(), plot.c_str(),
                advice.c_str());
  }
  return kExitOk;
}

}  // namespace

void RegisterSweepBench(CLI::App& bench, CommandContext& ctx) {
  static SweepArgs a;
  auto* cmd = bench.add_subcommand(
      "sweep",
      "Run time against error: acquisitions and calibrations over a grid, one CSV row each "
      "(resumable), a plot and a recommendation");
  cmd->add_option("--out", a.out, "The CSV (rows already in it are not run again)")
      ->capture_default_str();
  cmd->add_option("--work", a.work, "Where acquisitions are kept (default: <out>-runs)");
  cmd->add_option("--plot", a.plot, "The PNG plot (default: <out>.png)");
  cmd->add_option("--shapes", a.shapes, "Sensor shapes: cylinder, cone, spline")
      ->delimiter(',')
      ->check(CLI::IsMember({"cylinder", "cone", "spline"}))
      ->capture_default_str();
  cmd->add_option("--probes", a.probes, "Kept probes per acquisition")
      ->delimiter(',')
      ->check(CLI::Range(20, 20000))
      ->capture_default_str();
  cmd->add_option("--seeds", a.seeds, "Seeds (sampling, hidden camera, noise)")
      ->delimiter(',')
      ->capture_default_str();
  cmd->add_option("--widths", a.widths, "MLP hidden layer widths")
      ->delimiter(',')
      ->check(CLI::Range(4, 1024))
      ->capture_default_str();
  cmd->add_option("--depths", a.depths, "MLP hidden layer counts")
      ->delimiter(',')
      ->check(CLI::Range(1, 8))
      ->capture_default_str();
  cmd->add_option("--epochs", a.epochs, "Training epochs at most")
      ->delimiter(',')
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  cmd->add_option("--samples", a.samples, "Contact pixels sampled per probe at most")
      ->delimiter(',')
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  cmd->add_option("--features", a.features,
                  "Input features: fourier (the pixel position's Fourier features) or plain")
      ->delimiter(',')
      ->check(CLI::IsMember({"fourier", "plain"}))
      ->capture_default_str();
  cmd->add_flag("--dry-run", a.dry_run, "List the configurations still to run, run nothing");
  cmd->callback([&ctx] { ctx.exit_code = RunSweep(a, ctx); });
}

}  // namespace gs360::cli
