#include "gcode/marlin_client.h"

#include <algorithm>
#include <array>
#include <cctype>
#include <string>

namespace gs360 {
namespace {

using Clock = std::chrono::steady_clock;

// G-code words that heat: a calibration rig's printer has nothing to melt, and a heater left on
// unattended overnight is a fire risk.
bool Heats(std::string_view command) {
  static constexpr std::array<std::string_view, 6> kHeating = {"M104", "M109", "M140",
                                                               "M190", "M141", "M191"};
  std::string word;
  for (char c : command) {
    if (c == ' ' || c == ';') break;
    word.push_back(static_cast<char>(std::toupper(static_cast<unsigned char>(c))));
  }
  return std::find(kHeating.begin(), kHeating.end(), word) != kHeating.end();
}

}  // namespace

void MarlinClientOptions::Check() const {
  const auto positive = [](const char* field, std::chrono::milliseconds v) {
    if (v.count() <= 0) {
      throw std::invalid_argument(std::string("MarlinClientOptions.") + field +
                                  " must be > 0 ms, got " + std::to_string(v.count()));
    }
  };
  positive("boot_timeout", boot_timeout);
  positive("boot_quiet", boot_quiet);
  positive("reply_timeout", reply_timeout);
  if (max_retries < 0) {
    throw std::invalid_argument("MarlinClientOptions.max_retries must be >= 0, got " +
                                std::to_string(max_retries));
  }
}

bool MarlinInfo::Has(const std::string& capability) const {
  const auto it = capabilities.find(capability);
  return it != capabilities.end() && it->second;
}

MarlinClient::MarlinClient(std::unique_ptr<Transport> transport, const MarlinClientOptions& options)
    : transport_(std::move(transport)), options_(options) {
  options_.Check();
  if (!transport_) throw std::invalid_argument("MarlinClient: no transport");
}

std::optional<MarlinMessage> MarlinClient::ReadLine(std::chrono::milliseconds wait) {
  const auto until = Clock::now() + wait;
  while (lines_.empty()) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(until - Clock::now());
    if (left.count() <= 0) return std::nullopt;
    char buf[256];
    const std::size_t n =
        transport_->Read(buf, sizeof buf, std::min(left, std::chrono::milliseconds(50)));
    splitter_.Feed(buf, n, &lines_);
  }
  MarlinMessage m = ParseMarlinLine(lines_.front());
  lines_.erase(lines_.begin());
  return m;
}

void MarlinClient::WriteLine(const std::string& line) {
  transport_->Write(line + "\n");
}

// The boot messages' end, within a second boot_timeout: a line that never goes quiet (noise,
// a flood of reports) is not waited for forever. What arrives meanwhile is dropped: besides the
// boot's echoes, it may answer a line written while the board was restarting (the new boot
// refuses its number and asks for line 1), which must not be taken for an answer to the
// numbering that starts now.
void MarlinClient::AwaitBootEnd() {
  const auto quiet_until = Clock::now() + options_.boot_timeout;
  while (Clock::now() < quiet_until && ReadLine(options_.boot_quiet)) {
  }
  stream_.Restart();
}

MarlinInfo MarlinClient::Connect() {
  info_ = MarlinInfo{};
  // A board that reboots when the port opens prints "start" once its bootloader has passed; a
  // line written before then is lost, or taken by the bootloader.
  const auto boot_until = Clock::now() + options_.boot_timeout;
  while (Clock::now() < boot_until && !info_.rebooted_on_open) {
    const auto m = ReadLine(std::chrono::milliseconds(50));
    if (m && m->kind == MarlinMessageKind::kStart) info_.rebooted_on_open = true;
  }
  AwaitBootEnd();
  for (const MarlinMessage& m : Execute("M115", options_.reply_timeout).messages) {
    if (m.kind == MarlinMessageKind::kFirmware) {
      info_.firmware = m.text;
      info_.machine_type = m.name;
    }
    if (m.kind == MarlinMessageKind::kCapability) info_.capabilities[m.name] = m.enabled;
  }
  for (const MarlinMessage& m : Execute("M211", options_.reply_timeout).messages) {
    if (m.kind != MarlinMessageKind::kSoftEndstops) continue;
    info_.soft_endstops = m.enabled;
    info_.soft_min = m.soft_min;
    info_.soft_max = m.soft_max;
  }
  return info_;
}

