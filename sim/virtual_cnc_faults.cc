// Board-side faults of the virtual CNC: a restart with the USB link up, GRBL's reset input, and
// raw bytes on the line. They reuse the power-up (PowerOff/PowerOn, as Unplug(power_loss) and
// reset_on_open do) and the 0x18 path (McReset) of virtual_cnc.cc.

#include <unistd.h>

#include <mutex>
#include <string>

#include "sim/virtual_cnc_impl.h"

namespace gs360 {

// Brown-out, watchdog or reset button: the MCU's RAM is lost, including the UART's transmit
// ring (tx_, not yet on the wire). Bytes already past the UART (wire_, in the USB bridge or the
// pty) still reach the host. The firmware thread notices the new power-up (Rebooted()) and
// restarts from main(); anything the old run would still have printed is dropped by Emit().
void VirtualCnc::Impl::Reboot() {
  PowerOff();
  tx_.clear();
  // Bytes the host wrote that the UART had not taken yet (in the USB bridge; here the pty) reach
  // the restarting MCU's bootloader, which eats them: a real board never executes them.
  if (plugged_ && pty_.master_fd() >= 0) {
    char buf[256];
    while (::read(pty_.master_fd(), buf, sizeof(buf)) > 0) {
    }
  }
  PowerOn();
}

void VirtualCnc::Impl::PowerCycle() {
  std::lock_guard<std::mutex> lk(mu_);
  if (stop_ || !powered_) return;
  Reboot();
}

// GRBL 1.1h: the reset pin's ISR (system.c, CONTROL_PIN_INDEX_RESET) calls mc_reset(), as the
// serial ISR does for 0x18 (serial.c CMD_RESET).
void VirtualCnc::Impl::ResetNow() {
  std::lock_guard<std::mutex> lk(mu_);
  if (stop_ || !powered_) return;
  if (Marlin()) return Reboot();  // a printer's reset pin restarts its MCU
  McReset();
}

// GRBL 1.1h: the feed-hold pin's ISR (CONTROL_PIN_INDEX_FEED_HOLD) sets EXEC_FEED_HOLD, as '!'.
void VirtualCnc::Impl::FeedHoldPin() {
  std::lock_guard<std::mutex> lk(mu_);
  if (stop_ || !powered_) return;
  if (Marlin()) return;  // a printer has no hold input
  rt_feed_hold_ = true;
  cv_.notify_all();
}

void VirtualCnc::Impl::LoseNextReply(const std::string& instead) {
  std::lock_guard<std::mutex> lk(mu_);
  lose_replies_.push_back(instead);
}

void VirtualCnc::Impl::SendRaw(const std::string& bytes) {
  std::lock_guard<std::mutex> lk(mu_);
  Transmit(bytes);
}

std::size_t VirtualCnc::Impl::PendingOutputBytes() const {
  std::lock_guard<std::mutex> lk(mu_);
  return tx_.size() + wire_.size();
}

void VirtualCnc::PowerCycle() {
  impl_->PowerCycle();
}
void VirtualCnc::ResetNow() {
  impl_->ResetNow();
}
void VirtualCnc::ResetDuringNextDwell() {
  impl_->ResetDuringNextDwell();
}
void VirtualCnc::FeedHoldPin() {
  impl_->FeedHoldPin();
}
void VirtualCnc::LoseNextReply(const std::string& instead) {
  impl_->LoseNextReply(instead);
}
void VirtualCnc::SendRaw(const std::string& bytes) {
  impl_->SendRaw(bytes);
}
std::size_t VirtualCnc::PendingOutputBytes() const {
  return impl_->PendingOutputBytes();
}

}  // namespace gs360
