// Issue 4's acceptance test: a few hundred probes end to end through the real pty, the runner
// process killed with SIGKILL at random moments several times, resumed each time; at the end
// exactly one committed frame per reachable probe, each taken while the virtual CNC truly stood
// at the press position.

#include <catch2/catch.hpp>

#include <fcntl.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>

#include <fstream>
#include <random>
#include <set>
#include <thread>

#include <nlohmann/json.hpp>

#include "rig_fixture.h"
#include "storage/run_database.h"

extern char** environ;

using namespace gs360;

namespace {

pid_t Spawn(const std::vector<std::string>& args, const std::filesystem::path& log) {
  std::vector<char*> argv;
  for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
  argv.push_back(nullptr);
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, 1, log.c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644);
  posix_spawn_file_actions_adddup2(&actions, 1, 2);
  pid_t pid = -1;
  const int rc = posix_spawn(&pid, argv[0], &actions, nullptr, argv.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  REQUIRE(rc == 0);
  return pid;
}

// Waits up to `timeout` for the child; returns its exit status, or -1 if still running.
int WaitFor(pid_t pid, std::chrono::seconds timeout) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < deadline) {
    int status = 0;
    if (waitpid(pid, &status, WNOHANG) == pid) return WIFEXITED(status) ? WEXITSTATUS(status) : 128;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  return -1;
}

}  // namespace

TEST_CASE("SIGKILL at random moments, resume, and every reachable probe has exactly one frame",
          "[daemon][kill]") {
  test::RigFixture f("kill", 400, 0.0);
  const std::string gs360 = std::string(GS360_BINARY_DIR) + "/cli/gs360";
  const auto config_path = f.dir / "run.json";
  std::ofstream(config_path) << RunConfigToJson(f.config).dump(2);
  const auto log = f.dir / "runner.log";

  const pid_t planner = Spawn(
      {gs360, "run", "--db", f.db.string(), "start", config_path.string(), "--plan-only"}, log);
  REQUIRE(WaitFor(planner, std::chrono::seconds(120)) == 0);
  std::int64_t total = 0;
  {
    RunDatabase db(f.db);
    total = db.CountProbes(1).total;
  }
  REQUIRE(total >= 150);

  std::mt19937 rng(2026);
  std::uniform_int_distribution<int> delay_ms(1500, 6000);
  int kills = 0;
  std::int64_t last_captured = 0;
  for (int round = 0; round < 6; ++round) {
    const pid_t runner = Spawn({gs360, "run", "--db", f.db.string(), "resume", "1"}, log);
    std::this_thread::sleep_for(std::chrono::milliseconds(delay_ms(rng)));
    if (kill(runner, SIGKILL) == 0) ++kills;
    int status = 0;
    waitpid(runner, &status, 0);
    RunDatabase db(f.db);
    const auto captured = db.CountProbes(1).captured;
    CHECK(captured >= last_captured);  // nothing committed is ever lost
    last_captured = captured;
    CHECK(db.IntegrityCheck().empty());
  }
  CHECK(kills >= 5);

  const pid_t runner = Spawn({gs360, "run", "--db", f.db.string(), "resume", "1"}, log);
  const int rc = WaitFor(runner, std::chrono::seconds(600));
  if (rc == -1) kill(runner, SIGKILL);
  INFO("runner log: " << log.string());
  REQUIRE(rc == 0);

  RunDatabaseOptions ro;
  ro.read_only = true;
  RunDatabase db(f.db, ro);
  CHECK(db.GetRun(1)->state == RunState::kDone);
  const ProbeCounts counts = db.CountProbes(1);
  CHECK(counts.captured == total);
  CHECK(counts.failed == 0);
  const auto frames = db.ListFrames(1, FrameKind::kPress);
  CHECK(static_cast<std::int64_t>(frames.size()) == total);
  std::set<std::int64_t> probes;
  for (const auto& fr : frames) CHECK(probes.insert(*fr.probe_id).second);
  const cli::CaptureTruth truth = cli::CheckCapturesAgainstTruth(*f.rig, db, 1);
  CHECK(truth.frames == total);
  CHECK(truth.off_target == 0);
  CHECK(truth.unverified == 0);
  CHECK(truth.max_error_mm < 0.005);
}

TEST_CASE("SIGTERM finishes the current probe, retracts, commits and exits", "[daemon][kill]") {
  test::RigFixture f("term", 120, 0.0);
  const std::string gs360 = std::string(GS360_BINARY_DIR) + "/cli/gs360";
  const auto config_path = f.dir / "run.json";
  std::ofstream(config_path) << RunConfigToJson(f.config).dump(2);
  const auto log = f.dir / "runner.log";
  const pid_t runner =
      Spawn({gs360, "run", "--db", f.db.string(), "start", config_path.string()}, log);
  // Wait until it is probing, then ask it to stop.
  for (int i = 0; i < 600; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    if (!std::filesystem::exists(f.db)) continue;
    RunDatabaseOptions ro;
    ro.read_only = true;
    try {
      if (RunDatabase(f.db, ro).CountProbes(1).captured >= 3) break;
    } catch (const std::exception&) {
    }
  }
  kill(runner, SIGTERM);
  const int rc = WaitFor(runner, std::chrono::seconds(60));
  CHECK(rc == 3);  // stopped, resumable
  RunDatabase db(f.db);
  CHECK(db.GetRun(1)->state == RunState::kInterrupted);
  // Retracted: the tool is at a retract (approach) position, not pressing.
  const Eigen::Vector3d at = f.rig->cnc().TruePositionNow();
  double nearest = 1e9;
  for (const auto& p : db.ListProbes(1))
    nearest = std::min(nearest, (p.plan.retract_machine - at).norm());
  INFO("true position " << at.transpose() << ", nearest retract " << nearest << " mm");
  CHECK(nearest < 0.005);  // G-code carries 3 decimals; any other position is mm away
}
