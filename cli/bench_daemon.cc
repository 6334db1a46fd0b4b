// `gs360 bench daemon`: does gs360d stay responsive, and does the run keep its pace, while many
// clients watch? A run on the virtual rig at a time scale where motion still dominates a probe.
// The probes' pace varies along the plan (travel lengths), so quiet and loaded stretches
// alternate on the same run (`--cycles` of each, `--seconds` of load in all): no clients, then N
// pollers of GET /runs/ID at H Hz plus S event-stream clients. Prints the status latency (p50,
// p99, max) under load and the probes per hour with clients against without.

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <mutex>
#include <thread>
#include <vector>

#include "cli/commands.h"
#include "cli/daemon_client.h"
#include "cli/daemon_process.h"
#include "cli/progress.h"
#include "cli/sim_bridge.h"
#include "gcode/grbl_client.h"
#include "sim/virtual_rig.h"

// After Eigen (its kernels name a parameter `_res`, a macro of <resolv.h>).
#include <httplib.h>

namespace gs360::cli {
namespace {

using Clock = std::chrono::steady_clock;
using Json = nlohmann::json;

struct DaemonBenchOptions {
  double seconds = 60.0;  // of load in all, as much quiet
  int cycles = 4;
  int pollers = 50;
  double hz = 10.0;
  int streams = 5;
  double time_scale = 10.0;
  int probes = 3000;
};

struct Load {
  std::vector<double> latency_ms;
  std::int64_t requests = 0;
  std::int64_t failures = 0;
  std::int64_t events = 0;
};

double Percentile(std::vector<double> v, double q) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  return v[static_cast<std::size_t>(q * static_cast<double>(v.size() - 1))];
}

// Probes done and seconds passed over `seconds` of the running run.
struct Stretch {
  double probes = 0.0;
  double seconds = 0.0;
};
Stretch Measure(DaemonClient& client, double seconds) {
  const auto a = client.Get("/api/v1/runs/1");
  const auto t0 = Clock::now();
  std::this_thread::sleep_for(std::chrono::duration<double>(seconds));
  const auto b = client.Get("/api/v1/runs/1");
  return {b["probes_done"].get<double>() - a["probes_done"].get<double>(),
          std::chrono::duration<double>(Clock::now() - t0).count()};
}

void Loaded(const std::string& url, const DaemonBenchOptions& o, double seconds, Load& load,
            Stretch& stretch) {
  std::mutex mutex;
  std::atomic<bool> stop{false};
  std::vector<std::thread> threads;
  for (int i = 0; i < o.pollers; ++i) {
    threads.emplace_back([&, i] {
      httplib::Client http(url);
      http.set_keep_alive(true);
      std::vector<double> mine;
      std::int64_t failed = 0;
      const auto period = std::chrono::duration<double>(1.0 / o.hz);
      // Spread the pollers over one period so they do not arrive in lock step.
      auto next =
          Clock::now() + std::chrono::duration_cast<Clock::duration>(period * i / o.pollers);
      while (!stop) {
        std::this_thread::sleep_until(next);
        next += std::chrono::duration_cast<Clock::duration>(period);
        const auto t0 = Clock::now();
        const auto r = http.Get("/api/v1/runs/1");
        const double ms = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
        if (r && r->status == 200) {
          mine.push_back(ms);
        } else {
          ++failed;
        }
      }
      std::lock_guard lock(mutex);
      load.latency_ms.insert(load.latency_ms.end(), mine.begin(), mine.end());
      load.requests += static_cast<std::int64_t>(mine.size()) + failed;
      load.failures += failed;
    });
  }
  std::atomic<std::int64_t> events{0};
  for (int i = 0; i < o.streams; ++i) {
    threads.emplace_back([&] {
      DaemonClient stream(url, "");
      try {
        stream.Events("", [&](const std::string&, const Json&) {
          ++events;
          return !stop.load();
        });
      } catch (const std::exception&) {
        // The stream ended with the benchmark.
      }
    });
  }
  DaemonClient client(url, "");
  const Stretch s = Measure(client, seconds);
  stop = true;
  // Each stream ends at its next event (progress comes several times a second).
  for (auto& t : threads) t.join();
  load.events += events;
  stretch.probes += s.probes;
  stretch.seconds += s.seconds;
}

int RunDaemonBench(const DaemonBenchOptions& o, bool json) {
  const auto dir =
      std::filesystem::temp_directory_path() / ("gs360-bench-daemon-" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  RunConfig config;
  VirtualSetup setup = MakeVirtualSetup(config, o.time_scale, 1, dir / "camera.sock");
  {
    std::ofstream toml(dir / "gs360d.toml");
    toml << "data_dir = \".\"\n[server]\nport = 0\nthreads = " << (o.pollers + o.streams + 16)
         << "\n"
         << setup.DaemonToml();
  }
  DaemonProcess daemon(FindGs360d(), dir / "gs360d.toml", dir, dir / "gs360d.log");
  DaemonClient client(daemon.url(), "");
  const Json run = client.Post("/api/v1/runs", {{"name", "bench"}, {"probes", o.probes}});
  client.Post("/api/v1/runs/1/start");
  // Past connecting and homing.
  while (client.Get("/api/v1/runs/1")["probes_done"].get<int>() < 3) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  std::fprintf(stderr,
               "bench daemon: %d pollers at %.0f Hz, %d event streams, %.0f s loaded, "
               "virtual rig at %.0fx real time (%s)\n",
               o.pollers, o.hz, o.streams, o.seconds, o.time_scale, daemon.url().c_str());
  Load load;
  Stretch quiet_total, loaded_total;
  const double piece = o.seconds / o.cycles;
  for (int c = 0; c < o.cycles; ++c) {
    const Stretch q = Measure(client, piece);
    quiet_total.probes += q.probes;
    quiet_total.seconds += q.seconds;
    Loaded(daemon.url(), o, piece, load, loaded_total);
    std::fprintf(stderr, "  cycle %d/%d: %.0f probes quiet, %.0f with clients so far\n", c + 1,
                 o.cycles, quiet_total.probes, loaded_total.probes);
  }
  const Json end = client.Get("/api/v1/runs/1");
  client.Post("/api/v1/runs/1/cancel");
  daemon.Stop();
  std::filesystem::remove_all(dir);

  const double quiet = 3600.0 * quiet_total.probes / quiet_total.seconds;
  const double loaded = 3600.0 * loaded_total.probes / loaded_total.seconds;
  const double loss = quiet > 0 ? 100.0 * (1.0 - loaded / quiet) : 0.0;
  const Json figures{
      {"pollers", o.pollers},
      {"poll_hz", o.hz},
      {"streams", o.streams},
      {"seconds", o.seconds},
      {"time_scale", o.time_scale},
      {"requests", load.requests},
      {"failures", load.failures},
      {"events_received", load.events},
      {"latency_ms",
       {{"p50", Percentile(load.latency_ms, 0.50)},
        {"p99", Percentile(load.latency_ms, 0.99)},
        {"max", Percentile(load.latency_ms, 1.0)}}},
      {"cycles", o.cycles},
      {"probes_per_hour", {{"quiet", quiet}, {"loaded", loaded}}},
      {"rate_loss_percent", loss},
      {"probes_done", end["probes_done"]},
      {"targets", {{"p99_ms", 50.0}, {"rate_loss_percent", 2.0}}},
      {"pass", Percentile(load.latency_ms, 0.99) < 50.0 && loss <= 2.0 && load.failures == 0}};
  if (json) {
    std::printf("%s\n", figures.dump(2).c_str());
  } else {
    std::printf("bench daemon: %lld status requests (%lld failed), %lld events received\n",
                static_cast<long long>(load.requests), static_cast<long long>(load.failures),
                static_cast<long long>(load.events));
    std::printf("  status latency       p50 %.2f ms, p99 %.2f ms, max %.2f ms (target p99 < 50)\n",
                Percentile(load.latency_ms, 0.5), Percentile(load.latency_ms, 0.99),
                Percentile(load.latency_ms, 1.0));
    std::printf("  probes per hour      %.0f without clients, %.0f with (%d cycles of each)\n",
                quiet, loaded, o.cycles);
    std::printf("  with clients         %.2f %% fewer than quiet (target <= 2 %%)\n", loss);
  }
  return figures["pass"].get<bool>() ? kExitOk : kExitError;
}

}  // namespace

void RegisterDaemonBench(CLI::App& bench, CommandContext& ctx) {
  static DaemonBenchOptions o;
  auto* cmd = bench.add_subcommand(
      "daemon",
      "gs360d under many clients: status latency and the run's pace (docs/benchmarks.md)");
  cmd->add_option("--seconds", o.seconds, "Seconds with clients in all (as many without)")
      ->capture_default_str();
  cmd->add_option("--cycles", o.cycles, "Alternations of quiet and loaded stretches")
      ->capture_default_str();
  cmd->add_option("--pollers", o.pollers, "Clients polling the run's status")
      ->capture_default_str();
  cmd->add_option("--hz", o.hz, "Polls per second per client")->capture_default_str();
  cmd->add_option("--streams", o.streams, "Event-stream clients")->capture_default_str();
  cmd->add_option("--time-scale", o.time_scale, "Virtual machine speed (x real time)")
      ->capture_default_str();
  cmd->add_option("--probes", o.probes, "Candidate probes of the run (enough to outlast it)")
      ->capture_default_str();
  cmd->callback([&ctx] { ctx.exit_code = RunDaemonBench(o, ctx.json); });
}

}  // namespace gs360::cli
