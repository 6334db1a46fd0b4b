// The calibration stages end to end on a small simulated run, and the stage cache.

#include <catch2/catch.hpp>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <map>
#include <random>

#include <nlohmann/json.hpp>

#include "calib/pipeline.h"
#include "sim/rig_model.h"
#include "sim/tactile_camera.h"

using namespace gs360;

namespace {

struct SmallRun {
  std::filesystem::path dir;
  std::filesystem::path db_path;
  std::int64_t run_id = 0;
  CalibrationInputs inputs;
};

// A run of `n` presses rendered straight from the simulated camera (no CNC needed: the frames are
// committed with the planned machine positions, as a finished acquisition leaves them).
SmallRun MakeSmallRun(int n, const std::string& name) {
  SmallRun s;
  s.dir = std::filesystem::temp_directory_path() / ("gs360_pipeline_" + name);
  std::filesystem::remove_all(s.dir);
  std::filesystem::create_directories(s.dir);
  s.db_path = s.dir / "run.db";
  SimRigOptions so;
  auto rig = std::make_shared<const SimRig>(so);
  TactileCamera camera(rig);
  RunDatabaseOptions dbo;
  dbo.synchronous = SyncMode::kNormal;
  RunDatabase db(s.db_path, dbo);
  s.run_id = db.CreateRun("{}", "test-mesh", name);
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<double> t_dist(0.08, 0.85), phi_dist(0.0, 2.0 * M_PI);
  std::vector<ProbePlanEntry> plan;
  std::vector<Eigen::Vector3d> balls;
  while (static_cast<int>(plan.size()) < n) {
    const double t = t_dist(rng), phi = phi_dist(rng);
    // Keep away from the fins (the planner would drop those points).
    if (std::abs(std::sin(2.0 * phi)) < 0.3) continue;
    ProbePlanEntry e;
    e.point_sensor = rig->profile().SurfacePoint(t, phi);
    e.normal_sensor = rig->profile().SurfaceNormal(t, phi);
    const Eigen::Vector3d ball = e.point_sensor + (rig->ball_radius() - 1.0) * e.normal_sensor;
    e.press_machine = rig->MachinePositionForBall(ball);
    e.approach_machine = e.press_machine + Eigen::Vector3d(0, 0, 5);
    e.retract_machine = e.approach_machine;
    plan.push_back(e);
    balls.push_back(ball);
  }
  const auto ids = db.InsertPlan(s.run_id, plan);
  db.AddReferenceFrame(s.run_id, camera.RenderReference(0, 0.0), 0.0);
  for (int i = 0; i < n; ++i) {
    const cv::Mat frame = camera.RenderAtBall(balls[static_cast<std::size_t>(i)], i + 1, 2.0 * i);
    CaptureReport report;
    report.machine_position = plan[static_cast<std::size_t>(i)].press_machine;
    report.sync_time = 1.0 + i;
    report.frame_time = 1.05 + i;
    db.CommitCapture(ids[static_cast<std::size_t>(i)], frame, report);
  }
  s.inputs.sensor = "cylinder";
  s.inputs.gel_mesh = rig->gel_mesh();
  s.inputs.fin_mesh = rig->fin_mesh();
  s.inputs.nominal_intrinsics = rig->nominal_intrinsics();
  s.inputs.nominal_cam_from_sensor = rig->nominal_cam_from_sensor();
  s.inputs.machine_from_sensor = rig->machine_from_sensor();
  s.inputs.tool_offset = rig->tool_offset();
  s.inputs.ball_radius = rig->ball_radius();
  return s;
}

CalibrationOptions FastOptions(const std::filesystem::path& dir) {
  CalibrationOptions o;
  o.train.max_epochs = 3;
  o.train.hidden = {16, 16};
  o.validation.max_probes = 6;
  o.validation.examples = 1;
  o.export_dir = dir;
  o.model_version = "t";
  return o;
}

std::map<std::string, bool> Cached(const CalibrationResult& r) {
  std::map<std::string, bool> m;
  for (const StageReport& s : r.stages) m[s.stage] = s.cached;
  return m;
}

// What validation.json holds: every integrator (the height field the default), and one row
// per evaluated probe, in plan order, with every method's peak against the truth's.
void CheckValidationShape(const nlohmann::json& validation) {
  CHECK(validation.at("default_method") == "heightfield");
  for (const char* method : {"heightfield", "discontinuity", "poisson", "render_slopes"}) {
    INFO(method);
    CHECK(validation.at("results").at("rigid").at(method).at("all").at("pixels").get<int>() > 0);
    CHECK(validation.at("results").at("rigid").at(method).at("all").at("peak_bias_mm").is_number());
  }
  const auto& peaks = validation.at("probe_peaks");
  REQUIRE(peaks.size() == validation.at("probes_evaluated").get<std::size_t>());
  int last_index = -1, with_peak = 0;
  for (const auto& row : peaks) {
    CHECK(row.at("plan_index").get<int>() > last_index);
    last_index = row.at("plan_index").get<int>();
    CHECK(row.at("contact_pixels").get<int>() > 0);
    CHECK(row.at("rigid_mm").get<double>() > 0.0);
    CHECK(row.at("contact_point_mm").size() == 3);
    for (const char* method : {"heightfield", "discontinuity", "poisson", "render_slopes"}) {
      CHECK(row.at("peak_mm").contains(method));
    }
    if (row.at("peak_mm").at("heightfield").is_number()) ++with_peak;
  }
  CHECK(with_peak > 0);
}

}  // namespace

