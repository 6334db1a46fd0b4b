#include "gcode/grbl_machine.h"

#include <utility>

namespace gs360 {
namespace {

std::string Alarm(int code) {
  return "ALARM:" + std::to_string(code) + " (" + GrblAlarmText(code) + ")";
}

class GrblSource : public MachineHandle::Source {
 public:
  explicit GrblSource(GrblHandle handle) : handle_(std::move(handle)) {}
  bool Done() const override { return handle_.Done(); }
  MachineReply Wait(std::chrono::milliseconds timeout) const override {
    return ToMachineReply(handle_.Wait(timeout));
  }

 private:
  GrblHandle handle_;
};

MachineState ToMachineState(GrblMachineState s) {
  switch (s) {
    case GrblMachineState::kUnknown:
      return MachineState::kUnknown;
    case GrblMachineState::kIdle:
      return MachineState::kIdle;
    case GrblMachineState::kRun:
    case GrblMachineState::kJog:
      return MachineState::kRun;
    case GrblMachineState::kHold:
      return MachineState::kHold;
    case GrblMachineState::kAlarm:
      return MachineState::kAlarm;
    case GrblMachineState::kHome:
      return MachineState::kHome;
    default:
      return MachineState::kOther;
  }
}

}  // namespace

MachineReply ToMachineReply(const GrblReply& g) {
  MachineReply r;
  switch (g.kind) {
    case GrblReplyKind::kOk:
      r.kind = MachineReplyKind::kOk;
      break;
    case GrblReplyKind::kError:
      r.kind = MachineReplyKind::kError;
      break;
    case GrblReplyKind::kReset:
      r.kind = MachineReplyKind::kReset;
      break;
    case GrblReplyKind::kRefused:
      r.kind = MachineReplyKind::kRefused;
      break;
    case GrblReplyKind::kDisconnected:
      r.kind = MachineReplyKind::kDisconnected;
      break;
    case GrblReplyKind::kClosed:
      r.kind = MachineReplyKind::kClosed;
      break;
    case GrblReplyKind::kTimeout:
      r.kind = MachineReplyKind::kTimeout;
      break;
  }
  r.line = g.line;
  r.sequence = g.sequence;
  r.error_code = g.error_code;
  if (g.kind == GrblReplyKind::kError) {
    r.error = "error:" + std::to_string(g.error_code) + " (" + GrblErrorText(g.error_code) + ")";
  }
  if (g.alarm_code) r.alarm = Alarm(*g.alarm_code);
  r.detail = g.detail;
  r.received_at = g.received_at;
  return r;
}

MachineStatus ToMachineStatus(const GrblStatusSample& sample) {
  MachineStatus s;
  s.state = ToMachineState(sample.status.state);
  s.state_text = sample.status.state_text;
  s.machine_position = sample.machine_position;
  s.received_at = sample.received_at;
  return s;
}

GrblMachine::GrblMachine(std::unique_ptr<GrblClient> client) : client_(std::move(client)) {}

std::unique_ptr<GrblMachine> GrblMachine::ForUri(const std::string& uri,
                                                 const TransportOptions& transport_options,
                                                 const GrblClientOptions& options) {
  return std::make_unique<GrblMachine>(GrblClient::ForUri(uri, transport_options, options));
}

MachineInfo GrblMachine::Connect() {
  const GrblMachineInfo g = client_->Connect();
  MachineInfo info;
  info.firmware = g.firmware + " " + g.version;
  info.description = info.firmware + " (RX buffer " + std::to_string(g.rx_buffer_bytes) + " bytes)";
  info.settings = MachineSettings::FromGrblSettings(g.settings);
  info.rates_known = g.settings.count(110) && g.settings.count(120);
  info.rates_source = "$110-$112 / $120-$122";
  info.travel_known = g.settings.count(130) && g.settings.count(131) && g.settings.count(132);
  info.travel_source = "$130-$132";
  if (g.ended_feed_hold) {
    info.notes.push_back(
        "the controller stood in a feed hold: a soft reset ended it (a completed hold keeps the "
        "position; the held lines are dropped)");
  }
  return info;
}

bool GrblMachine::Reconnect(std::chrono::milliseconds timeout) {
  return client_->Reconnect(timeout);
}

MachineHandle GrblMachine::Send(std::string_view line) {
  return MachineHandle(std::make_shared<GrblSource>(client_->Send(line)));
}

MachineReply GrblMachine::Home(double /*lift_mm: $H seeks Z first*/) {
  return ToMachineReply(client_->Home());
}

MachineReply GrblMachine::Unlock() {
  return ToMachineReply(client_->Unlock());
}

std::optional<MachineStatus> GrblMachine::LatestStatus() const {
  const auto s = client_->LatestStatus();
  if (!s) return std::nullopt;
  return ToMachineStatus(*s);
}

std::optional<MachineStatus> GrblMachine::QueryStatus(std::chrono::milliseconds timeout) {
  const auto s = client_->QueryStatus(timeout);
  if (!s) return std::nullopt;
  return ToMachineStatus(*s);
}

MachineWaitResult GrblMachine::WaitIdle(std::chrono::milliseconds timeout) {
  switch (client_->WaitIdle(timeout)) {
    case GrblWaitResult::kIdle:
      return MachineWaitResult::kIdle;
    case GrblWaitResult::kTimeout:
      return MachineWaitResult::kTimeout;
    case GrblWaitResult::kAlarm:
      return MachineWaitResult::kAlarm;
    case GrblWaitResult::kDisconnected:
      return MachineWaitResult::kDisconnected;
    case GrblWaitResult::kHeld:
      return MachineWaitResult::kHeld;
  }
  return MachineWaitResult::kTimeout;
}

std::string GrblMachine::AlarmText() const {
  if (!client_->Alarmed()) return "";
  const auto code = client_->LastAlarm();
  return code ? Alarm(*code) : std::string("it restarted");
}

}  // namespace gs360
