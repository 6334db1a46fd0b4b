// gs360d killed: a few hundred probes through the real pty, the daemon SIGKILLed at random
// moments several times and started again, the run resumed each time; at the end exactly one
// committed frame per reachable probe, each taken while the virtual CNC truly stood at the press
// position. And SIGTERM: the current probe is finished and the daemon exits cleanly.

#include <catch2/catch.hpp>

#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <atomic>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <random>
#include <set>
#include <thread>
#include <vector>

#include "cli/daemon_client.h"
#include "daemon_fixture.h"
#include "storage/run_database.h"
#include "tests/wait.h"

using namespace gs360;
using Json = nlohmann::json;

namespace {

RunDatabase ReadOnly(const std::filesystem::path& path) {
  RunDatabaseOptions ro;
  ro.read_only = true;
  return RunDatabase(path, ro);
}

// Polls the daemon until the run's view satisfies `pred`. The bound only catches a hang: the
// last resume's few hundred probes take about a minute at instant motion, longer on a loaded CI
// machine, so it is generous (5 min).
template <typename Pred>
Json WaitFor(cli::DaemonClient& client, std::int64_t id, Pred pred) {
  Json run;
  const auto done = [&] {
    run = client.Get("/api/v1/runs/" + std::to_string(id));
    return pred(run);
  };
  if (!test::WaitUntil(done, std::chrono::minutes(5))) FAIL("timed out; last view " << run.dump());
  return run;
}

}  // namespace

TEST_CASE(
    "gs360d SIGKILLed at random moments: resume, and every reachable probe has exactly "
    "one frame",
    "[daemon][kill]") {
  test::RigFixture f("kill", 400, 0.0);
  const auto db_path = f.dir / "data" / "gs360.db";
  std::int64_t total = 0;
  {
    auto daemon = test::StartDaemonProcess(f);
    cli::DaemonClient client(daemon->url(), "");
    const Json created = client.Post("/api/v1/runs", {{"name", "kill"}, {"probes", 400}});
    total = created["probes_total"];
    daemon->Stop();
  }
  REQUIRE(total >= 150);

  // GS360_KILL_SEED and GS360_KILL_ROUNDS replay other kill schedules (scripts/kill_loop.sh).
  const char* seed = std::getenv("GS360_KILL_SEED");
  const char* rounds_env = std::getenv("GS360_KILL_ROUNDS");
  std::mt19937 rng(seed ? static_cast<unsigned>(std::stoul(seed)) : 2026u);
  const int rounds = rounds_env ? std::stoi(rounds_env) : 6;
  // Each round kills after a random number of further probes (and a random moment within one):
  // at instant motion a probe takes some 20-100 ms, so a kill at a random time would as likely
  // come after the run ended; by count the rounds stay inside the run, at any machine's pace.
  std::uniform_int_distribution<int> probes_more(2, std::max(3, 300 / rounds));
  std::uniform_int_distribution<int> moment_ms(0, 60);
  std::int64_t last_captured = 0;
  for (int round = 0; round < rounds; ++round) {
    auto daemon = test::StartDaemonProcess(f);
    cli::DaemonClient client(daemon->url(), "");
    // A run the previous daemon left running shows as interrupted, never running.
    const Json before = client.Get("/api/v1/runs/1");
    CHECK(before["state"] == (round == 0 ? "created" : "interrupted"));
    client.Post(std::string("/api/v1/runs/1/") + (round == 0 ? "start" : "resume"));
    const std::int64_t kill_at = last_captured + probes_more(rng);
    WaitFor(client, 1, [&](const Json& r) {
      const std::string state = r["state"];
      const bool going = state == "starting" || state == "running" || state == "interrupted";
      return r["probes_done"].get<std::int64_t>() >= kill_at || !going;
    });
    std::this_thread::sleep_for(std::chrono::milliseconds(moment_ms(rng)));
    // Nothing moved the machine by hand: a resume never needs the user to confirm its position.
    const Json during = client.Get("/api/v1/runs/1");
    INFO("round " << round << ": " << during.dump());
    CHECK(during["awaiting"].is_null());
    daemon->Kill();
    RunDatabase db = ReadOnly(db_path);
    const auto captured = db.CountProbes(1).captured;
    CHECK(captured >= last_captured);  // nothing committed is ever lost
    last_captured = captured;
    CHECK(db.IntegrityCheck().empty());
  }
  CHECK(last_captured > 0);
  CHECK(last_captured < total);

  auto daemon = test::StartDaemonProcess(f);
  cli::DaemonClient client(daemon->url(), "");
  client.Post("/api/v1/runs/1/resume");
  const Json done = WaitFor(client, 1, [](const Json& r) {
    return r["state"] != "running" && r["state"] != "starting" && r["state"] != "interrupted";
  });
  CHECK(done["state"] == "done");
  CHECK(daemon->Stop() == 0);

  RunDatabase db = ReadOnly(db_path);
  const ProbeCounts counts = db.CountProbes(1);
  // Every probe was pressed; the few the true camera cannot see (a fin's edge hides them) failed
  // for want of an impression, and nothing else failed.
  CHECK(counts.captured + counts.failed == total);
  CHECK(counts.failed <= 8);
  for (const ProbeRecord& p : db.ListProbes(1, ProbeState::kFailed)) {
    CHECK_THAT(p.last_error, Catch::Contains("no impression"));
  }
  const auto frames = db.ListFrames(1, FrameKind::kPress);
  CHECK(static_cast<std::int64_t>(frames.size()) == counts.captured);
  std::set<std::int64_t> probes;
  for (const auto& fr : frames) CHECK(probes.insert(*fr.probe_id).second);
  const cli::CaptureTruth truth = cli::CheckCapturesAgainstTruth(*f.rig, db, 1);
  CHECK(truth.frames == counts.captured);
  CHECK(truth.off_target == 0);
  CHECK(truth.unverified == 0);
  CHECK(truth.max_error_mm < 0.005);
}