TEST_CASE(
    "calibration stages: a second run is all cache, a changed option re-runs what depends on it",
    "[calib][pipeline]") {
  SmallRun s = MakeSmallRun(60, "cache");
  RunDatabase db(s.db_path);
  CalibrationOptions o = FastOptions(s.dir);

  const auto t_log = std::chrono::steady_clock::now();
  const CalibrationResult first = RunCalibration(
      db, s.run_id, s.inputs, o, nullptr, [&](const std::string& stage, const std::string& m) {
        if (std::getenv("GS360_TEST_LOG") == nullptr) return;
        std::fprintf(
            stderr, "%8.2f %s %s\n",
            std::chrono::duration<double>(std::chrono::steady_clock::now() - t_log).count(),
            stage.c_str(), m.c_str());
      });
  if (std::getenv("GS360_TEST_LOG") != nullptr) {
    std::fprintf(stderr, "validation: %s\n", first.validation.dump().substr(0, 600).c_str());
  }
  REQUIRE(first.stages.size() == CalibrationStages().size());
  for (const StageReport& st : first.stages) CHECK_FALSE(st.cached);
  CHECK(std::filesystem::exists(first.model_path));
  CHECK(std::filesystem::exists(first.onnx_path));
  CHECK(std::filesystem::exists(first.report_path));
  CheckValidationShape(first.validation);
  // The pose moved from the nominal toward the (hidden) truth: the sim's camera is 0.3 mm / 1 deg
  // off.
  CHECK(TranslationDifferenceMm(first.cam_from_sensor, s.inputs.nominal_cam_from_sensor) > 0.05);

  const CalibrationResult second = RunCalibration(db, s.run_id, s.inputs, o);
  for (const StageReport& st : second.stages) CHECK(st.cached);
  CHECK(TranslationDifferenceMm(second.cam_from_sensor, first.cam_from_sensor) == 0.0);
  CHECK(second.validation == first.validation);

  // A deleted model file is written again (the export is the product), nothing else re-runs.
  std::filesystem::remove(first.model_path);
  auto c = Cached(RunCalibration(db, s.run_id, s.inputs, o));
  CHECK(c["validate"]);
  CHECK_FALSE(c["export"]);
  CHECK(std::filesystem::exists(first.model_path));

  // A training option: train and everything after it run again, nothing before.
  o.train.learning_rate *= 0.5;
  c = Cached(RunCalibration(db, s.run_id, s.inputs, o));
  for (const char* stage :
       {"intrinsics", "impressions", "pose", "surface_map", "render", "dataset"}) {
    CHECK(c[stage]);
  }
  for (const char* stage : {"train", "validate", "export"}) CHECK_FALSE(c[stage]);

  // --from render forces render and later stages.
  o.from_stage = "render";
  c = Cached(RunCalibration(db, s.run_id, s.inputs, o));
  CHECK(c["surface_map"]);
  CHECK_FALSE(c["render"]);
  CHECK_FALSE(c["dataset"]);

  o.from_stage = "nonsense";
  CHECK_THROWS_WITH(RunCalibration(db, s.run_id, s.inputs, o), Catch::Contains("nonsense"));

  // --to pose stops there: no model, the later stages not even looked up.
  o.from_stage.clear();
  o.to_stage = "pose";
  CalibrationResult to = RunCalibration(db, s.run_id, s.inputs, o);
  REQUIRE(to.stages.size() == 3);
  CHECK(to.stages.back().stage == "pose");
  CHECK(to.model_path.empty());

  // --only train runs train again on cached inputs, and nothing after it.
  o.to_stage.clear();
  o.only_stage = "train";
  to = RunCalibration(db, s.run_id, s.inputs, o);
  REQUIRE(to.stages.back().stage == "train");
  CHECK_FALSE(to.stages.back().cached);
  for (std::size_t k = 0; k + 1 < to.stages.size(); ++k) CHECK(to.stages[k].cached);
  // The training left its last checkpoint beside its artifact; a forced run resumes from it, and
  // from the first epoch when it is corrupt, with the same weights either way.
  std::string train_key;
  for (const ArtifactRecord& a : db.ListArtifacts(s.run_id)) {
    if (a.stage == "train-checkpoint") train_key = a.input_hash;
  }
  REQUIRE_FALSE(train_key.empty());
  const auto trained = db.GetArtifact(s.run_id, "train", train_key)->blob;
  for (const bool corrupt : {false, true}) {
    if (corrupt) {
      db.PutArtifact(s.run_id, "train-checkpoint", train_key, std::vector<std::uint8_t>(40, 3));
    }
    std::string log;
    to = RunCalibration(db, s.run_id, s.inputs, o, nullptr,
                        [&](const std::string& stage, const std::string& m) {
                          if (stage == "train") log += m + "\n";
                        });
    INFO(log);
    CHECK_THAT(log, Catch::Contains(corrupt ? "the checkpoint cannot be used"
                                            : "resuming from the checkpoint after epoch 2"));
    CHECK(db.GetArtifact(s.run_id, "train", train_key)->blob == trained);
  }
  // ... and refuses to compute an input that is not cached, naming it and the --to to run.
  o.render.margin_px += 1.0;
  CHECK_THROWS_WITH(RunCalibration(db, s.run_id, s.inputs, o),
                    Catch::Contains("input render") && Catch::Contains("--to render"));
  o.only_stage = "bogus";
  CHECK_THROWS_WITH(RunCalibration(db, s.run_id, s.inputs, o), Catch::Contains("only_stage"));
  std::filesystem::remove_all(s.dir);
}

TEST_CASE("calibration stages: too few captured probes is a clear error", "[calib][pipeline]") {
  SmallRun s = MakeSmallRun(8, "few");
  RunDatabase db(s.db_path);
  CHECK_THROWS_WITH(RunCalibration(db, s.run_id, s.inputs, FastOptions(s.dir)),
                    Catch::Contains("8 captured probes"));
  std::filesystem::remove_all(s.dir);
}
