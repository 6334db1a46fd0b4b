// A writer process is killed with SIGKILL at random moments, many times over; afterwards the
// database must be sound and every probe either fully committed or not at all.

#include <catch2/catch.hpp>

#include <poll.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <random>
#include <thread>

#include <opencv2/imgcodecs.hpp>

#include "base/hash.h"
#include "storage/run_database.h"
#include "tests/storage/kill_writer_common.h"
#include "tests/storage/storage_test_util.h"

extern char** environ;

namespace gs360 {
namespace {

struct Writer {
  pid_t pid = 0;
  int ready_fd = -1;  // the writer's stdout
};

Writer SpawnWriter(const std::string& db, const std::string& sync) {
  std::string exe = GS360_STORAGE_KILL_WRITER;
  std::vector<char*> argv = {exe.data(), const_cast<char*>(db.c_str()),
                             const_cast<char*>(sync.c_str()), nullptr};
  int fds[2];
  REQUIRE(::pipe(fds) == 0);
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_adddup2(&actions, fds[1], STDOUT_FILENO);
  posix_spawn_file_actions_addclose(&actions, fds[0]);
  Writer w;
  const int rc = ::posix_spawn(&w.pid, exe.c_str(), &actions, nullptr, argv.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  ::close(fds[1]);
  REQUIRE(rc == 0);
  w.ready_fd = fds[0];
  return w;
}

// Waits until the writer has opened the database (or exited); false on timeout.
bool WaitReady(const Writer& w) {
  pollfd pfd{w.ready_fd, POLLIN, 0};
  return ::poll(&pfd, 1, 20000) == 1;
}

TEST_CASE("SIGKILLed writers never leave a half-written probe", "[storage][kill]") {
  test::TempDir dir;
  const std::string path = (dir / "rig.gs360db").string();
  std::mt19937 rng(360);
  constexpr int kKills = 60;
  // Kill delays are drawn from [0, max_delay_ms]; on a slow machine (sanitizers, heavy load) a
  // writer may not finish a single transaction in that time, so the range doubles after three
  // kills in a row without progress.
  int max_delay_ms = 60;
  int stalled = 0;
  auto delay = [&] {
    return std::chrono::milliseconds(std::uniform_int_distribution<int>(0, max_delay_ms)(rng));
  };

  int kills = 0;
  std::int64_t last_done = 0;
  for (int iteration = 0; kills < kKills; ++iteration) {
    const Writer w = SpawnWriter(path, iteration % 2 == 0 ? "full" : "normal");
    // Every 8th kill lands anywhere in start-up and recovery; the others while committing.
    if (iteration % 8 == 7) {
      std::this_thread::sleep_for(delay() + std::chrono::milliseconds(60));
    } else {
      CHECK(WaitReady(w));
      std::this_thread::sleep_for(delay());
    }
    ::kill(w.pid, SIGKILL);
    ::close(w.ready_fd);
    int status = 0;
    REQUIRE(::waitpid(w.pid, &status, 0) == w.pid);
    if (WIFEXITED(status)) {
      FAIL("storage_kill_writer exited by itself with status " << WEXITSTATUS(status));
    }
    REQUIRE(WIFSIGNALED(status));
    REQUIRE(WTERMSIG(status) == SIGKILL);
    ++kills;

    // Reopen after every kill: committed work never goes backwards.
    if (std::filesystem::exists(path)) {
      RunDatabase db(path);
      std::int64_t done = 0;
      for (const RunRecord& run : db.ListRuns()) {
        const ProbeCounts c = db.CountProbes(run.id);
        done += c.captured + c.failed + c.skipped;
      }
      CHECK(done >= last_done);
      stalled = done > last_done ? 0 : stalled + 1;
      if (stalled >= 3 && max_delay_ms < 4000) {
        max_delay_ms *= 2;
        stalled = 0;
      }
      last_done = done;
    }
  }
  CHECK(kills >= 50);
  INFO("probes committed over " << kills << " kills: " << last_done << " (max kill delay "
                                << max_delay_ms << " ms)");
  CHECK(last_done >= 30);

  // The file as SQLite sees it, without RunDatabase's help.
  {
    test::RawDb raw(path);
    CHECK(raw.Text("PRAGMA integrity_check") == "ok");
    CHECK(raw.Column("PRAGMA foreign_key_check").empty());
    // Every captured probe has exactly one frame; no press frame without a captured probe.
    CHECK(raw.Int("SELECT count(*) FROM probes p WHERE p.state = 'captured' AND "
                  "(SELECT count(*) FROM frames f WHERE f.probe_id = p.id) <> 1") == 0);
    CHECK(raw.Int("SELECT count(*) FROM frames f LEFT JOIN probes p ON p.id = f.probe_id "
                  "WHERE f.kind = 'press' AND (p.id IS NULL OR p.state <> 'captured')") == 0);
    CHECK(raw.Int("SELECT count(*) FROM probes WHERE state = 'captured' AND "
                  "(mpos_x IS NULL OR sync_time IS NULL OR captured_at IS NULL)") == 0);
    // Each stored PNG matches its checksum and decodes.
    const std::vector<std::string> ids = raw.Column("SELECT id FROM frames ORDER BY id");
    CHECK(ids.size() >= 30);
    for (const std::string& id : ids) {
      const std::vector<std::uint8_t> png = raw.Blob("SELECT png FROM frames WHERE id = " + id);
      const std::string checksum = raw.Text("SELECT checksum FROM frames WHERE id = " + id);
      CAPTURE(id);
      REQUIRE(HashHex(png.data(), png.size()) == checksum);
      REQUIRE_FALSE(cv::imdecode(png, cv::IMREAD_UNCHANGED).empty());
    }
  }

  // Through the API: every committed byte is the one the writer meant to commit.
  RunDatabase db(path);
  CHECK(db.IntegrityCheck().empty());
  std::vector<cv::Mat> pool;
  for (int k = 0; k < test::kKillPoolSize; ++k) pool.push_back(test::KillPoolFrame(k));
  for (const RunRecord& run : db.ListRuns()) {
    CAPTURE(run.id);
    for (const ProbeRecord& p : db.ListProbes(run.id)) {
      const int i = p.plan_index;
      CAPTURE(i);
      REQUIRE(p.plan.press_machine == test::KillPosition(i));
      if (test::KillSkips(i)) {
        REQUIRE((p.state == ProbeState::kPlanned || p.state == ProbeState::kSkipped));
        REQUIRE(p.attempts == 0);
      } else if (p.state == ProbeState::kFailed) {
        REQUIRE(test::KillFailsFirst(i));
        REQUIRE(p.attempts == 1);
      } else if (p.state == ProbeState::kCaptured) {
        REQUIRE(p.attempts == (test::KillFailsFirst(i) ? 2 : 1));
        REQUIRE(*p.machine_position == test::KillPosition(i));
        REQUIRE(*p.sync_time == test::KillSyncTime(i));
      } else {
        REQUIRE(p.state == ProbeState::kPlanned);
        REQUIRE(p.attempts == 0);
      }
    }
    for (const CapturedProbe& c : db.ListCapturedProbes(run.id)) {
      CAPTURE(c.probe.plan_index);
      REQUIRE(c.frame_time == test::KillFrameTime(c.probe.plan_index));
      const cv::Mat& expected = pool[test::KillPressSlot(run.id, c.probe.plan_index)];
      REQUIRE(test::SameImage(db.LoadFrame(c.frame_id), expected));
    }
    for (const FrameInfo& f : db.ListFrames(run.id, FrameKind::kReference)) {
      const int i = test::KillReferenceIndex(f.timestamp);
      CAPTURE(f.id, i);
      REQUIRE(test::KillHasReference(i));
      REQUIRE(test::SameImage(db.LoadFrame(f.id), pool[test::KillReferenceSlot(i)]));
    }
  }
}

}  // namespace
}  // namespace gs360
