// The virtual controller's serial side (GRBL's serial.c): bytes from the host as the receive
// interrupt sees them (real-time characters picked out, the 128-byte buffer), the I/O thread
// that moves bytes between the pty and the firmware at the port's baud rate, and replies.

#include <poll.h>
#include <unistd.h>

#include <algorithm>
#include <iostream>
#include <random>

#include "sim/virtual_cnc_impl.h"

namespace gs360 {
namespace {

// How often a hung-up pty (no host attached) is polled again.
constexpr auto kHupPollInterval = std::chrono::milliseconds(20);

}  // namespace

void VirtualCnc::Impl::OnHostByte(unsigned char c) {
  if (to_cnc_.drop_next > 0) {
    --to_cnc_.drop_next;
    ++stats_.injected_drops;
    return;
  }
  if (to_cnc_.drop_probability > 0.0 &&
      std::uniform_real_distribution<double>(0.0, 1.0)(rng_) < to_cnc_.drop_probability) {
    ++stats_.injected_drops;
    return;
  }
  if (to_cnc_.garble_next > 0) {
    --to_cnc_.garble_next;
    ++stats_.injected_garbles;
    c = static_cast<unsigned char>(c ^ (1u << (rng_() % 7)));
  }
  if (!powered_) return;
  if (Marlin()) {  // no real-time bytes: the emergency parser watches the line go by
    MarlinEmergencyByte(static_cast<char>(c));
    if (rx_.size() < static_cast<std::size_t>(options_.rx_buffer_bytes)) {
      rx_.push_back(static_cast<char>(c));
    } else {
      ++stats_.rx_overflow_dropped;
    }
    cv_.notify_all();
    return;
  }
  switch (c) {
    case 0x18:
      McReset();
      break;
    case '?':
      rt_status_ = true;
      break;
    case '~':
      rt_cycle_start_ = true;
      break;
    case '!':
      rt_feed_hold_ = true;
      break;
    default:
      if (c > 0x7F) {
        if (c == 0x85 && state_ == GrblState::kJog) rt_motion_cancel_ = true;  // jog cancel
        // Other extended real-time bytes (overrides, safety door) are not modelled: discarded.
      } else if (rx_.size() < static_cast<std::size_t>(options_.rx_buffer_bytes)) {
        rx_.push_back(static_cast<char>(c));
      } else {
        ++stats_.rx_overflow_dropped;
      }
  }
  cv_.notify_all();
}

void VirtualCnc::Impl::Emit(const std::string& s) {
  // The firmware thread may still be unwinding the run of a previous power-up (e.g. a dwell
  // cut short by PowerCycle()): that code no longer exists on the board, its output is not sent.
  if (boot_id_ != running_boot_) return;
  if (!lose_replies_.empty() &&
      (s.rfind("ok\r\n", 0) == 0 || s.rfind("ok\n", 0) == 0 || s.rfind("error:", 0) == 0)) {
    const std::string instead = std::move(lose_replies_.front());  // LoseNextReply()
    lose_replies_.pop_front();
    if (!instead.empty()) Transmit(instead);
    return;
  }
  Transmit(s);
}

void VirtualCnc::Impl::Transmit(const std::string& s) {
  if (!plugged_ || !powered_) return;
  // Nobody listening: lost (a printer's USB-serial bridge drops what arrives with the port
  // closed; GRBL's output waits in the pty unless the board resets on open).
  if ((options_.reset_on_open || Marlin()) && !host_open_) {
    ++stats_.unheard;
    return;
  }
  if (tx_.empty()) tx_clock_ = std::max(tx_clock_, Clock::now());
  tx_ += s;
  WakeIo();
}

void VirtualCnc::Impl::IoMain() {
  bool hup = true;  // no host has the slave open yet
  int last_fd = -1;
  while (true) {
    int fd = -1;
    int watch = -1;
    bool want_write = false;
    int timeout_ms = -1;
    {
      Lock lk(mu_);
      if (stop_) return;
      if (close_request_) {
        pty_.Close();
        plugged_ = false;
        host_open_ = false;
        close_request_ = false;
        rx_line_.clear();
        io_cv_.notify_all();
      }
      const Clock::time_point now = Clock::now();
      if (replug_at_ && now >= *replug_at_) {
        try {
          ReplugLocked();
        } catch (const std::exception& e) {
          std::cerr << "virtual CNC: replug failed: " << e.what() << "\n";
          replug_at_ = now + std::chrono::milliseconds(100);
        }
      }
      if (plugged_) {
        fd = pty_.master_fd();
        watch = pty_.open_watch_fd();
      }
      if (fd != last_fd) {
        hup = true;
        last_fd = fd;
      }
      PaceRx(now);
      PaceTx(now);
      want_write = fd >= 0 && !wire_.empty();
      auto limit = [&](Clock::time_point when) {
        const auto us = std::chrono::duration_cast<std::chrono::microseconds>(when - now).count();
        const int v = static_cast<int>(std::clamp<long long>((us + 999) / 1000, 0, 1000000));
        timeout_ms = timeout_ms < 0 ? v : std::min(timeout_ms, v);
      };
      if (!rx_line_.empty()) limit(rx_clock_ + byte_time_);
      if (!tx_.empty()) limit(std::max(tx_clock_ + byte_time_, stall_until_));
      if (replug_at_) limit(*replug_at_);
      if (fd >= 0 && hup) limit(now + kHupPollInterval);
    }
    pollfd fds[3];
    fds[0] = {wake_[0], POLLIN, 0};
    int nfds = 1;
    if (watch >= 0) fds[nfds++] = {watch, POLLIN, 0};
    if (fd >= 0 && !hup) {
      fds[nfds++] = {fd, static_cast<short>(POLLIN | (want_write ? POLLOUT : 0)), 0};
    }
    ::poll(fds, static_cast<nfds_t>(nfds), timeout_ms);
    if (fds[0].revents & POLLIN) {
      char buf[64];
      while (::read(wake_[0], buf, sizeof(buf)) > 0) {
      }
    }
    if (fd < 0) continue;
    pollfd probe = {fd, static_cast<short>(POLLIN | (want_write ? POLLOUT : 0)), 0};
    ::poll(&probe, 1, 0);
    Lock lk(mu_);
    if (stop_ || close_request_ || !plugged_ || pty_.master_fd() != fd) continue;
    const bool now_hup = (probe.revents & POLLHUP) != 0;
    // The DTR pulse of each open resets the board. Counted by the watch where there is one: a
    // host that closes and reopens the port between two of these looks leaves no POLLHUP.
    const int opens = pty_.TakeOpens();
    const bool opened = watch >= 0 ? opens > 0 : !now_hup && !host_open_;
    host_open_ = !now_hup;
    if (opened && options_.reset_on_open) Reboot();
    hup = now_hup;
    if (probe.revents & POLLIN) ReadFromHost(fd);
    if (!wire_.empty() && (probe.revents & POLLOUT)) {
      const ssize_t n = ::write(fd, wire_.data(), wire_.size());
      if (n > 0) wire_.erase(0, static_cast<std::size_t>(n));
    }
  }
}

void VirtualCnc::Impl::ReadFromHost(int fd) {
  char buf[256];
  const ssize_t n = ::read(fd, buf, sizeof(buf));
  if (n <= 0) return;
  stats_.bytes_from_host += static_cast<std::uint64_t>(n);
  if (rx_line_.empty()) rx_clock_ = std::max(rx_clock_, Clock::now());
  rx_line_.append(buf, static_cast<std::size_t>(n));
  PaceRx(Clock::now());
}

void VirtualCnc::Impl::PaceRx(Clock::time_point now) {
  std::size_t n = 0;
  while (n < rx_line_.size() && (byte_time_.count() == 0 || rx_clock_ + byte_time_ <= now)) {
    rx_clock_ += byte_time_;
    OnHostByte(static_cast<unsigned char>(rx_line_[n]));
    ++n;
  }
  rx_line_.erase(0, n);
}

void VirtualCnc::Impl::PaceTx(Clock::time_point now) {
  if (now < stall_until_) return;
  if (tx_clock_ < stall_until_) tx_clock_ = stall_until_;
  std::size_t n = 0;
  while (n < tx_.size() && (byte_time_.count() == 0 || tx_clock_ + byte_time_ <= now)) {
    tx_clock_ += byte_time_;
    unsigned char c = static_cast<unsigned char>(tx_[n++]);
    if (to_host_.drop_next > 0) {
      --to_host_.drop_next;
      ++stats_.injected_drops;
      continue;
    }
    if (to_host_.drop_probability > 0.0 &&
        std::uniform_real_distribution<double>(0.0, 1.0)(rng_) < to_host_.drop_probability) {
      ++stats_.injected_drops;
      continue;
    }
    if (to_host_.garble_next > 0) {
      --to_host_.garble_next;
      ++stats_.injected_garbles;
      c = static_cast<unsigned char>(c ^ (1u << (rng_() % 7)));
    }
    wire_.push_back(static_cast<char>(c));
  }
  tx_.erase(0, n);
}

}  // namespace gs360
