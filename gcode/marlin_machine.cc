#include "gcode/marlin_machine.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <stdexcept>
#include <utility>

#include <spdlog/spdlog.h>

#include "base/format.h"

namespace gs360 {
namespace {

using Clock = std::chrono::steady_clock;

bool StartsWith(std::string_view s, std::string_view p) {
  return s.substr(0, p.size()) == p;
}

// "G0 ..." / "G1 ..." / "G28": what moves the tool.
bool Moves(const std::string& command) {
  return StartsWith(command, "G0 ") || StartsWith(command, "G1 ") || StartsWith(command, "G28");
}

MachineReply Reply(MachineReplyKind kind, const std::string& line, std::uint64_t sequence,
                   std::string detail = "") {
  MachineReply r;
  r.kind = kind;
  r.line = line;
  r.sequence = sequence;
  r.detail = std::move(detail);
  r.received_at = Clock::now();
  return r;
}

// "X500.00 Y500.00 Z5.00 E25.00" -> x, y, z.
std::optional<Eigen::Vector3d> Axes(std::string_view words) {
  Eigen::Vector3d v;
  int found = 0;
  for (std::size_t i = 0; i < words.size(); ++i) {
    const int axis = words[i] == 'X' ? 0 : words[i] == 'Y' ? 1 : words[i] == 'Z' ? 2 : -1;
    if (axis < 0 || (i > 0 && words[i - 1] != ' ')) continue;
    char* end = nullptr;
    const std::string rest(words.substr(i + 1));
    v[axis] = std::strtod(rest.c_str(), &end);
    if (end != rest.c_str()) found |= 1 << axis;
  }
  if (found != 7) return std::nullopt;
  return v;
}

}  // namespace

struct MarlinMachine::Job {
  enum class Kind { kLine, kStatus, kHome, kIdle };
  Kind kind = Kind::kLine;
  std::vector<std::string> commands;
  std::string line;
  std::uint64_t sequence = 0;
  bool motion = false;
  std::chrono::milliseconds timeout{0};
  // The result.
  std::mutex mu;
  std::condition_variable cv;
  std::optional<MachineReply> reply;
  std::optional<Eigen::Vector3d> position;  // kStatus
};

class MarlinMachine::Source : public MachineHandle::Source {
 public:
  explicit Source(std::shared_ptr<Job> job) : job_(std::move(job)) {}
  bool Done() const override {
    std::lock_guard lock(job_->mu);
    return job_->reply.has_value();
  }
  MachineReply Wait(std::chrono::milliseconds timeout) const override {
    std::unique_lock lock(job_->mu);
    if (job_->cv.wait_for(lock, timeout, [&] { return job_->reply.has_value(); })) {
      return *job_->reply;
    }
    return Reply(MachineReplyKind::kTimeout, job_->line, job_->sequence,
                 "no reply within " + std::to_string(timeout.count()) + " ms");
  }

