// daemon/convergence.h: the stop rule, the stored curve, and a run that calibrates itself after
// each round, through gs360d's HTTP API on the virtual rig.

#include <catch2/catch.hpp>

#include <nlohmann/json.hpp>

#include "api_helpers.h"
#include "calib/report.h"
#include "daemon/convergence.h"
#include "daemon_fixture.h"
#include "storage/run_database.h"
#include "tests/storage/storage_test_util.h"

using namespace gs360;
using Json = nlohmann::json;
using test::Body;
using test::PostJson;
using test::WaitRun;

namespace {

// A validation.json with the figures ValidationTargets() reads (rigid truth, heightfield).
Json Validation(double mean, double band50, double peak = 0.04, double normal = 2.0) {
  return {
      {"truths", {"rigid"}},
      {"default_method", "heightfield"},
      {"probes_captured", 500},
      {"results",
       {{"rigid",
         {{"heightfield",
           {{"all", {{"mean_mm", mean}, {"peak_error_mm", peak}, {"median_normal_deg", normal}}},
            {"view:>50", {{"mean_mm", band50}}}}}}}}}};
}

Checkpoint Done(std::int64_t probes, double mean, double band50, double peak = 0.04) {
  Checkpoint c;
  c.plan_index_limit = static_cast<int>(probes);
  c.probes = probes;
  c.state = "done";
  c.targets = ValidationTargets(Validation(mean, band50, peak));
  return c;
}

}  // namespace

TEST_CASE("convergence: the stop rule needs every target twice and a flat error",
          "[daemon][converge]") {
  const ConvergeConfig config;  // 10 %
  CHECK_FALSE(Judge({}, config).converged);
  // Missing a target: the figure that misses is named.
  Verdict v = Judge({Done(250, 0.045, 0.054)}, config);
  CHECK_FALSE(v.converged);
  CHECK_THAT(v.reason, Catch::Contains("misses") && Catch::Contains("mean depth error"));
  // Met once: one more round.
  v = Judge({Done(250, 0.045, 0.054), Done(500, 0.028, 0.040)}, config);
  CHECK_FALSE(v.converged);
  CHECK_THAT(v.reason, Catch::Contains("first time"));
  // Met twice, still improving by 18 % in the mean.
  v = Judge({Done(500, 0.028, 0.040), Done(750, 0.023, 0.039)}, config);
  CHECK_FALSE(v.converged);
  CHECK_THAT(v.reason, Catch::Contains("still improving"));
  // Met twice and flat: converged. The band's improvement counts too.
  v = Judge({Done(750, 0.023, 0.039), Done(1000, 0.022, 0.038)}, config);
  CHECK(v.converged);
  CHECK_THAT(v.reason, Catch::Contains("converged at 1000 probes"));
  CHECK_FALSE(Judge({Done(750, 0.023, 0.045), Done(1000, 0.022, 0.038)}, config).converged);
  // An error that grew is no improvement.
  CHECK(Judge({Done(750, 0.020, 0.030), Done(1000, 0.024, 0.035)}, config).converged);
  // A failed checkpoint or a missed target in between resets the count.
  Checkpoint failed;
  failed.probes = 1000;
  failed.state = "failed";
  failed.error = "disk full";
  v = Judge({Done(750, 0.023, 0.039), failed}, config);
  CHECK_FALSE(v.converged);
  CHECK_THAT(v.reason, Catch::Contains("disk full"));
  CHECK_FALSE(Judge({Done(500, 0.023, 0.060), Done(750, 0.022, 0.040)}, config).converged);
  // A stricter rule (0 %): never flat enough while it improves at all.
  ConvergeConfig strict;
  strict.min_improvement = 0.0;
  CHECK_FALSE(Judge({Done(750, 0.023, 0.039), Done(1000, 0.022, 0.038)}, strict).converged);
  strict.min_improvement = 1.0;
  CHECK_THROWS_WITH(strict.Check(), Catch::Contains("converge.min_improvement"));
}

