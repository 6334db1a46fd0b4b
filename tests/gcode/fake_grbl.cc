#include "tests/gcode/fake_grbl.h"

#include <fcntl.h>
#include <poll.h>
#include <pty.h>
#include <sys/socket.h>
#include <termios.h>
#include <unistd.h>
#include <cctype>
#include <cerrno>
#include <charconv>
#include <cstdlib>
#include <stdexcept>

#include "tests/wait.h"

namespace gs360 {

namespace {

using Clock = std::chrono::steady_clock;

bool IsSettingsWrite(const std::string& line) {
  return !line.empty() && line[0] == '$' && line.find('=') != std::string::npos &&
         line.rfind("$J=", 0) != 0;
}

std::string Upper(const std::string& s) {
  std::string out;
  for (char c : s) {
    if (c != ' ') out.push_back(static_cast<char>(std::toupper(static_cast<unsigned char>(c))));
  }
  return out;
}

std::string Fixed3(double v) {
  char buf[32];
  const auto [ptr, ec] = std::to_chars(buf, buf + sizeof(buf), v, std::chars_format::fixed, 3);
  return std::string(buf, ptr);
}

}  // namespace

std::unique_ptr<FakeGrbl> FakeGrbl::CreatePty(FakeGrblOptions options) {
  int master = -1;
  int slave = -1;
  char name[256] = {};
  termios raw{};
  ::cfmakeraw(&raw);
  if (::openpty(&master, &slave, name, &raw, nullptr) != 0) {
    throw std::runtime_error("openpty failed");
  }
  ::fcntl(master, F_SETFD, FD_CLOEXEC);
  ::fcntl(slave, F_SETFD, FD_CLOEXEC);
  return std::make_unique<FakeGrbl>(master, slave, name, options);
}

FakeGrbl::FakeGrbl(int fd, int slave_fd, std::string path, FakeGrblOptions options)
    : fd_(fd),
      slave_fd_(slave_fd),
      path_(std::move(path)),
      options_(options),
      alarm_(options.alarm_at_start) {
  if (options_.welcome_on_start) {
    std::string hello = std::string("\r\n") + kFakeWelcome + "\r\n";
    if (options_.alarm_at_start) hello += "[MSG:'$H'|'$X' to unlock]\r\n";
    WriteRaw(hello);
  }
  reader_ = std::thread([this] { ReaderLoop(); });
  processor_ = std::thread([this] { ProcessorLoop(); });
}

FakeGrbl::~FakeGrbl() {
  Close();
}

void FakeGrbl::Close() {
  {
    std::lock_guard lock(mu_);
    if (closed_) return;
    closed_ = true;
    stop_ = true;
  }
  cv_.notify_all();
  if (reader_.joinable()) reader_.join();
  if (processor_.joinable()) processor_.join();
  std::lock_guard wlock(write_mu_);
  if (slave_fd_ < 0) ::shutdown(fd_, SHUT_RDWR);  // a socket: make the host see EOF now
  ::close(fd_);
  if (slave_fd_ >= 0) ::close(slave_fd_);
  fd_ = -1;
  slave_fd_ = -1;
}

void FakeGrbl::WriteRaw(const std::string& bytes) {
  std::lock_guard wlock(write_mu_);
  if (fd_ < 0) return;
  std::size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t n = ::write(fd_, bytes.data() + done, bytes.size() - done);
    if (n > 0) {
      done += static_cast<std::size_t>(n);
    } else if (n < 0 && (errno == EINTR || errno == EAGAIN)) {
      ::usleep(200);
    } else {
      return;  // host gone
    }
  }
}

void FakeGrbl::SetResponder(Responder responder) {
  std::lock_guard lock(mu_);
  responder_ = std::move(responder);
}

void FakeGrbl::SetProcessing(bool on) {
  {
    std::lock_guard lock(mu_);
    processing_ = on;
  }
  cv_.notify_all();
}

void FakeGrbl::Emit(const std::string& bytes) {
  WriteRaw(bytes);
}