MarlinReply MarlinClient::Execute(std::string_view command, std::chrono::milliseconds timeout) {
  if (Heats(command)) {
    throw std::invalid_argument("MarlinClient: \"" + std::string(command) +
                                "\" heats; gs360 never sends a heating command");
  }
  if (stream_.Halted()) {
    throw MarlinError(MarlinError::Kind::kHalted,
                      "the printer is halted: reset it (M999 or its reset button) and confirm "
                      "the position before anything moves");
  }
  const std::uint64_t sequence = stream_.Queue(command);
  MarlinReply reply;
  const auto deadline = Clock::now() + timeout;
  auto last_heard = Clock::now();
  int retries = 0;
  const std::string what = "\"" + std::string(command) + "\"";
  while (true) {
    while (const auto line = stream_.NextToWrite()) WriteLine(*line);
    const auto m = ReadLine(std::chrono::milliseconds(50));
    // Checked whatever arrives: a printer that only ever says it is busy, or a line full of
    // garbage, must not hold the call past its time.
    if (Clock::now() > deadline) {
      throw MarlinError(MarlinError::Kind::kTimeout,
                        what + " not done within " + std::to_string(timeout.count()) + " ms");
    }
    if (!m) {
      if (Clock::now() - last_heard < options_.reply_timeout) continue;
      if (++retries > options_.max_retries) {
        throw MarlinError(MarlinError::Kind::kTimeout,
                          "no answer from the printer to " + what + " after " +
                              std::to_string(options_.max_retries) + " retries");
      }
      if (const auto again = stream_.RetryInFlight()) WriteLine(*again);
      last_heard = Clock::now();
      continue;
    }
    last_heard = Clock::now();
    const MarlinStreamEvent e = stream_.OnReply(*m);
    switch (e.kind) {
      case MarlinStreamEvent::Kind::kAcked:
        if (e.sequence == sequence) return reply;
        break;
      case MarlinStreamEvent::Kind::kBusy:
        ++reply.busy;
        break;
      case MarlinStreamEvent::Kind::kHalted:
        throw MarlinError(MarlinError::Kind::kHalted,
                          "the printer halted during " + what + " (\"" + e.text +
                              "\"): reset it and confirm the position before anything moves");
      case MarlinStreamEvent::Kind::kRebooted:
        stream_.ClearQueue();
        AwaitBootEnd();
        throw MarlinError(MarlinError::Kind::kRebooted,
                          "the printer rebooted during " + what +
                              ": it may not have run, and the printer no longer knows where it "
                              "is (it reports 0,0,0 until homed)");
      case MarlinStreamEvent::Kind::kError:
        if (m->kind == MarlinMessageKind::kResend) {
          throw MarlinError(MarlinError::Kind::kProtocol, e.text);
        }
        break;
      default:
        break;
    }
    if (m->kind != MarlinMessageKind::kOk && m->kind != MarlinMessageKind::kEmpty) {
      reply.messages.push_back(*m);
    }
  }
}

Eigen::Vector3d MarlinClient::StoppedPosition(std::chrono::milliseconds timeout, bool real) {
  Execute("M400", timeout);
  const MarlinReply r = Execute(real ? "M114 R" : "M114", options_.reply_timeout);
  for (const MarlinMessage& m : r.messages) {
    if (m.kind == MarlinMessageKind::kPosition) return *m.position;
  }
  throw MarlinError(
      MarlinError::Kind::kProtocol,
      std::string("the printer's answer to ") + (real ? "M114 R" : "M114") + " held no position");
}

void MarlinClient::EmergencyStop() {
  WriteLine("M112");
}

}  // namespace gs360