TEST_CASE("convergence: checkpoints from a calibration view, the curve stored and read back",
          "[daemon][converge]") {
  const Json view{{"state", "done"},
                  {"started_at", 1000.0},
                  {"finished_at", 1042.5},
                  {"validation", Validation(0.025, 0.041)}};
  const Checkpoint c = CheckpointFromCalibration(view, 500);
  CHECK(c.state == "done");
  CHECK(c.probes == 500);
  CHECK(c.plan_index_limit == 500);
  CHECK(c.seconds == Approx(42.5));
  CHECK(c.TargetsMet());
  CHECK(*c.Value("mean depth error") == Approx(0.025));
  const Checkpoint failed = CheckpointFromCalibration(
      {{"state", "failed"}, {"error", "calibrate: run 1 has 12 captured probes"}}, 250);
  CHECK(failed.state == "failed");
  CHECK_THAT(failed.error, Catch::Contains("12 captured"));
  CHECK_FALSE(failed.TargetsMet());
  CHECK(CheckpointFromCalibration(Json::object(), 250).error.size() > 0);

  test::TempDir dir;
  RunDatabase db(dir / "run.db");
  const std::int64_t run = db.CreateRun("{}", "h");
  CHECK(LoadConvergenceCurve(db, run).checkpoints.empty());
  ConvergenceCurve curve;
  curve.checkpoints = {failed, c};
  curve.verdict = "every target met at 500 probes for the first time";
  StoreConvergenceCurve(db, run, curve);
  const ConvergenceCurve back = LoadConvergenceCurve(db, run);
  REQUIRE(back.checkpoints.size() == 2);
  CHECK(back.checkpoints[0].error == failed.error);
  CHECK(back.checkpoints[1].ToJson() == c.ToJson());
  CHECK(back.verdict == curve.verdict);
  CHECK_FALSE(back.converged);
  // A damaged artifact reads as what can be read, never throws.
  const std::string junk = "{\"checkpoints\": [3, {\"probes\": \"many\"}], \"converged\": 1";
  db.PutArtifact(run, kConvergenceStage, kConvergenceKey,
                 std::span(reinterpret_cast<const std::uint8_t*>(junk.data()), junk.size()));
  CHECK(LoadConvergenceCurve(db, run).checkpoints.empty());
  CHECK(ConvergenceCurve::FromJson(Json::parse(R"({"checkpoints": [3, {"probes": 7}]})"))
            .checkpoints.size() == 1);
}

TEST_CASE("convergence: the report draws the checkpoints with this model's own point",
          "[daemon][converge]") {
  const Json earlier = Json::array(
      {{{"probes", 250}, {"mean_mm", 0.045}, {"band50_mm", 0.054}, {"targets_met", false}}});
  Json validation = Validation(0.024, 0.039);
  validation["convergence"] = ConvergencePoints(earlier, validation, 500);
  REQUIRE(validation["convergence"].size() == 2);
  CHECK(validation["convergence"][1]["this"] == true);
  CHECK(validation["convergence"][1]["targets_met"] == true);
  ReportInputs in;
  in.validation = validation;
  const std::string html = RenderReportHtml(in);
  CHECK_THAT(html, Catch::Contains("Error against probes"));
  CHECK_THAT(html, Catch::Contains("500 (this model)"));
  CHECK_THAT(html, Catch::Contains("0.0450"));
  // Malformed points leave the section out; the page still renders.
  in.validation["convergence"] = Json::array({1, "x"});
  CHECK_THAT(RenderReportHtml(in), !Catch::Contains("Error against probes"));
}

