// `gs360 bench daemon`: does gs360d stay responsive, and does the run keep its pace, while many
// clients watch and others misbehave? A run on the virtual rig at a time scale where motion
// still dominates a probe. The probes' pace varies along the plan (travel lengths), so quiet and
// loaded stretches alternate on the same run (`--cycles` of each, `--seconds` of load in all): no
// clients, then N pollers of GET /runs/ID at H Hz, S event streams, I idle sockets and W clients
// that send a header line every 4 s (the server cuts those off; they come back). Prints the status
// latency (p50, p99, max) under load, the time a pause takes to be answered in the crowd, and the
// probes per hour with clients against without.

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <unistd.h>

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
  int streams = 200;
  int idle = 500;
  int slow = 200;
  double time_scale = 10.0;
  int probes = 3000;
};

struct Load {
  std::vector<double> latency_ms;
  std::int64_t requests = 0;
  std::int64_t failures = 0;
  std::int64_t events = 0;
  std::int64_t reconnects = 0;  // idle and slow sockets the server closed (and the bench reopened)
  int streams_open = 0;         // event streams answered 200 (the rest: 503)
  double pause_ms = -1.0;       // POST pause answered, in the crowd (last cycle)
};

// A connection the crowd holds open (idle, slow or streaming): a socket and what it asked.
struct CrowdSocket {
  int fd = -1;
  std::string request;  // sent on connect ("" for an idle one)
};

int Connect(int port) {
  const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(static_cast<std::uint16_t>(port));
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (fd >= 0 && ::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
    ::close(fd);
    return -1;
  }
  return fd;
}

void Open(CrowdSocket& s, int port) {
  s.fd = Connect(port);
  if (s.fd >= 0 && !s.request.empty()) {
    ::send(s.fd, s.request.data(), s.request.size(), MSG_NOSIGNAL);
  }
}

// Idle sockets, slow senders and event streams on one thread with poll(): every 4 s each slow
// socket sends one more header line; a socket the server has closed is opened again; what the
// streams send is read and its events counted.
void Crowd(const std::string& url, const DaemonBenchOptions& o, const std::atomic<bool>& stop,
           Load& load) {
  const int port = std::stoi(url.substr(url.rfind(':') + 1));
  std::vector<CrowdSocket> crowd;
  const std::string stream = "GET /api/v1/events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n";
  const std::string slow = "GET /api/v1/info HTTP/1.1\r\nHost: 127.0.0.1\r\n";
  for (int i = 0; i < o.streams; ++i) crowd.push_back({-1, stream});
  for (int i = 0; i < o.idle; ++i) crowd.push_back({-1, ""});
  for (int i = 0; i < o.slow; ++i) crowd.push_back({-1, slow});
  for (CrowdSocket& s : crowd) Open(s, port);
  std::vector<pollfd> polls(crowd.size());
  auto next_line = Clock::now() + std::chrono::seconds(4);
  std::int64_t events = 0;
  std::int64_t reconnects = 0;
  std::vector<bool> answered(crowd.size(), false);
  char buf[16384];
  while (!stop) {
    for (std::size_t i = 0; i < crowd.size(); ++i) polls[i] = {crowd[i].fd, POLLIN, 0};
    ::poll(polls.data(), polls.size(), 200);
    for (std::size_t i = 0; i < crowd.size(); ++i) {
      if ((polls[i].revents & (POLLIN | POLLHUP | POLLERR)) == 0) continue;
      const ssize_t n = ::recv(crowd[i].fd, buf, sizeof buf, 0);
      if (n > 0) {
        const std::string_view got(buf, static_cast<std::size_t>(n));
        if (got.rfind("HTTP/1.1 200", 0) == 0) answered[i] = true;
        for (auto at = got.find("event: "); at != std::string_view::npos;
             at = got.find("event: ", at + 1)) {
          ++events;
        }
        continue;
      }
      ::close(crowd[i].fd);
      Open(crowd[i], port);
      ++reconnects;
    }
    if (Clock::now() >= next_line) {
      for (CrowdSocket& s : crowd) {
        if (s.request == slow) ::send(s.fd, "X-Slow: 1\r\n", 11, MSG_NOSIGNAL);
      }
      next_line += std::chrono::seconds(4);
    }
  }
  for (CrowdSocket& s : crowd) ::close(s.fd);
  load.events += events;
  load.reconnects += reconnects;
  load.streams_open =
      static_cast<int>(std::count(answered.begin(), answered.begin() + o.streams, true));
}

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