void FakeGrbl::ResetLocked() {
  partial_.clear();
  pending_.clear();
  outstanding_ = 0;
  hold_ = false;
}

void FakeGrbl::ResetAndWelcome() {
  {
    std::lock_guard lock(mu_);
    ResetLocked();
  }
  WriteRaw(std::string("\r\n") + kFakeWelcome + "\r\n");
}

std::string FakeGrbl::StatusReportLocked() const {
  std::string state = alarm_                         ? "Alarm"
                      : hold_                        ? "Hold:0"
                      : (busy_ || !pending_.empty()) ? "Run"
                                                     : "Idle";
  return "<" + state + "|MPos:" + Fixed3(position_.x()) + "," + Fixed3(position_.y()) + "," +
         Fixed3(position_.z()) + "|Bf:" + std::to_string(options_.planner_blocks) + "," +
         std::to_string(options_.rx_size - static_cast<int>(outstanding_)) + "|FS:0,0>\r\n";
}

void FakeGrbl::ReaderLoop() {
  char buf[512];
  while (true) {
    {
      std::lock_guard lock(mu_);
      if (stop_) return;
    }
    pollfd p{};
    p.fd = fd_;
    p.events = POLLIN;
    const int r = ::poll(&p, 1, 20);
    if (r <= 0) continue;
    const ssize_t n = ::read(fd_, buf, sizeof(buf));
    if (n <= 0) {
      // EIO on a pty master while no slave is open; EOF on a socket: the host went away.
      ::usleep(2000);
      continue;
    }
    const auto now = Clock::now();
    std::string to_write;
    {
      std::lock_guard lock(mu_);
      for (ssize_t i = 0; i < n; ++i) {
        const char c = buf[i];
        if (c == '?' || c == '!' || c == '~' || c == '\x18') {
          realtime_.push_back({c, pending_.size() + (busy_ ? 1 : 0), now});
          if (c == '?') to_write += StatusReportLocked();
          if (c == '!') hold_ = true;
          if (c == '~') hold_ = false;
          if (c == '\x18') {
            ResetLocked();
            ++resets_;
            // A processor in a critical-alarm wait writes its own ok + welcome.
            if (!waiting_reset_) to_write += std::string("\r\n") + kFakeWelcome + "\r\n";
          }
          continue;
        }
        if (outstanding_ + 1 > static_cast<std::size_t>(options_.rx_size)) {
          overflowed_ = true;  // GRBL drops the byte
          continue;
        }
        ++outstanding_;
        max_outstanding_ = std::max(max_outstanding_, outstanding_);
        if (c == '\n') {
          FakeLine line;
          line.line = partial_;
          line.unanswered_at_arrival = pending_.size() + (busy_ ? 1 : 0);
          line.outstanding_bytes = outstanding_;
          line.at = now;
          lines_.push_back(line);
          pending_.push_back(partial_);
          partial_.clear();
        } else if (c != '\r') {
          partial_.push_back(c);
        }
      }
    }
    cv_.notify_all();
    if (!to_write.empty()) WriteRaw(to_write);
  }
}

std::vector<std::string> FakeGrbl::DefaultReply(const std::string& raw) {
  const std::string line = Upper(raw);
  if (line == "$I") {
    std::vector<std::string> r = {"[VER:1.1h.20190830:]"};
    if (options_.report_opt) {
      r.push_back("[OPT:V," + std::to_string(options_.planner_blocks) + "," +
                  std::to_string(options_.rx_size) + "]");
    }
    r.push_back("ok");
    return r;
  }
  if (line == "$$") {
    return {"$0=10",         "$11=0.010",
            "$20=1",         "$22=1",
            "$110=3000.000", "$111=3000.000",
            "$112=1200.000", "$120=200.000",
            "$121=200.000",  "$122=100.000",
            "$130=300.000",  "$131=300.000",
            "$132=100.000",  "ok"};
  }
  if (line == "$H") {
    std::lock_guard lock(mu_);
    alarm_ = false;
    position_.setZero();
    return {"ok"};
  }
  if (line == "$X") {
    std::lock_guard lock(mu_);
    alarm_ = false;
    return {"[MSG:Caution: Unlocked]", "ok"};
  }
  if (IsSettingsWrite(line) || (!line.empty() && line[0] == '$')) return {"ok"};
  {
    std::lock_guard lock(mu_);
    if (alarm_) return {"error:9"};
    // Absolute axis words move at once.
    for (std::size_t i = 0; i < line.size(); ++i) {
      const char c = line[i];
      if (c != 'X' && c != 'Y' && c != 'Z') continue;
      double v = 0;
      const char* begin = line.data() + i + 1;
      const auto [ptr, ec] = std::from_chars(begin, line.data() + line.size(), v);
      if (ec != std::errc()) continue;
      position_[c - 'X'] = v;
      i = static_cast<std::size_t>(ptr - line.data()) - 1;
    }
  }
  return {"ok"};
}