TEST_CASE("convergence: a run through the API calibrates after its rounds and at its end",
          "[daemon][converge][api]") {
  // At 20x real time (some 0.1 s a probe), so that the run is still going when it is paused.
  test::RigFixture f("api-converge", 80, 20.0);
  test::InProcessDaemon d(test::ConfigFor(f));
  auto c = d.Client();
  // Bad requests name the field.
  auto r = PostJson(c, "/api/v1/runs", {{"until_converged", "yes"}});
  CHECK(r->status == 400);
  CHECK(Body(r)["error"]["field"] == "until_converged");
  r = PostJson(c, "/api/v1/runs", {{"converge", {{"min_improvement", 1.5}}}});
  CHECK(r->status == 400);
  CHECK_THAT(Body(r)["error"]["message"].get<std::string>(),
             Catch::Contains("converge.min_improvement"));

  r = PostJson(c, "/api/v1/runs",
               {{"probes", 80}, {"until_converged", true}, {"plan", {{"checkpoint_probes", 20}}}});
  REQUIRE(r->status == 201);
  const Json created = Body(r);
  CHECK(created["plan"]["until_converged"] == true);
  CHECK(created["plan"]["checkpoint_probes"] == 20);
  CHECK(created["convergence"]["state"] == "probing");
  const int total = created["probes_total"].get<int>();
  REQUIRE(total > 40);
  // Paused once a checkpoint has started, the checkpoint is recorded while the run stands; the
  // resumed run goes on from the stored curve.
  REQUIRE(PostJson(c, "/api/v1/runs/1/start", Json::object())->status == 202);
  WaitRun(
      c, 1,
      [](const Json& run) {
        return run["convergence"]["state"] == "calibrating" ||
               !run["convergence"]["checkpoints"].empty();
      },
      std::chrono::seconds(120));
  REQUIRE(PostJson(c, "/api/v1/runs/1/pause", Json::object())->status == 202);
  WaitRun(
      c, 1,
      [](const Json& run) {
        return run["state"] == "paused" && run["convergence"]["checkpoints"].size() >= 1 &&
               run["convergence"]["state"] != "calibrating";
      },
      std::chrono::seconds(180));
  REQUIRE(PostJson(c, "/api/v1/runs/1/resume", Json::object())->status == 202);
  const Json run = WaitRun(
      c, 1,
      [](const Json& view) {
        return view["state"] == "done" && view["convergence"]["state"] == "not_converged";
      },
      std::chrono::seconds(180));
  // Too few probes to meet the targets: the whole plan is probed, the last checkpoint is the
  // whole run.
  const int done = run["probes_done"].get<int>();
  CHECK(done + run["probes_failed"].get<int>() == total);
  CHECK(done > total * 3 / 4);
  CHECK(run["probes_skipped"] == 0);
  const Json& list = run["convergence"]["checkpoints"];
  REQUIRE(list.size() >= 2);
  int last = 0;
  for (std::size_t i = 0; i < list.size(); ++i) {
    INFO(list[i].dump());
    CHECK(list[i]["plan_index_limit"].get<int>() > last);
    last = list[i]["plan_index_limit"].get<int>();
    if (i + 1 < list.size()) CHECK(last % 20 == 0);
    if (list[i]["state"] == "done") {
      CHECK(list[i]["probes"].get<int>() <= last);
      CHECK(list[i]["targets"].size() == 4);
    }
  }
  CHECK(list.back()["plan_index_limit"] == total);
  CHECK(list.back()["state"] == "done");
  CHECK(list.back()["probes"] == done);
  CHECK(list.back()["targets_met"] == false);
  CHECK_THAT(run["convergence"]["verdict"].get<std::string>(), Catch::Contains("misses"));
  // The model is the last checkpoint's; its report draws the curve.
  CHECK(Body(c.Get("/api/v1/runs/1/calibration"))["state"] == "done");
  const auto report = c.Get("/api/v1/runs/1/report");
  REQUIRE(report);
  CHECK_THAT(report->body, Catch::Contains("Error against probes"));
  const std::string log = c.Get("/api/v1/runs/1/log")->body;
  CHECK_THAT(log, Catch::Contains("checkpoint at"));
}