namespace {

// Starts a calibration with `body` and waits until it ends (any state but running); its view.
Json CalibrateToTheEnd(cli::DaemonClient& client, const Json& body) {
  client.Post("/api/v1/runs/1/calibrate", body);
  Json view;
  const auto ended = [&] {
    view = client.Get("/api/v1/runs/1/calibration");
    return view["state"] != "running";
  };
  if (!test::WaitUntil(ended, std::chrono::minutes(5))) FAIL("timed out; " << view.dump());
  return view;
}

// Copies a database with SQLite's log beside it (gs360d's last transactions may still be there,
// not yet copied into the file); a stale shared-memory index at `to` is removed.
void CopyDatabase(const std::filesystem::path& from, const std::filesystem::path& to) {
  for (const char* suffix : {"", "-wal"}) {
    std::filesystem::remove(to.string() + suffix);
    if (std::filesystem::exists(from.string() + suffix)) {
      std::filesystem::copy_file(from.string() + suffix, to.string() + suffix);
    }
  }
  std::filesystem::remove(to.string() + "-shm");
}

struct CalibrationKill {
  std::string stage;  // killed once this stage runs
  int delay_ms = 0;   // ... and this long after
};

// By default one kill in each of three stages; GS360_KILL_SEED and GS360_KILL_ROUNDS replay
// others (scripts/kill_loop.sh --calibration): each round a random stage, and a random moment
// after it starts.
std::vector<CalibrationKill> CalibrationKills() {
  const char* rounds = std::getenv("GS360_KILL_ROUNDS");
  if (!rounds) return {{"pose", 0}, {"dataset", 0}, {"train", 0}};
  const char* seed = std::getenv("GS360_KILL_SEED");
  std::mt19937 rng(seed ? static_cast<unsigned>(std::stoul(seed)) : 2026u);
  const std::vector<std::string> all = {"impressions", "pose",  "surface_map", "render",
                                        "dataset",     "train", "validate"};
  std::vector<CalibrationKill> kills;
  for (int i = 0; i < std::stoi(rounds); ++i) {
    const std::string& stage = all[rng() % all.size()];
    kills.push_back({stage, static_cast<int>(rng() % 300)});
  }
  return kills;
}

// Starts a calibration with `body`, waits until `kill.stage` runs (or the calibration ended),
// waits kill.delay_ms more and SIGKILLs gs360d; the database must stay sound.
void CalibrateAndKill(const test::RigFixture& f, const Json& body, const CalibrationKill& kill,
                      const std::filesystem::path& db_path) {
  auto daemon = test::StartDaemonProcess(f);
  cli::DaemonClient client(daemon->url(), "");
  client.Post("/api/v1/runs/1/calibrate", body);
  Json view;
  const auto reached = [&] {
    view = client.Get("/api/v1/runs/1/calibration");
    return view["stage"] == kill.stage || view["state"] != "running";
  };
  REQUIRE(test::WaitUntil(reached, std::chrono::minutes(5)));
  std::this_thread::sleep_for(std::chrono::milliseconds(kill.delay_ms));
  INFO("killed at " << view.dump().substr(0, 300));
  daemon->Kill();
  CHECK(ReadOnly(db_path).IntegrityCheck().empty());
}

}  // namespace