void Loaded(const std::string& url, const DaemonBenchOptions& o, double seconds, bool last,
            Load& load, Stretch& stretch) {
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
  threads.emplace_back([&] { Crowd(url, o, stop, load); });
  DaemonClient client(url, "");
  const Stretch s = Measure(client, seconds);
  if (last) {
    // Can the run still be paused from inside the crowd? (The pause is answered at once; the run
    // stops after its probe, after the stretch's figures are taken.)
    httplib::Client http(url);
    const auto t0 = Clock::now();
    const auto r = http.Post("/api/v1/runs/1/pause", "{}", "application/json");
    if (r && r->status == 202) {
      load.pause_ms = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
    }
  }
  stop = true;
  for (auto& t : threads) t.join();
  stretch.probes += s.probes;
  stretch.seconds += s.seconds;
}

// The figures as text: latency, the crowd, the pause, the rate with and without clients.
void PrintDaemonBench(const DaemonBenchOptions& o, const Load& load, double quiet, double loaded,
                      double loss) {
  std::printf("bench daemon: %lld status requests (%lld failed), %lld events received\n",
              static_cast<long long>(load.requests), static_cast<long long>(load.failures),
              static_cast<long long>(load.events));
  std::printf("  status latency       p50 %.2f ms, p99 %.2f ms, max %.2f ms (target p99 < 50)\n",
              Percentile(load.latency_ms, 0.5), Percentile(load.latency_ms, 0.99),
              Percentile(load.latency_ms, 1.0));
  std::printf(
      "  in the crowd         %d of %d event streams open, %d idle sockets, %d slow "
      "senders (%lld cut off and reopened)\n",
      load.streams_open, o.streams, o.idle, o.slow, static_cast<long long>(load.reconnects));
  std::printf("  pause answered in    %.1f ms (target < 1000)\n", load.pause_ms);
  std::printf("  probes per hour      %.0f without clients, %.0f with (%d cycles of each)\n", quiet,
              loaded, o.cycles);
  std::printf("  with clients         %.2f %% fewer than quiet (target <= 2 %%)\n", loss);
}

int RunDaemonBench(const DaemonBenchOptions& o, bool json) {
  // The crowd's sockets, and the daemon's (its own limit it raises itself).
  rlimit files{};
  getrlimit(RLIMIT_NOFILE, &files);
  files.rlim_cur = std::max(files.rlim_cur, std::min<rlim_t>(files.rlim_max, 8192));
  setrlimit(RLIMIT_NOFILE, &files);
  const auto dir =
      std::filesystem::temp_directory_path() / ("gs360-bench-daemon-" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  RunConfig config;
  VirtualSetup setup = MakeVirtualSetup(config, o.time_scale, 1, dir / "camera.sock");
  {
    std::ofstream toml(dir / "gs360d.toml");
    toml << "data_dir = \".\"\n[server]\nport = 0\n" << setup.DaemonToml();
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
               "bench daemon: %d pollers at %.0f Hz, %d event streams, %d idle sockets, %d slow "
               "senders, %.0f s loaded, virtual rig at %.0fx real time (%s)\n",
               o.pollers, o.hz, o.streams, o.idle, o.slow, o.seconds, o.time_scale,
               daemon.url().c_str());
  Load load;
  Stretch quiet_total, loaded_total;
  const double piece = o.seconds / o.cycles;
  for (int c = 0; c < o.cycles; ++c) {
    const Stretch q = Measure(client, piece);
    quiet_total.probes += q.probes;
    quiet_total.seconds += q.seconds;
    Loaded(daemon.url(), o, piece, c + 1 == o.cycles, load, loaded_total);
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
      {"streams_open", load.streams_open},
      {"idle_sockets", o.idle},
      {"slow_senders", o.slow},
      {"reconnects", load.reconnects},
      {"pause_ms", load.pause_ms},
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
      {"targets", {{"p99_ms", 50.0}, {"rate_loss_percent", 2.0}, {"pause_ms", 1000.0}}},
      {"pass", Percentile(load.latency_ms, 0.99) < 50.0 && loss <= 2.0 && load.failures == 0 &&
                   load.pause_ms >= 0 && load.pause_ms < 1000.0}};
  if (json) {
    std::printf("%s\n", figures.dump(2).c_str());
  } else {
    PrintDaemonBench(o, load, quiet, loaded, loss);
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
  cmd->add_option("--idle", o.idle, "Sockets that connect and send nothing")->capture_default_str();
  cmd->add_option("--slow", o.slow, "Clients that send a header line every 4 s")
      ->capture_default_str();
  cmd->add_option("--time-scale", o.time_scale, "Virtual machine speed (x real time)")
      ->capture_default_str();
  cmd->add_option("--probes", o.probes, "Candidate probes of the run (enough to outlast it)")
      ->capture_default_str();
  cmd->callback([&ctx] { ctx.exit_code = RunDaemonBench(o, ctx.json); });
}

}  // namespace gs360::cli
