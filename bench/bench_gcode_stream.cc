// gcode/ streaming figures: GRBL line parsing rate, and GrblClient over a real pty against a
// minimal peer that answers "ok" per line (no motion): pipelined throughput with character
// counting, and the send -> ok round trip of a single line (what a press's G4 sync adds).
//
//   bench_gcode_stream [lines]   (default 20000)

#include <poll.h>
#include <pty.h>
#include <termios.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <limits>
#include <string>
#include <thread>
#include <vector>

#include <spdlog/spdlog.h>
#include <CLI/CLI.hpp>

#include "gcode/grbl_client.h"
#include "gcode/grbl_messages.h"

namespace {

using Clock = std::chrono::steady_clock;

// Answers "ok" to every line and a status report to '?', like an idle GRBL with a 128-byte RX.
class OkPeer {
 public:
  OkPeer() {
    termios raw{};
    ::cfmakeraw(&raw);
    char name[256] = {};
    if (::openpty(&master_, &slave_, name, &raw, nullptr) != 0) std::abort();
    path_ = name;
    const std::string hello = "\r\nGrbl 1.1h ['$' for help]\r\n";
    if (::write(master_, hello.data(), hello.size()) < 0) std::abort();
    thread_ = std::thread([this] { Loop(); });
  }
  ~OkPeer() {
    stop_ = true;
    thread_.join();
    ::close(master_);
    ::close(slave_);
  }
  const std::string& Path() const { return path_; }

 private:
  void Loop() {
    char buf[4096];
    std::string out;
    while (!stop_) {
      pollfd p{master_, POLLIN, 0};
      if (::poll(&p, 1, 20) <= 0) continue;
      const ssize_t n = ::read(master_, buf, sizeof(buf));
      if (n <= 0) continue;
      out.clear();
      for (ssize_t i = 0; i < n; ++i) {
        if (buf[i] == '\n') {
          if (line_ == "$I") out += "[VER:1.1h.20190830:]\r\n[OPT:V,15,128]\r\n";
          out += "ok\r\n";
          line_.clear();
        } else if (buf[i] == '?') {
          out += "<Idle|MPos:0.000,0.000,0.000|FS:0,0>\r\n";
        } else {
          line_.push_back(buf[i]);
        }
      }
      if (!out.empty() && ::write(master_, out.data(), out.size()) < 0) return;
    }
  }
  int master_ = -1;
  int slave_ = -1;
  std::string path_;
  std::string line_;
  std::atomic<bool> stop_{false};
  std::thread thread_;
};

double Percentile(std::vector<double> v, double q) {
  std::sort(v.begin(), v.end());
  return v[static_cast<std::size_t>(q * static_cast<double>(v.size() - 1))];
}

}  // namespace

int main(int argc, char** argv) {
  int lines = 20000;
  CLI::App app(
      "bench_gcode_stream: GRBL line parsing rate, pty streaming throughput and round trip");
  app.option_defaults()->always_capture_default();
  app.add_option("lines", lines, "lines streamed through the pty")
      ->transform(CLI::Bound(100, std::numeric_limits<int>::max()).description("raised to >= 100"));
  CLI11_PARSE(app, argc, argv);
  spdlog::set_level(spdlog::level::warn);

  // 1. Parsing.
  const std::vector<std::string> samples = {
      "ok",
      "error:20",
      "<Run|MPos:12.345,-67.890,1.250|Bf:12,96|FS:600,0|WCO:0.000,0.000,0.000>",
      "[MSG:Caution: Unlocked]",
      "$110=3000.000",
      "ALARM:2",
      "[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]"};
  const int parse_rounds = 200000;
  std::size_t sink = 0;
  auto t0 = Clock::now();
  for (int i = 0; i < parse_rounds; ++i) {
    sink += static_cast<std::size_t>(
        gs360::ParseGrblLine(samples[static_cast<std::size_t>(i) % samples.size()]).kind);
  }
  const double parse_s = std::chrono::duration<double>(Clock::now() - t0).count();
  std::printf("parse: %.2f M lines/s (mixed GRBL messages, %d lines, checksum %zu)\n",
              parse_rounds / parse_s / 1e6, parse_rounds, sink);

  // 2. Pipelined streaming through a pty with character counting.
  OkPeer peer;
  gs360::GrblClientOptions options;
  options.status_poll_interval = std::chrono::milliseconds(0);
  gs360::GrblClient client(
      [&] { return gs360::OpenTransport(peer.Path(), gs360::TransportOptions{}); }, options);
  client.Connect();
  client.MarkPositionTrusted();
  std::vector<gs360::GrblHandle> handles;
  handles.reserve(static_cast<std::size_t>(lines));
  t0 = Clock::now();
  for (int i = 0; i < lines; ++i) {
    handles.push_back(client.Send("G1 X" + std::to_string(i % 100) + ".123 Y45.678 Z-1.250 F600"));
  }
  for (const auto& h : handles) {
    if (!h.Wait(std::chrono::seconds(30)).Ok()) {
      std::fprintf(stderr, "line failed\n");
      return 1;
    }
  }
  const double stream_s = std::chrono::duration<double>(Clock::now() - t0).count();
  const auto stats = client.Stats();
  std::printf("stream: %d lines in %.3f s = %.0f lines/s (max %zu bytes in flight of %zu)\n", lines,
              stream_s, lines / stream_s, stats.max_in_flight_bytes, client.StreamCapacity());

  // 3. Round trip of one line at a time (send -> ok read), as for a press's G4 sync.
  std::vector<double> rtt_us;
  for (int i = 0; i < 2000; ++i) {
    const gs360::GrblReply r = client.Send("G4 P0").Wait(std::chrono::seconds(5));
    if (!r.Ok()) return 1;
    rtt_us.push_back(std::chrono::duration<double, std::micro>(r.received_at - r.sent_at).count());
  }
  std::printf("round trip send->ok: median %.0f us, p99 %.0f us, max %.0f us (2000 lines)\n",
              Percentile(rtt_us, 0.5), Percentile(rtt_us, 0.99), Percentile(rtt_us, 1.0));
  return 0;
}
