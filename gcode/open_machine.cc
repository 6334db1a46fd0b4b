#include "gcode/open_machine.h"

#include <algorithm>
#include <functional>
#include <optional>
#include <stdexcept>
#include <string_view>
#include <vector>

#include "gcode/grbl_machine.h"
#include "gcode/grbl_messages.h"

namespace gs360 {
namespace {

using Clock = std::chrono::steady_clock;

bool StartsWith(std::string_view s, std::string_view p) {
  return s.substr(0, p.size()) == p;
}

// What one line says about the firmware; nullopt when it tells nothing.
std::optional<MachineFirmware> Tell(std::string_view line) {
  for (std::string_view p : {"Grbl", "GrblHAL", "[MSG:", "[VER:", "ALARM:", "error:", "<"}) {
    if (StartsWith(line, p)) return MachineFirmware::kGrbl;
  }
  for (std::string_view p : {"start", "echo:", "FIRMWARE_NAME:", "Cap:", "//", "!!"}) {
    if (StartsWith(line, p)) return MachineFirmware::kMarlin;
  }
  return std::nullopt;
}

// Reads until a line tells the firmware or `wait` passes; every byte read is appended to `seen`.
std::optional<MachineFirmware> Listen(Transport& t, std::chrono::milliseconds wait,
                                      std::string* seen) {
  GrblLineSplitter splitter;
  const auto until = Clock::now() + wait;
  std::vector<std::string> lines;
  while (Clock::now() < until) {
    char buf[256];
    const std::size_t n = t.Read(buf, sizeof buf, std::chrono::milliseconds(50));
    seen->append(buf, n);
    splitter.Feed(buf, n, &lines);
    for (const std::string& line : lines) {
      if (const auto f = Tell(line)) return f;
    }
    lines.clear();
  }
  return std::nullopt;
}

// A transport that first gives back what detection read from it.
class ReplayTransport : public Transport {
 public:
  ReplayTransport(std::unique_ptr<Transport> inner, std::string replay)
      : inner_(std::move(inner)), replay_(std::move(replay)) {}
  void Write(std::string_view bytes) override { inner_->Write(bytes); }
  std::size_t Read(char* buf, std::size_t n, std::chrono::milliseconds timeout) override {
    if (replay_.empty()) return inner_->Read(buf, n, timeout);
    const std::size_t k = std::min(n, replay_.size());
    replay_.copy(buf, k);
    replay_.erase(0, k);
    return k;
  }
  std::string Describe() const override { return inner_->Describe(); }

 private:
  std::unique_ptr<Transport> inner_;
  std::string replay_;
};

}  // namespace

FirmwareDetection DetectFirmware(Transport& transport, std::chrono::milliseconds wait) {
  FirmwareDetection d;
  if (const auto f = Listen(transport, wait, &d.replay)) {
    d.firmware = *f;
    return d;
  }
  // Silent (no reset on open): asked. Its answer is the detection's, not the session's: dropped,
  // with whatever follows it until the line is quiet.
  transport.Write("M115\n");
  std::string answer;
  const auto f = Listen(transport, wait, &answer);
  if (!f) {
    throw std::runtime_error("nothing at " + transport.Describe() +
                             " answered as GRBL or Marlin (no welcome, no start, no answer to "
                             "M115): set [machine] firmware in gs360d.toml, and check the port "
                             "and its baud rate");
  }
  char buf[256];
  while (transport.Read(buf, sizeof buf, std::chrono::milliseconds(200)) > 0) {
  }
  d.firmware = *f;
  return d;
}

std::unique_ptr<Machine> OpenMachine(MachineFirmware firmware, const std::string& uri,
                                     const OpenMachineOptions& options, MachineFirmware* detected) {
  options.transport.Check();
  std::function<std::unique_ptr<Transport>()> factory = [uri, t = options.transport] {
    return OpenTransport(uri, t);
  };
  if (firmware == MachineFirmware::kAuto) {
    auto transport = OpenTransport(uri, options.transport);
    FirmwareDetection d = DetectFirmware(*transport, options.detect_wait);
    firmware = d.firmware;
    // The port stays open: a board that resets on open is not rebooted twice, and what it said
    // (a welcome, its start) is read again by the machine's own handshake.
    auto primed = std::make_shared<std::unique_ptr<Transport>>(
        std::make_unique<ReplayTransport>(std::move(transport), std::move(d.replay)));
    factory = [primed, next = factory]() -> std::unique_ptr<Transport> {
      if (*primed) return std::move(*primed);
      return next();
    };
  }
  if (detected) *detected = firmware;
  if (firmware == MachineFirmware::kMarlin) {
    return std::make_unique<MarlinMachine>(factory, options.marlin);
  }
  return std::make_unique<GrblMachine>(std::make_unique<GrblClient>(factory, options.grbl));
}

}  // namespace gs360