TEST_CASE(
    "gs360d SIGKILLed during calibrations: calibrated again, the results equal an "
    "uninterrupted calibration's",
    "[daemon][kill]") {
  test::RigFixture f("killcal", 150, 0.0);
  const auto data = f.dir / "data";
  const auto db_path = data / "gs360.db";
  {
    auto daemon = test::StartDaemonProcess(f);
    cli::DaemonClient client(daemon->url(), "");
    client.Post("/api/v1/runs", {{"name", "killcal"}, {"probes", 150}});
    client.Post("/api/v1/runs/1/start");
    WaitFor(client, 1, [](const Json& r) { return r["state"] == "done"; });
    REQUIRE(daemon->Stop() == 0);
  }
  // The database as the acquisition left it.
  const auto pristine = f.dir / "pristine";
  std::filesystem::create_directories(pristine);
  CopyDatabase(db_path, pristine / "gs360.db");
  // Small and short, so that the rounds land in different stages within seconds.
  const Json body = {{"max_epochs", 6}, {"hidden", {24, 24}}, {"max_validation_probes", 20}};

  Json uninterrupted;
  {
    auto daemon = test::StartDaemonProcess(f);
    cli::DaemonClient client(daemon->url(), "");
    uninterrupted = CalibrateToTheEnd(client, body);
    REQUIRE(daemon->Stop() == 0);
  }
  REQUIRE(uninterrupted["state"] == "done");

  // The same acquisition again, calibrated with gs360d killed in the middle of stages.
  CopyDatabase(pristine / "gs360.db", db_path);
  for (const CalibrationKill& kill : CalibrationKills()) CalibrateAndKill(f, body, kill, db_path);
  auto daemon = test::StartDaemonProcess(f);
  cli::DaemonClient client(daemon->url(), "");
  // Killed while it ran, or (a round's moment came after the last stage) already done.
  const std::string last = client.Get("/api/v1/runs/1/calibration")["state"];
  CHECK((last == "interrupted" || last == "done"));
  const Json resumed = CalibrateToTheEnd(client, body);
  REQUIRE(daemon->Stop() == 0);
  REQUIRE(resumed["state"] == "done");
  // Bit-identical stages give identical figures, to the last digit of every band.
  CHECK(resumed["validation"]["results"] == uninterrupted["validation"]["results"]);
  CHECK(resumed["targets"] == uninterrupted["targets"]);
}