TEST_CASE("convergence: a run whose stored curve has converged ends at once, its rest skipped",
          "[daemon][converge][api]") {
  test::RigFixture f("api-converged", 60, 0.0);
  test::InProcessDaemon d(test::ConfigFor(f));
  auto c = d.Client();
  auto r = PostJson(c, "/api/v1/runs", {{"probes", 60}, {"until_converged", true}});
  REQUIRE(r->status == 201);
  CHECK(Body(r)["plan"]["checkpoint_probes"] == kDefaultConvergeRound);
  const int total = Body(r)["probes_total"].get<int>();
  {
    // As a daemon killed between the verdict and the run's end leaves it.
    RunDatabase db(d.daemon->config().DatabasePath());
    ConvergenceCurve curve;
    curve.checkpoints = {Done(20, 0.022, 0.038), Done(40, 0.021, 0.037)};
    curve.converged = true;
    curve.verdict = "converged at 40 probes";
    StoreConvergenceCurve(db, 1, curve);
  }
  REQUIRE(PostJson(c, "/api/v1/runs/1/start", Json::object())->status == 202);
  const Json run = WaitRun(
      c, 1, [](const Json& view) { return view["state"] == "done"; }, std::chrono::seconds(120));
  CHECK(run["convergence"]["state"] == "converged");
  CHECK(run["probes_done"].get<int>() + run["probes_skipped"].get<int>() == total);
  CHECK(run["probes_skipped"].get<int>() > 0);
  CHECK_THAT(c.Get("/api/v1/runs/1/log")->body, Catch::Contains("done early (converged)"));
}

TEST_CASE("convergence: a converged run's model takes in every probe it captured",
          "[daemon][converge][api]") {
  // Fast enough to finish, slow enough to stop with part of the plan captured.
  test::RigFixture f("api-converged-all", 80, 5.0);
  {
    test::InProcessDaemon d(test::ConfigFor(f));
    auto c = d.Client();
    REQUIRE(PostJson(c, "/api/v1/runs", {{"probes", 80}, {"until_converged", true}})->status ==
            201);
    REQUIRE(PostJson(c, "/api/v1/runs/1/start", Json::object())->status == 202);
    WaitRun(
        c, 1, [](const Json& run) { return run["probes_done"].get<int>() >= 25; },
        std::chrono::seconds(120));
  }  // gs360d stops: the run is interrupted
  {
    // As a daemon leaves a run whose verdict came at 20 probes while it went on to more.
    RunDatabase db(test::ConfigFor(f).DatabasePath());
    ConvergenceCurve curve;
    curve.checkpoints = {Done(10, 0.022, 0.038), Done(20, 0.021, 0.037)};
    curve.converged = true;
    curve.verdict = "converged at 20 probes";
    StoreConvergenceCurve(db, 1, curve);
  }
  test::InProcessDaemon d(test::ConfigFor(f));
  auto c = d.Client();
  Json body = Json::object();
  const Json stopped = Body(c.Get("/api/v1/runs/1"));
  if (stopped.contains("awaiting") && stopped["awaiting"].is_string()) {
    body["confirm"] = stopped["awaiting"];
  }
  REQUIRE(PostJson(c, "/api/v1/runs/1/resume", body)->status == 202);
  const Json run = WaitRun(
      c, 1,
      [](const Json& view) {
        return view["state"] == "done" && view["convergence"]["state"] == "converged";
      },
      std::chrono::seconds(240));
  const int captured = run["probes_done"].get<int>();
  CHECK(captured >= 25);
  CHECK(run["probes_skipped"].get<int>() > 0);
  // The last checkpoint is on every captured probe, and it is the run's model.
  const Json& list = run["convergence"]["checkpoints"];
  REQUIRE(list.size() == 3);
  CHECK(list.back()["state"] == "done");
  CHECK(list.back()["probes"] == captured);
  CHECK(Body(c.Get("/api/v1/runs/1/calibration"))["validation"]["probes_captured"] == captured);
  CHECK_THAT(c.Get("/api/v1/runs/1/log")->body,
             Catch::Contains("the model now takes in every probe of the run"));
}
