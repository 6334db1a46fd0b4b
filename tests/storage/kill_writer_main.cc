// storage_kill_writer DB_PATH {full|normal}: commits probes into DB_PATH forever, the way the
// run engine does, until it is killed. When a run's plan is exhausted it marks the run done
// and starts another. Prints "ready" once the database is open. Used by kill_test.cc, which
// SIGKILLs it at random moments.

#include <cstdio>
#include <cstring>
#include <exception>
#include <string>
#include <vector>

#include "storage/run_database.h"
#include "tests/storage/kill_writer_common.h"

int main(int argc, char** argv) {
  using namespace gs360;
  if (argc != 3) {
    std::fprintf(stderr, "usage: %s DB_PATH {full|normal}\n", argv[0]);
    return 2;
  }
  try {
    RunDatabaseOptions options;
    options.synchronous = std::strcmp(argv[2], "normal") == 0 ? SyncMode::kNormal : SyncMode::kFull;
    std::vector<EncodedFrame> pool;
    for (int k = 0; k < test::kKillPoolSize; ++k)
      pool.push_back(EncodeFrame(test::KillPoolFrame(k)));
    RunDatabase db(argv[1], options);
    // Process start-up (loading OpenCV) takes ~0.1 s; tell the test when the real work starts.
    std::fputs("ready\n", stdout);
    std::fflush(stdout);
    for (;;) {
      std::vector<RunRecord> runs = db.ListRuns();
      if (runs.empty() || IsTerminal(runs.back().state)) {
        db.CreateRun(R"({"writer": "storage_kill_writer"})", "kill-test-mesh");
        continue;
      }
      const std::int64_t run = runs.back().id;
      if (db.CountProbes(run).total == 0) {
        std::vector<ProbePlanEntry> plan;
        for (int i = 0; i < test::kKillPlanSize; ++i) plan.push_back(test::KillPlanEntry(i));
        db.InsertPlan(run, plan);
      }
      // A run left "running" belonged to a writer that was killed: record the interruption
      // and resume it, as the daemon does on start-up.
      if (runs.back().state == RunState::kRunning) db.SetRunState(run, RunState::kInterrupted);
      db.SetRunState(run, RunState::kRunning);
      for (;;) {
        const std::optional<ProbeRecord> p = db.NextPendingProbe(run, 2);
        if (!p) break;
        const int i = p->plan_index;
        if (test::KillSkips(i)) {
          db.MarkProbeSkipped(p->id, "unreachable");
          continue;
        }
        if (test::KillFailsFirst(i) && p->attempts == 0) {
          db.MarkProbeFailed(p->id, "sync timeout");
          db.AppendEvent(run, EventLevel::kWarning, "probe failed",
                         R"({"plan_index": )" + std::to_string(i) + "}");
          continue;
        }
        if (test::KillHasReference(i)) {
          db.AddReferenceFrame(run, pool[test::KillReferenceSlot(i)], test::KillReferenceTime(i));
        }
        db.CommitCapture(p->id, pool[test::KillPressSlot(run, i)],
                         {test::KillPosition(i), test::KillSyncTime(i), test::KillFrameTime(i)});
      }
      db.SetRunState(run, RunState::kDone);
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "storage_kill_writer: %s\n", e.what());
    return 1;
  }
}