 private:
  std::shared_ptr<Job> job_;
};

void MarlinMachineOptions::Check() const {
  client.Check();
  const auto positive = [](const char* field, std::chrono::milliseconds v) {
    if (v.count() <= 0) {
      throw std::invalid_argument(std::string("MarlinMachineOptions.") + field +
                                  " must be > 0 ms, got " + std::to_string(v.count()));
    }
  };
  positive("homing_timeout", homing_timeout);
  positive("command_timeout", command_timeout);
  positive("reconnect_backoff", reconnect_backoff);
  if (!(rapid_mm_per_min >= 0.0) || !std::isfinite(rapid_mm_per_min)) {
    throw std::invalid_argument("MarlinMachineOptions.rapid_mm_per_min must be >= 0, got " +
                                FormatFixed(rapid_mm_per_min, 1));
  }
  if (!(fallback_rapid_mm_per_min > 0.0) || !std::isfinite(fallback_rapid_mm_per_min)) {
    throw std::invalid_argument("MarlinMachineOptions.fallback_rapid_mm_per_min must be > 0, got " +
                                FormatFixed(fallback_rapid_mm_per_min, 1));
  }
}

std::vector<std::string> MarlinCommandsFor(std::string_view line, double rapid_mm_per_min) {
  if (StartsWith(line, "$")) {
    throw std::invalid_argument("'" + std::string(line) +
                                "' is a GRBL system command; a Marlin printer has none");
  }
  std::vector<std::string> out;
  if (StartsWith(line, "G90 G53 ")) {
    out.push_back("G90");
    line.remove_prefix(4);
  }
  if (StartsWith(line, "G53 G0 ")) {
    out.push_back("G0 " + std::string(line.substr(7)) + " F" + FormatFixed(rapid_mm_per_min, 1));
  } else if (StartsWith(line, "G53 G1 ")) {
    out.push_back("G1 " + std::string(line.substr(7)));
  } else if (line.find("G53") != std::string_view::npos) {
    throw std::invalid_argument("'" + std::string(line) +
                                "': only G53 G0 and G53 G1 moves are known for Marlin");
  } else if (StartsWith(line, "G4 P")) {
    const double s = std::strtod(std::string(line.substr(4)).c_str(), nullptr);
    if (!(s >= 0.0) || !std::isfinite(s)) {
      throw std::invalid_argument("'" + std::string(line) + "': not a dwell in seconds");
    }
    out.push_back("M400");
    out.push_back("G4 P" + std::to_string(static_cast<long long>(std::ceil(s * 1000.0 - 1e-9))));
  } else {
    out.emplace_back(line);
  }
  return out;
}

bool ReadMarlinSettings(const std::vector<MarlinMessage>& m503, MachineSettings* settings) {
  bool rates = false, accels = false;
  for (const MarlinMessage& m : m503) {
    if (m.kind != MarlinMessageKind::kEcho) continue;
    const std::string_view t = m.text;
    if (StartsWith(t, "M203 ")) {
      if (const auto v = Axes(t.substr(5))) {
        settings->max_rate_mm_per_min = *v * 60.0;
        rates = true;
      }
    } else if (StartsWith(t, "M201 ")) {
      if (const auto v = Axes(t.substr(5))) {
        settings->acceleration_mm_per_s2 = *v;
        accels = true;
      }
    } else if (StartsWith(t, "M205 ")) {
      const std::size_t j = t.find(" J");
      if (j != std::string_view::npos) {
        settings->junction_deviation_mm =
            std::strtod(std::string(t.substr(j + 2)).c_str(), nullptr);
      }
    }
  }
  return rates && accels;
}

MarlinMachine::MarlinMachine(TransportFactory factory, const MarlinMachineOptions& options)
    : factory_(std::move(factory)), options_(options) {
  options_.Check();
}

std::unique_ptr<MarlinMachine> MarlinMachine::ForUri(const std::string& uri,
                                                     const TransportOptions& transport_options,
                                                     const MarlinMachineOptions& options) {
  transport_options.Check();
  return std::make_unique<MarlinMachine>(
      [uri, transport_options] { return OpenTransport(uri, transport_options); }, options);
}

MarlinMachine::~MarlinMachine() {
  StopWorker();
}

void MarlinMachine::StopWorker() {
  {
    std::lock_guard lock(mu_);
    stop_ = true;
    cv_.notify_all();
  }
  if (worker_.joinable()) worker_.join();
  std::lock_guard lock(mu_);
  while (!queue_.empty()) {
    const auto job = queue_.front();
    queue_.pop_front();
    Resolve(job, Reply(MachineReplyKind::kClosed, job->line, job->sequence, "the port was closed"));
  }
  client_.reset();
  connected_ = false;
}

void MarlinMachine::StartWorker() {
  std::lock_guard lock(mu_);
  stop_ = false;
  worker_ = std::thread([this] { Worker(); });
}

MachineInfo MarlinMachine::Handshake() {
  auto client = std::make_unique<MarlinClient>(factory_(), options_.client);
  try {
    info_ = client->Connect();
  } catch (const MarlinError& e) {
    if (e.kind() != MarlinError::Kind::kTimeout) throw;
    throw MarlinError(e.kind(), std::string(e.what()) +
                                    ": the printer does not answer. A halted printer (kill(): "
                                    "M112, a fault) answers nothing until it is reset: check its "
                                    "screen, reset it, then resume");
  }
  MachineInfo info;
  info.firmware = info_.firmware;
  info.description = info_.firmware.empty() ? std::string("a Marlin printer") : info_.firmware;
  if (!info_.machine_type.empty()) info.description += " (" + info_.machine_type + ")";
  info.rates_known = ReadMarlinSettings(
      client->Execute("M503", options_.client.reply_timeout).messages, &info.settings);
  info.rates_source = "M203 / M201 (M503)";
  if (info_.soft_endstops && info_.soft_min && info_.soft_max) {
    info.travel_known = true;
    info.settings.travel_min_mm = *info_.soft_min;
    info.settings.max_travel_mm = *info_.soft_max - *info_.soft_min;
    info.travel_source = "M211";
  } else {
    info.notes.push_back(
        "the printer's soft endstops are off (M211): nothing on the printer stops a move beyond "
        "its travel; [limits] in gs360d.toml is the only envelope");
  }
  rapid_mm_per_min_ = options_.rapid_mm_per_min > 0.0 ? options_.rapid_mm_per_min
                      : info.rates_known              ? info.settings.max_rate_mm_per_min.maxCoeff()
                                                      : options_.fallback_rapid_mm_per_min;
  z_rate_mm_per_min_ = info.rates_known ? info.settings.max_rate_mm_per_min.z() : 300.0;
  if (info_.rebooted_on_open) {
    info.notes.push_back(
        "the printer rebooted when the port opened (its board resets on DTR): it believes it is "
        "at 0,0,0 until homed");
  }
  std::lock_guard lock(mu_);
  client_ = std::move(client);
  connected_ = true;
  trusted_ = false;
  halted_ = false;
  unanswered_ = false;
  rebooted_ = info_.rebooted_on_open;
  alarm_text_ = rebooted_ ? "the printer rebooted when the port opened" : "";
  moved_ = false;
  return info;
}

MachineInfo MarlinMachine::Connect() {
  StopWorker();
  MachineInfo info = Handshake();
  StartWorker();
  return info;
}

bool MarlinMachine::Reconnect(std::chrono::milliseconds timeout) {
  StopWorker();
  const auto until = Clock::now() + timeout;
  while (true) {
    try {
      Handshake();
      StartWorker();
      return true;
    } catch (const std::exception& e) {
      spdlog::warn("marlin: reconnect failed: {}", e.what());
    }
    if (Clock::now() + options_.reconnect_backoff >= until) return false;
    std::this_thread::sleep_for(options_.reconnect_backoff);
  }
}

bool MarlinMachine::SoftReset() {
  return Reconnect(options_.client.boot_timeout * 3);
}

bool MarlinMachine::Connected() const {
  std::lock_guard lock(mu_);
  return connected_;
}

std::shared_ptr<MarlinMachine::Job> MarlinMachine::Enqueue(std::vector<std::string> commands,
                                                           std::string line, bool motion,
                                                           int kind) {
  auto job = std::make_shared<Job>();
  job->kind = static_cast<Job::Kind>(kind);
  job->commands = std::move(commands);
  job->line = std::move(line);
  job->motion = motion;
  job->timeout = job->kind == Job::Kind::kHome ? options_.homing_timeout : options_.command_timeout;
  std::lock_guard lock(mu_);
  job->sequence = ++next_sequence_;
  std::string refused;
  if (!connected_) refused = "not connected";
  if (halted_) refused = "the printer is halted: " + alarm_text_;
  if (unanswered_) refused = "the printer stopped answering; reconnect first";
  if (motion && !trusted_) refused = "position not trusted (home, or confirm the position)";
  if (!refused.empty()) {
    Resolve(job, Reply(MachineReplyKind::kRefused, job->line, job->sequence, refused));
    return job;
  }
  queue_.push_back(job);
  cv_.notify_all();
  return job;
}

MachineHandle MarlinMachine::Send(std::string_view line) {
  std::vector<std::string> commands = MarlinCommandsFor(line, rapid_mm_per_min_);
  const bool motion = std::any_of(commands.begin(), commands.end(), Moves);
  return MachineHandle(
      std::make_shared<Source>(Enqueue(std::move(commands), std::string(line), motion, 0)));
}

void MarlinMachine::Resolve(const std::shared_ptr<Job>& job, MachineReply reply) {
  std::lock_guard lock(job->mu);
  job->reply = std::move(reply);
  job->cv.notify_all();
}

void MarlinMachine::FailLocked(const std::shared_ptr<Job>& job, MachineReplyKind kind,
                               const std::string& why, std::optional<std::string> alarm) {
  MachineReply r = Reply(kind, job->line, job->sequence, why);
  r.alarm = alarm;
  Resolve(job, r);
  while (!queue_.empty()) {
    const auto next = queue_.front();
    queue_.pop_front();
    Resolve(next, Reply(kind == MachineReplyKind::kTimeout ? MachineReplyKind::kRefused : kind,
                        next->line, next->sequence, why));
  }
}

void MarlinMachine::Worker() {
  while (true) {
    std::shared_ptr<Job> job;
    {
      std::unique_lock lock(mu_);
      cv_.wait(lock, [&] { return stop_ || !queue_.empty(); });
      if (stop_) return;
      job = queue_.front();
      queue_.pop_front();
      if (job->motion) moved_ = true;
    }
    Run(job);
  }
}

void MarlinMachine::Run(const std::shared_ptr<Job>& job) {
  MachineReply ok = Reply(MachineReplyKind::kOk, job->line, job->sequence);
  try {
    for (const std::string& command : job->commands) {
      const MarlinReply r = client_->Execute(command, job->timeout);
      for (const MarlinMessage& m : r.messages) {
        std::lock_guard lock(mu_);
        if (m.kind == MarlinMessageKind::kUnknown) ++unreadable_;
        if (m.kind == MarlinMessageKind::kPosition && m.position) {
          job->position = m.position;
          MachineStatus s;
          s.machine_position = m.position;
          s.received_at = Clock::now();
          latest_ = s;
        }
        if (m.kind == MarlinMessageKind::kError && ok.error.empty()) ok.error = m.text;
      }
    }
    ok.received_at = Clock::now();
    std::lock_guard lock(mu_);
    if (job->kind == Job::Kind::kIdle || job->line.rfind("G4", 0) == 0) moved_ = false;
    if (job->kind == Job::Kind::kHome) {
      trusted_ = true;
      rebooted_ = false;
      alarm_text_.clear();
      moved_ = false;
    }
    if (latest_) {
      latest_->state = moved_ ? MachineState::kRun : MachineState::kIdle;
      latest_->state_text = moved_ ? "Run" : "Idle";
    }
    if (!ok.error.empty()) ok.kind = MachineReplyKind::kError;
    Resolve(job, ok);
  } catch (const MarlinError& e) {
    std::lock_guard lock(mu_);
    trusted_ = false;
    switch (e.kind()) {
      case MarlinError::Kind::kHalted:
        halted_ = true;
        alarm_text_ = std::string("the printer halted: ") + e.what();
        FailLocked(job, MachineReplyKind::kReset, e.what(), alarm_text_);
        break;
      case MarlinError::Kind::kRebooted:
        rebooted_ = true;
        alarm_text_ = "the printer rebooted: it believes it is at 0,0,0 wherever the tool is";
        FailLocked(job, MachineReplyKind::kReset, e.what(), std::nullopt);
        break;
      case MarlinError::Kind::kTimeout:
      case MarlinError::Kind::kProtocol:
        unanswered_ = true;
        FailLocked(job, MachineReplyKind::kTimeout, e.what(), std::nullopt);
        break;
    }
  } catch (const std::exception& e) {  // TransportError: the port vanished
    std::lock_guard lock(mu_);
    connected_ = false;
    trusted_ = false;
    FailLocked(job, MachineReplyKind::kDisconnected, e.what(), std::nullopt);
  }
}

MachineReply MarlinMachine::Home(double lift_mm) {
  std::vector<std::string> commands;
  if (lift_mm > 0.0) {
    commands = {"G91", "G0 Z" + FormatFixed(lift_mm, 3) + " F" + FormatFixed(z_rate_mm_per_min_, 1),
                "G90"};
  }
  commands.push_back("G28");
  const auto job = Enqueue(commands, "G28", false, static_cast<int>(Job::Kind::kHome));
  return Source(job).Wait(options_.homing_timeout + options_.client.reply_timeout);
}

MachineReply MarlinMachine::Unlock() {
  std::lock_guard lock(mu_);
  if (halted_) {
    return Reply(MachineReplyKind::kRefused, "", 0,
                 "the printer is halted: reset it (its reset button or power), then resume");
  }
  rebooted_ = false;
  alarm_text_.clear();
  return Reply(MachineReplyKind::kOk, "", 0);
}

std::optional<MachineStatus> MarlinMachine::LatestStatus() const {
  std::lock_guard lock(mu_);
  return latest_;
}

std::optional<MachineStatus> MarlinMachine::QueryStatus(std::chrono::milliseconds timeout) {
  const auto job = Enqueue({"M114 R"}, "M114 R", false, static_cast<int>(Job::Kind::kStatus));
  const MachineReply r = Source(job).Wait(timeout);
  if (!r.Ok()) return std::nullopt;
  std::lock_guard lock(mu_);  // job->position is written under it, before the job resolves
  // This query's own answer: an earlier report must not stand in for a position it lacked.
  if (!job->position || !latest_) return std::nullopt;
  MachineStatus s = *latest_;
  s.machine_position = job->position;
  return s;
}

MachineWaitResult MarlinMachine::WaitIdle(std::chrono::milliseconds timeout) {
  const auto job = Enqueue({"M400"}, "M400", false, static_cast<int>(Job::Kind::kIdle));
  const MachineReply r = Source(job).Wait(timeout);
  if (r.Ok()) return MachineWaitResult::kIdle;
  if (Alarmed()) return MachineWaitResult::kAlarm;
  if (!Connected()) return MachineWaitResult::kDisconnected;
  return MachineWaitResult::kTimeout;
}

bool MarlinMachine::Alarmed() const {
  std::lock_guard lock(mu_);
  return halted_;
}

bool MarlinMachine::PositionLost() const {
  std::lock_guard lock(mu_);
  return halted_ || rebooted_;
}

std::string MarlinMachine::AlarmText() const {
  std::lock_guard lock(mu_);
  return halted_ || rebooted_ ? alarm_text_ : std::string();
}

bool MarlinMachine::PositionTrusted() const {
  std::lock_guard lock(mu_);
  return trusted_;
}

void MarlinMachine::MarkPositionTrusted() {
  std::lock_guard lock(mu_);
  trusted_ = true;
  if (!halted_) {
    rebooted_ = false;  // established: the reboot is behind it
    alarm_text_.clear();
  }
}

std::uint64_t MarlinMachine::UnreadableLines() const {
  std::lock_guard lock(mu_);
  return unreadable_;
}

}  // namespace gs360