TEST_CASE("gs360d on SIGTERM finishes the current probe, retracts, commits and exits 0",
          "[daemon][kill]") {
  test::RigFixture f("term", 120, 0.0);
  auto daemon = test::StartDaemonProcess(f);
  cli::DaemonClient client(daemon->url(), "");
  client.Post("/api/v1/runs", {{"probes", 120}});
  client.Post("/api/v1/runs/1/start");
  WaitFor(client, 1, [](const Json& r) { return r["probes_done"].get<int>() >= 3; });
  CHECK(daemon->Stop() == 0);
  RunDatabase db = ReadOnly(f.dir / "data" / "gs360.db");
  CHECK(db.GetRun(1)->state == RunState::kInterrupted);
  CHECK(db.GetRun(1)->last_error.empty());
  const auto captured = db.ListCapturedProbes(1);
  CHECK(db.ListFrames(1, FrameKind::kPress).size() == captured.size());
  // Retracted: the ball is clear of the gel.
  const Eigen::Vector3d ball = f.rig->rig()->BallCenterSensor(f.rig->cnc().TruePositionNow());
  const TravelPlanner travel(MakeRigGeometry(f.config.rig), f.config.plan);
  CHECK(travel.ToolGaps(ball).ball > 0.5);
}

TEST_CASE("a second gs360d on the same data folder or the same machine port refuses to start",
          "[daemon][lock]") {
  test::RigFixture f("second", 40, 0.0);
  auto first = test::StartDaemonProcess(f);
  const std::string gs360d = std::string(GS360_BINARY_DIR) + "/daemon/gs360d";
  // The same configuration: the data folder is taken.
  const auto log = f.dir / "second.log";
  CHECK_THROWS_WITH(cli::DaemonProcess(gs360d, f.dir / "gs360d.toml", f.dir / "data", log,
                                       std::chrono::seconds(20)),
                    Catch::Contains("data folder") &&
                        Catch::Contains("in use by gs360d pid " + std::to_string(first->pid())));
  // Another data folder, the same machine: the port is taken.
  const auto other = f.dir / "other.toml";
  std::ofstream(other) << test::RigToml(f.config).replace(
      0, std::string("data_dir = \"data\"").size(), "data_dir = \"data2\"");
  CHECK_THROWS_WITH(
      cli::DaemonProcess(gs360d, other, f.dir / "data2", log, std::chrono::seconds(20)),
      Catch::Contains("machine port") && Catch::Contains(first->url()));
  // The first is unharmed.
  cli::DaemonClient client(first->url(), "");
  CHECK(client.Get("/api/v1/info")["name"] == "gs360d");
  CHECK(first->Stop() == 0);
}

TEST_CASE(
    "storage: a read-only database stops gs360d naming the file and the run resumes once "
    "it is writable",
    "[daemon][storage]") {
  test::RigFixture f("readonly", 40, 0.0);
  const auto db_path = f.dir / "data" / "gs360.db";
  {
    auto daemon = test::StartDaemonProcess(f);
    cli::DaemonClient client(daemon->url(), "");
    client.Post("/api/v1/runs", {{"probes", 40}});
    client.Post("/api/v1/runs/1/start");
    WaitFor(client, 1, [](const Json& r) { return r["probes_done"].get<int>() >= 4; });
    CHECK(daemon->Stop() == 0);
  }
  const std::int64_t before = ReadOnly(db_path).CountProbes(1).captured;
  REQUIRE(before >= 4);
  // The file loses its write permission (copied back by another user, a restored backup), and
  // gs360d runs as a service user would: without root's capabilities, so the permission counts.
  namespace fs = std::filesystem;
  fs::permissions(db_path, fs::perms::owner_read | fs::perms::group_read | fs::perms::others_read);
  const auto unprivileged = f.dir / "gs360d-unprivileged";
  std::ofstream(unprivileged) << "#!/bin/sh\nexec setpriv --bounding-set=-all --inh-caps=-all '"
                              << GS360_BINARY_DIR << "/daemon/gs360d' \"$@\"\n";
  fs::permissions(unprivileged, fs::perms::owner_all);
  CHECK_THROWS_WITH(cli::DaemonProcess(unprivileged, f.dir / "gs360d.toml", f.dir / "data",
                                       f.dir / "readonly.log", std::chrono::seconds(20)),
                    Catch::Contains(db_path.string()) && Catch::Contains("not writable"));
  CHECK(ReadOnly(db_path).CountProbes(1).captured == before);

  // Writable again: the run resumes where it stopped and every probe is captured once.
  fs::permissions(db_path, fs::perms::owner_write, fs::perm_options::add);
  auto daemon = std::make_unique<cli::DaemonProcess>(unprivileged, f.dir / "gs360d.toml",
                                                     f.dir / "data", f.dir / "gs360d.log");
  cli::DaemonClient client(daemon->url(), "");
  client.Post("/api/v1/runs/1/resume");
  const Json done = WaitFor(client, 1, [](const Json& r) { return r["state"] == "done"; });
  CHECK(done["probes_done"].get<int>() > before);
  CHECK(daemon->Stop() == 0);
  RunDatabase db = ReadOnly(db_path);
  const auto captured = db.ListCapturedProbes(1);
  CHECK(static_cast<std::int64_t>(captured.size()) == db.CountProbes(1).captured);
  CHECK(db.ListFrames(1, FrameKind::kPress).size() == captured.size());
  CHECK(db.CountProbes(1).planned == 0);
}