void FakeGrbl::WriteReplies(const std::vector<std::string>& lines) {
  std::string bytes;
  for (const std::string& l : lines) {
    if (l == kFakeWaitReset) {
      WriteRaw(bytes);
      bytes.clear();
      std::unique_lock lock(mu_);
      waiting_reset_ = true;
      const std::size_t before = resets_;
      cv_.wait(lock, [&] { return stop_ || resets_ > before; });
      waiting_reset_ = false;
      continue;
    }
    if (l.rfind("ALARM:", 0) == 0) {
      std::lock_guard lock(mu_);
      alarm_ = true;
    }
    if (l.find("Grbl ") != std::string::npos && l.find("for help]") != std::string::npos) {
      std::lock_guard lock(mu_);
      ResetLocked();
    }
    // Garbage lines (e.g. "\xff") are written as they are; real lines get "\r\n".
    bytes += l;
    if (l.empty() || l.back() != '\n') bytes += "\r\n";
  }
  WriteRaw(bytes);
}

void FakeGrbl::ProcessorLoop() {
  while (true) {
    std::string line;
    Responder responder;
    {
      std::unique_lock lock(mu_);
      cv_.wait(lock, [&] { return stop_ || (processing_ && !pending_.empty()); });
      if (stop_) return;
      line = pending_.front();
      pending_.erase(pending_.begin());
      outstanding_ -= line.size() + 1;  // GRBL frees the bytes as it reads the line
      busy_ = true;
      responder = responder_;
    }
    if (options_.line_delay.count() > 0) std::this_thread::sleep_for(options_.line_delay);
    std::optional<std::vector<std::string>> reply;
    if (responder) reply = responder(line);
    if (!reply) reply = DefaultReply(line);
    {
      // Answered before the bytes leave, so a host reacting to this reply never sees it pending.
      std::lock_guard lock(mu_);
      busy_ = false;
    }
    WriteReplies(*reply);
  }
}

std::vector<FakeLine> FakeGrbl::Lines() const {
  std::lock_guard lock(mu_);
  return lines_;
}

std::vector<FakeRealtime> FakeGrbl::Realtime() const {
  std::lock_guard lock(mu_);
  return realtime_;
}

std::size_t FakeGrbl::CountRealtime(char c) const {
  std::lock_guard lock(mu_);
  std::size_t n = 0;
  for (const auto& r : realtime_) n += r.byte == c ? 1 : 0;
  return n;
}

std::size_t FakeGrbl::MaxOutstandingBytes() const {
  std::lock_guard lock(mu_);
  return max_outstanding_;
}

bool FakeGrbl::Overflowed() const {
  std::lock_guard lock(mu_);
  return overflowed_;
}

std::size_t FakeGrbl::Pending() const {
  std::lock_guard lock(mu_);
  return pending_.size();
}

Eigen::Vector3d FakeGrbl::Position() const {
  std::lock_guard lock(mu_);
  return position_;
}

bool FakeGrbl::InAlarm() const {
  std::lock_guard lock(mu_);
  return alarm_;
}

bool FakeGrbl::WaitUntil(const std::function<bool()>& pred, std::chrono::milliseconds timeout) {
  return test::WaitUntil(pred, timeout);
}

}  // namespace gs360
