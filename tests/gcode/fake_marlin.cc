#include "fake_marlin.h"

#include <poll.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <utility>

#include "gcode/marlin_messages.h"

namespace gs360::test {

FakeMarlin::FakeMarlin(const FakeMarlinOptions& options)
    : options_(options), pty_(Pty::Open()), thread_([this] { Serve(); }) {}

FakeMarlin::~FakeMarlin() {
  stop_ = true;
  thread_.join();
}

std::vector<std::string> FakeMarlin::Ran() const {
  std::lock_guard<std::mutex> lock(mu_);
  return ran_;
}

Eigen::Vector3d FakeMarlin::Position() const {
  std::lock_guard<std::mutex> lock(mu_);
  return position_;
}

void FakeMarlin::Reply(const std::string& text) {
  const std::string bytes = text + "\n";
  std::size_t done = 0;
  while (done < bytes.size() && !stop_) {
    const ssize_t n = ::write(pty_.master_fd(), bytes.data() + done, bytes.size() - done);
    if (n > 0) done += static_cast<std::size_t>(n);
    if (n < 0) std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
}

void FakeMarlin::Serve() {
  if (options_.reboot_on_open) {
    std::this_thread::sleep_for(std::chrono::milliseconds(200));  // the bootloader
    Reply("start");
    Reply("echo:Marlin 2.1.2.1");
    Reply("echo: Last Updated: 2023-07-16 | Author: (none, default config)");
  }
  std::string partial;
  bool asked = false;
  while (!stop_) {
    if (options_.busy_forever && asked) Reply("echo:busy: processing");  // every 20 ms
    pollfd p{pty_.master_fd(), POLLIN, 0};
    if (::poll(&p, 1, 20) <= 0 || !(p.revents & POLLIN)) continue;
    asked = true;
    char buf[256];
    const ssize_t n = ::read(pty_.master_fd(), buf, sizeof buf);
    for (ssize_t i = 0; i < n; ++i) {
      if (buf[i] != '\n') {
        partial.push_back(buf[i]);
        continue;
      }
      Line(std::exchange(partial, {}));
    }
  }
}

void FakeMarlin::Line(std::string line) {
  if (line == "M112") {  // the emergency parser: unnumbered, at once
    halted_ = true;
    Reply("Error:Printer halted. kill() called!");
    return;
  }
  if (halted_ || options_.busy_forever) return;  // a halted Marlin answers nothing
  const auto refuse = [&](const std::string& why) {
    Reply("Error:" + why + ", Last Line: " + std::to_string(last_));
    Reply("Resend: " + std::to_string(last_ + 1));
    Reply("ok");
  };
  const auto space = line.find(' ');
  const long number = line[0] == 'N' ? std::stol(line.substr(1, space - 1)) : -1;
  if (number == options_.garble_line) {
    options_.garble_line = -1;
    line[line.size() / 2] ^= 0x04;
  }
  const auto star = line.rfind('*');
  if (number < 0 || star == std::string::npos) return refuse("No Checksum with line number");
  if (std::to_string(MarlinChecksum(line.substr(0, star))) != line.substr(star + 1)) {
    return refuse("checksum mismatch");
  }
  const std::string command = line.substr(space + 1, star - space - 1);
  const bool m110 = command.rfind("M110", 0) == 0;
  if (!m110 && number != last_ + 1) return refuse("Line Number is not Last Line Number+1");
  if (number == options_.reboot_at_line) {
    options_.reboot_at_line = -1;
    last_ = -1;
    {
      std::lock_guard<std::mutex> lock(mu_);
      position_ = Eigen::Vector3d::Zero();  // a rebooted Marlin believes 0,0,0
    }
    Reply("start");
    return;
  }
  last_ = number;
  Run(command);
  if (number == options_.drop_ok_line) {
    options_.drop_ok_line = -1;
    return;
  }
  Reply("ok");
}

void FakeMarlin::Run(const std::string& command) {
  std::lock_guard<std::mutex> lock(mu_);
  if (command.rfind("M110", 0) != 0) ran_.push_back(command);
  if (command == "M115") {
    Reply(
        "FIRMWARE_NAME:Marlin 2.1.2.1 (Jul 16 2023) SOURCE_CODE_URL:github.com/MarlinFirmware/"
        "Marlin PROTOCOL_VERSION:1.0 MACHINE_TYPE:Ender-3 EXTRUDER_COUNT:1");
    Reply("Cap:AUTOREPORT_POS:1");
    Reply("Cap:EMERGENCY_PARSER:1");
  } else if (command == "M211") {
    Reply("echo:Soft endstops: On  Min:  X0.00 Y0.00 Z0.00   Max:  X235.00 Y235.00 Z250.00");
  } else if (command == "G28") {
    Reply("echo:busy: processing");
    position_ = Eigen::Vector3d::Zero();
  } else if (command.rfind("M114", 0) == 0) {
    char text[160];
    std::snprintf(text, sizeof text, "X:%.2f Y:%.2f Z:%.2f E:0.00 Count X:%d Y:%d Z:%d",
                  position_.x(), position_.y(), position_.z(), static_cast<int>(80 * position_.x()),
                  static_cast<int>(80 * position_.y()), static_cast<int>(400 * position_.z()));
    Reply(text);
  } else if (command.rfind("G0", 0) == 0 || command.rfind("G1", 0) == 0) {
    for (std::size_t i = 0; i < command.size(); ++i) {
      const int axis = command[i] == 'X' ? 0 : command[i] == 'Y' ? 1 : command[i] == 'Z' ? 2 : -1;
      if (axis >= 0) position_[axis] = std::stod(command.substr(i + 1));
    }
  }
}

}  // namespace gs360::test