TEST_CASE("gs360d tells systemd it is ready, pings the watchdog and reports the run's progress",
          "[daemon][systemd]") {
  test::RigFixture f("notify", 60, 0.0);
  // A notification socket as systemd would give it (Type=notify, WatchdogSec=).
  const auto socket_path = f.dir / "notify.sock";
  const int fd = ::socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC, 0);
  REQUIRE(fd >= 0);
  sockaddr_un addr{};
  addr.sun_family = AF_UNIX;
  std::strncpy(addr.sun_path, socket_path.c_str(), sizeof(addr.sun_path) - 1);
  REQUIRE(::bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) == 0);
  timeval timeout{0, 200000};
  ::setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &timeout, sizeof timeout);
  ::setenv("NOTIFY_SOCKET", socket_path.c_str(), 1);
  ::setenv("WATCHDOG_USEC", "300000", 1);
  auto daemon = test::StartDaemonProcess(f);
  ::unsetenv("NOTIFY_SOCKET");
  ::unsetenv("WATCHDOG_USEC");
  cli::DaemonClient client(daemon->url(), "");
  client.Post("/api/v1/runs", {{"probes", 60}});
  client.Post("/api/v1/runs/1/start");

  std::vector<std::string> messages;
  bool ready = false, watchdog = false, progress = false;
  for (int i = 0; i < 300 && !(ready && watchdog && progress); ++i) {
    char buf[512];
    const ssize_t n = ::recv(fd, buf, sizeof buf, 0);
    if (n <= 0) continue;
    const std::string m(buf, static_cast<std::size_t>(n));
    messages.push_back(m);
    if (m.find("READY=1") != std::string::npos) {
      ready = true;
      CHECK_THAT(m, Catch::Contains("STATUS=listening on " + daemon->url()));
    }
    if (m.find("WATCHDOG=1") != std::string::npos) watchdog = true;
    if (m.find("STATUS=run 1: ") != std::string::npos && m.find(" probes") != std::string::npos) {
      progress = true;
    }
  }
  INFO("received: " << messages.size() << " messages, last "
                    << (messages.empty() ? "" : messages.back()));
  CHECK(ready);
  CHECK(watchdog);
  CHECK(progress);
  // systemd keeps reading: a full socket would block the daemon's notifications (as it would
  // under systemd), so drain it while the daemon stops.
  std::atomic<bool> stopped{false};
  std::thread drain([&] {
    char buf[512];
    while (!stopped) ::recv(fd, buf, sizeof buf, 0);
  });
  CHECK(daemon->Stop(std::chrono::seconds(60)) == 0);
  stopped = true;
  drain.join();
  ::close(fd);
}
