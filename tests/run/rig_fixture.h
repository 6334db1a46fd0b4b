#pragma once
// A virtual rig plus a matching run configuration and a fresh database, for run-engine tests.

#include <unistd.h>

#include <catch2/catch.hpp>

#include <atomic>
#include <cstdlib>
#include <filesystem>
#include <functional>
#include <memory>
#include <string>

#include "cli/sim_bridge.h"
#include "run/run_config.h"
#include "run/run_engine.h"
#include "sim/virtual_rig.h"
#include "storage/run_database.h"
#include "tests/wait.h"

namespace gs360::test {

inline std::filesystem::path FreshDir(const std::string& name) {
  static std::atomic<int> n{0};
  auto dir = std::filesystem::temp_directory_path() /
             ("gs360-" + name + "-" + std::to_string(::getpid()) + "-" + std::to_string(n++));
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  return dir;
}

struct RigFixture {
  RunConfig config;
  std::unique_ptr<VirtualRig> rig;
  std::filesystem::path dir;
  std::filesystem::path db;

  // `candidates`: points sampled (about half are kept on the default cylinder); `time_scale` 0 is
  // instant motion.
  // `tweak` adjusts the virtual rig's options (firmware, settings) before it is built;
  // `configure` the run's configuration before the rig is built from it.
  RigFixture(const std::string& name, int candidates, double time_scale, bool symlink = false,
             const std::function<void(VirtualRigOptions&)>& tweak = {},
             const std::function<void(RunConfig&)>& configure = {}) {
    dir = FreshDir(name);
    db = dir / "run.db";
    config.name = name;
    config.plan.probe_count = candidates;
    config.plan.reference_every = 25;
    if (configure) configure(config);
    cli::VirtualSetup setup =
        cli::MakeVirtualSetup(config, time_scale, 7, dir / "camera.sock",
                              symlink ? (dir / "ttyCNC").string() : "", tweak);
    config = setup.config;
    rig = std::move(setup.rig);
    config.engine.reconnect_timeout_s = 10.0;
    // The virtual camera renders in this process: slower under a sanitizer.
    config.camera.capture.timeout = Scaled(config.camera.capture.timeout);
  }
  ~RigFixture() {
    rig.reset();
    // GS360_KEEP_TEST_DIRS=1 keeps the database and logs for a look afterwards.
    if (const char* keep = std::getenv("GS360_KEEP_TEST_DIRS"); keep && *keep == '1') return;
    std::error_code ec;
    std::filesystem::remove_all(dir, ec);
  }
};

// Calls `action` once, from the progress callback, when `after` probes are committed.
inline void AtProbe(RunEngine& engine, std::int64_t after, std::function<void()> action) {
  auto done = std::make_shared<std::atomic<bool>>(false);
  engine.SetProgressCallback([=](const RunProgress& p) {
    if (p.counts.captured >= after && !done->exchange(true)) action();
  });
}

// Runs `run_id` until at least `after` probes are committed, then stops it (left interrupted).
inline void StopAfter(RunEngine& engine, std::int64_t run_id, std::int64_t after) {
  AtProbe(engine, after, [&engine] { engine.RequestStop(); });
  REQUIRE(engine.Execute(run_id).outcome == RunOutcome::kStopped);
}

// Every event message of the run, one per line (the fixture's database, read-only).
inline std::string RunEvents(const RigFixture& f, std::int64_t run_id) {
  RunDatabaseOptions ro;
  ro.read_only = true;
  RunDatabase db(f.db, ro);
  std::string all;
  for (const EventRecord& e : db.ListEvents(run_id, 0, 100000)) all += e.message + "\n";
  return all;
}

}  // namespace gs360::test
