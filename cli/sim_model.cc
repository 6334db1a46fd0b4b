#include "cli/sim_model.h"

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <numbers>
#include <random>
#include <stdexcept>
#include <string>

#include "calib/pipeline.h"
#include "sim/tactile_camera.h"
#include "storage/run_database.h"

namespace gs360::cli {

void SimModelOptions::Check() const {
  const auto bad = [](const std::string& field, const std::string& value) {
    throw std::invalid_argument("SimModelOptions." + field + " = " + value + " is out of range");
  };
  if (probes < 10) bad("probes", std::to_string(probes));
  if (hidden.empty()) bad("hidden", "[]");
  for (int h : hidden) {
    if (h < 1) bad("hidden", std::to_string(h));
  }
  if (epochs < 1) bad("epochs", std::to_string(epochs));
  if (!(press_depth_mm > 0.0 && press_depth_mm < 2.0)) {
    bad("press_depth_mm", std::to_string(press_depth_mm));
  }
  if (threads < 1) bad("threads", std::to_string(threads));
}

std::vector<SimPress> SimPresses(const SimRig& rig, int count, double depth_mm,
                                 std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> along(0.08, 0.85);
  std::uniform_real_distribution<double> around(0.0, 2.0 * std::numbers::pi);
  std::vector<SimPress> out;
  while (static_cast<int>(out.size()) < count) {
    const double t = along(rng), phi = around(rng);
    // The planner keeps clear of the four fins (at phi = k pi / 2); so do we.
    if (std::abs(std::sin(2.0 * phi)) < 0.3) continue;
    SimPress p;
    p.point_sensor = rig.profile().SurfacePoint(t, phi);
    p.normal_sensor = rig.profile().SurfaceNormal(t, phi);
    p.ball_sensor = p.point_sensor + (rig.ball_radius() - depth_mm) * p.normal_sensor;
    out.push_back(p);
  }
  return out;
}

namespace {

// A database with one finished run of rendered presses; returns the run id (1).
std::int64_t RenderRun(const std::filesystem::path& db_path,
                       const std::shared_ptr<const SimRig>& shared, const SimModelOptions& o) {
  const SimRig& rig = *shared;
  RunDatabaseOptions dbo;
  dbo.synchronous = SyncMode::kNormal;
  RunDatabase db(db_path, dbo);
  if (db.GetRun(1)) return 1;  // rendered before: the calibration's cache does the rest
  const std::int64_t run = db.CreateRun("{}", "sim-model", "sim-model");
  const std::vector<SimPress> presses = SimPresses(rig, o.probes, o.press_depth_mm, o.seed);
  std::vector<ProbePlanEntry> plan;
  for (const SimPress& p : presses) {
    ProbePlanEntry e;
    e.point_sensor = p.point_sensor;
    e.normal_sensor = p.normal_sensor;
    e.press_machine = rig.MachinePositionForBall(p.ball_sensor);
    e.approach_machine = e.press_machine + Eigen::Vector3d(0, 0, 5);
    e.retract_machine = e.approach_machine;
    plan.push_back(e);
  }
  const auto ids = db.InsertPlan(run, plan);
  TactileCamera camera(shared);
  db.AddReferenceFrame(run, camera.RenderReference(0, 0.0), 0.0);
  for (std::size_t i = 0; i < presses.size(); ++i) {
    CaptureReport report;
    report.machine_position = plan[i].press_machine;
    report.sync_time = 1.0 + static_cast<double>(i);
    report.frame_time = report.sync_time + 0.05;
    db.CommitCapture(ids[i], camera.RenderAtBall(presses[i].ball_sensor, i + 1, 2.0 * i), report);
  }
  return run;
}

}  // namespace

std::filesystem::path MakeSimModel(const std::filesystem::path& dir, const SimModelOptions& o) {
  o.Check();
  std::filesystem::create_directories(dir);
  SimRigOptions so;
  so.seed = o.seed;
  const auto shared = std::make_shared<const SimRig>(so);
  const SimRig& rig = *shared;
  const std::int64_t run = RenderRun(dir / "run.db", shared, o);
  CalibrationInputs in;
  in.sensor = "virtual rig cylinder";
  in.gel_mesh = rig.gel_mesh();
  in.fin_mesh = rig.fin_mesh();
  in.nominal_intrinsics = rig.nominal_intrinsics();
  in.nominal_cam_from_sensor = rig.nominal_cam_from_sensor();
  in.machine_from_sensor = rig.machine_from_sensor();
  in.tool_offset = rig.tool_offset();
  in.ball_radius = rig.ball_radius();
  CalibrationOptions co;
  co.train.max_epochs = o.epochs;
  co.train.hidden = o.hidden;
  co.validation.max_probes = 6;
  co.validation.examples = 1;
  co.export_dir = dir;
  co.model_name = "sim";
  co.model_version = "1";
  co.threads = o.threads;
  RunDatabase db(dir / "run.db");
  return RunCalibration(db, run, in, co).model_path;
}

std::filesystem::path SimModelCacheDir(const std::string& cache, const std::string& name) {
  std::filesystem::path base = cache;
  if (base.empty()) {
    const char* xdg = std::getenv("XDG_CACHE_HOME");
    const char* home = std::getenv("HOME");
    base = xdg && *xdg ? std::filesystem::path(xdg) / "gs360"
           : home      ? std::filesystem::path(home) / ".cache" / "gs360"
                       : std::filesystem::temp_directory_path() / "gs360-cache";
  }
  return base / name;
}

}  // namespace gs360::cli
