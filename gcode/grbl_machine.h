#pragma once
// A GRBL-family controller (GRBL 1.1, grblHAL, FluidNC) as a Machine (gcode/machine.h): the
// GrblClient (gcode/grbl_client.h) with its replies and statuses in the machine's terms. The
// engine's G-code is GRBL's own and is sent as it is.

#include <memory>
#include <string>

#include "gcode/grbl_client.h"
#include "gcode/machine.h"

namespace gs360 {

class GrblMachine : public Machine {
 public:
  // Owns the client; Connect() connects it.
  explicit GrblMachine(std::unique_ptr<GrblClient> client);
  // A client on OpenTransport(uri, transport_options).
  static std::unique_ptr<GrblMachine> ForUri(const std::string& uri,
                                             const TransportOptions& transport_options,
                                             const GrblClientOptions& options);

  MachineInfo Connect() override;
  bool Reconnect(std::chrono::milliseconds timeout) override;
  bool Connected() const override { return client_->Connected(); }
  MachineHandle Send(std::string_view line) override;
  MachineReply Home(double lift_mm) override;
  bool HomesZFirst() const override { return true; }
  std::chrono::milliseconds HomingTimeout() const override {
    return client_->Options().homing_timeout;
  }
  MachineReply Unlock() override;
  bool SoftReset() override { return client_->SoftReset(); }
  std::optional<MachineStatus> LatestStatus() const override;
  std::optional<MachineStatus> QueryStatus(std::chrono::milliseconds timeout) override;
  MachineWaitResult WaitIdle(std::chrono::milliseconds timeout) override;
  bool Held() const override { return client_->Held(); }
  bool Alarmed() const override { return client_->Alarmed(); }
  bool PositionLost() const override { return client_->Alarmed(); }
  std::string AlarmText() const override;
  bool PositionTrusted() const override { return client_->PositionTrusted(); }
  void MarkPositionTrusted() override { client_->MarkPositionTrusted(); }
  std::uint64_t StrayRepliesSinceWelcome() const override {
    return client_->StrayRepliesSinceWelcome();
  }
  bool RepliesCanBeLost() const override { return true; }
  std::uint64_t UnreadableLines() const override { return client_->Stats().unknown_lines; }

  GrblClient& Client() { return *client_; }

 private:
  std::unique_ptr<GrblClient> client_;
};

// The machine's terms for a GRBL reply and status.
MachineReply ToMachineReply(const GrblReply& reply);
MachineStatus ToMachineStatus(const GrblStatusSample& sample);

}  // namespace gs360
