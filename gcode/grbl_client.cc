#include "gcode/grbl_client.h"

#include <algorithm>
#include <cctype>
#include <charconv>
#include <cmath>

#include <spdlog/spdlog.h>

#include "base/format.h"

namespace gs360 {

namespace {

using Clock = std::chrono::steady_clock;
using std::chrono::milliseconds;

constexpr milliseconds kReadSlice{50};  // reader wake-up period (for stop requests)

struct LineTraits {
  bool exclusive = false;  // settings write or '$' system command: sent alone
  bool system = false;     // '$' command (allowed in alarm)
  bool motion = false;     // moves the machine
  bool home = false;       // $H
  bool unlock = false;     // $X
};

// Uppercase, without spaces and comments ("(...)" and ";..."), as GRBL's parser sees the line.
std::string Normalise(std::string_view line) {
  std::string out;
  bool paren = false;
  for (char c : line) {
    if (paren) {
      if (c == ')') paren = false;
      continue;
    }
    if (c == '(') {
      paren = true;
      continue;
    }
    if (c == ';') break;
    if (c == ' ' || c == '\t') continue;
    out.push_back(static_cast<char>(std::toupper(static_cast<unsigned char>(c))));
  }
  return out;
}

LineTraits ClassifyLine(std::string_view line) {
  LineTraits t;
  const std::string n = Normalise(line);
  if (!n.empty() && n[0] == '$') {
    if (n.rfind("$J=", 0) == 0) {
      t.motion = true;  // jogging is streamed like G-code
      return t;
    }
    t.system = true;
    t.exclusive = true;
    t.home = (n == "$H");  // single-axis $HX.. does not establish the whole position
    t.unlock = (n == "$X");
    return t;
  }
  // G-code words: letter + number.
  bool has_axis = false;
  bool g10 = false;
  bool l2_or_l20 = false;
  bool non_motion_axis_user = false;  // G10, G92, G43.1 consume axis words without moving
  bool goes_home = false;             // G28 / G30 move to stored positions
  bool writes_eeprom = false;         // G28.1 / G30.1 store positions
  for (std::size_t i = 0; i < n.size();) {
    const char letter = n[i++];
    const std::size_t start = i;
    while (i < n.size() && (std::isdigit(static_cast<unsigned char>(n[i])) || n[i] == '.' ||
                            n[i] == '-' || n[i] == '+')) {
      ++i;
    }
    double value = 0.0;
    const std::string_view num(n.data() + start, i - start);
    std::string_view parse = num;
    if (!parse.empty() && parse.front() == '+') parse.remove_prefix(1);
    const auto [ptr, ec] = std::from_chars(parse.data(), parse.data() + parse.size(), value);
    const bool ok = ec == std::errc() && ptr == parse.data() + parse.size();
    if (!std::isalpha(static_cast<unsigned char>(letter)) || !ok) continue;
    auto is = [&](double v) { return std::abs(value - v) < 1e-6; };
    switch (letter) {
      case 'X':
      case 'Y':
      case 'Z':
      case 'A':
      case 'B':
      case 'C':
        has_axis = true;
        break;
      case 'G':
        if (is(10)) g10 = true;
        if (is(10) || is(92) || is(43.1)) non_motion_axis_user = true;
        if (is(28) || is(30)) goes_home = true;
        if (is(28.1) || is(30.1)) writes_eeprom = true;
        break;
      case 'L':
        if (is(2) || is(20)) l2_or_l20 = true;
        break;
      default:
        break;
    }
  }
  t.exclusive = (g10 && l2_or_l20) || writes_eeprom;
  t.motion = (has_axis && !non_motion_axis_user) || goes_home;
  return t;
}

// For logs: non-printable bytes as \xNN, cut after 120 characters.
std::string Printable(std::string_view s) {
  std::string out;
  const bool cut = s.size() > 120;
  if (cut) s = s.substr(0, 120);
  for (char c : s) {
    const auto u = static_cast<unsigned char>(c);
    if (u >= 0x20 && u < 0x7f) {
      out.push_back(c);
    } else {
      static constexpr char kHex[] = "0123456789abcdef";
      out += "\\x";
      out.push_back(kHex[u >> 4]);
      out.push_back(kHex[u & 15]);
    }
  }
  if (cut) out += "...";
  return out;
}

}  // namespace

struct GrblClient::LineState {
  std::promise<GrblReply> promise;
  GrblReply reply;  // filled progressively; moved into the promise when resolved
  std::size_t bytes = 0;
  LineTraits traits;
};

// --- small types -------------------------------------------------------------------------------

std::string_view GrblReplyKindName(GrblReplyKind kind) {
  switch (kind) {
    case GrblReplyKind::kOk:
      return "ok";
    case GrblReplyKind::kError:
      return "error";
    case GrblReplyKind::kReset:
      return "reset";
    case GrblReplyKind::kRefused:
      return "refused";
    case GrblReplyKind::kDisconnected:
      return "disconnected";
    case GrblReplyKind::kClosed:
      return "closed";
    case GrblReplyKind::kTimeout:
      return "timeout";
  }
  return "?";
}

namespace {

bool HeldReport(const std::optional<GrblStatusSample>& s) {
  return s && s->status.state == GrblMachineState::kHold && s->status.substate <= 0;
}

}  // namespace

std::string_view GrblWaitResultName(GrblWaitResult result) {
  switch (result) {
    case GrblWaitResult::kIdle:
      return "idle";
    case GrblWaitResult::kTimeout:
      return "timeout";
    case GrblWaitResult::kAlarm:
      return "alarm";
    case GrblWaitResult::kDisconnected:
      return "disconnected";
    case GrblWaitResult::kHeld:
      return "held";
  }
  return "?";
}

std::string GrblReply::Describe() const {
  std::string s = "'" + line + "' #" + std::to_string(sequence) + ": ";
  s += GrblReplyKindName(kind);
  if (kind == GrblReplyKind::kError) s += ":" + std::to_string(error_code);
  if (!detail.empty()) s += " (" + detail + ")";
  if (alarm_code) s += " [ALARM:" + std::to_string(*alarm_code) + " before the reply]";
  return s;
}

bool GrblHandle::Done() const {
  return future_.valid() && future_.wait_for(std::chrono::seconds(0)) == std::future_status::ready;
}

GrblReply GrblHandle::Wait(std::chrono::milliseconds timeout) const {
  if (!future_.valid()) {
    GrblReply r;
    r.kind = GrblReplyKind::kRefused;
    r.detail = "invalid handle";
    return r;
  }
  if (future_.wait_for(timeout) != std::future_status::ready) {
    GrblReply r;
    r.kind = GrblReplyKind::kTimeout;
    r.line = line_;
    r.sequence = sequence_;
    r.detail = "no reply within " + std::to_string(timeout.count()) + " ms";
    return r;
  }
  return future_.get();
}

void GrblClientOptions::Check() const {
  auto positive = [](const char* name, milliseconds v) {
    if (v.count() <= 0) {
      throw std::invalid_argument(std::string("GrblClientOptions.") + name +
                                  " must be > 0 ms, got " + std::to_string(v.count()));
    }
  };
  positive("welcome_timeout", welcome_timeout);
  positive("reset_timeout", reset_timeout);
  positive("query_timeout", query_timeout);
  positive("homing_timeout", homing_timeout);
  positive("reconnect_backoff_initial", reconnect_backoff_initial);
  if (reconnect_backoff_max < reconnect_backoff_initial) {
    throw std::invalid_argument("GrblClientOptions.reconnect_backoff_max (" +
                                std::to_string(reconnect_backoff_max.count()) +
                                " ms) must be >= reconnect_backoff_initial (" +
                                std::to_string(reconnect_backoff_initial.count()) + " ms)");
  }
  if (status_min_interval.count() < 1 || status_min_interval.count() > 1000) {
    throw std::invalid_argument(
        "GrblClientOptions.status_min_interval must be in 1..1000 ms, got " +
        std::to_string(status_min_interval.count()) + " ms");
  }
  if (status_poll_interval.count() != 0 && status_poll_interval < status_min_interval) {
    throw std::invalid_argument(
        "GrblClientOptions.status_poll_interval must be 0 (off) or >= status_min_interval (" +
        std::to_string(status_min_interval.count()) + " ms), got " +
        std::to_string(status_poll_interval.count()) + " ms");
  }
  if (default_rx_buffer_bytes < 16) {
    throw std::invalid_argument("GrblClientOptions.default_rx_buffer_bytes must be >= 16, got " +
                                std::to_string(default_rx_buffer_bytes));
  }
  if (rx_reserve_bytes < 0 || rx_reserve_bytes >= default_rx_buffer_bytes) {
    throw std::invalid_argument("GrblClientOptions.rx_reserve_bytes must be in [0, " +
                                std::to_string(default_rx_buffer_bytes) + "), got " +
                                std::to_string(rx_reserve_bytes));
  }
}

std::optional<double> GrblMachineInfo::Setting(int number) const {
  const auto it = settings.find(number);
  if (it == settings.end()) return std::nullopt;
  return it->second;
}

// --- lifecycle ---------------------------------------------------------------------------------

GrblClient::GrblClient(TransportFactory factory, GrblClientOptions options)
    : options_(options), factory_(std::move(factory)) {
  options_.Check();
  if (!factory_) throw std::invalid_argument("GrblClient: empty transport factory");
  rx_buffer_bytes_ = options_.default_rx_buffer_bytes;
}

std::unique_ptr<GrblClient> GrblClient::ForUri(const std::string& uri,
                                               const TransportOptions& transport_options,
                                               const GrblClientOptions& options) {
  transport_options.Check();
  return std::make_unique<GrblClient>(
      [uri, transport_options] { return OpenTransport(uri, transport_options); }, options);
}

GrblClient::~GrblClient() {
  Disconnect();
}

void GrblClient::StartThreads() {
  {
    std::lock_guard lock(mu_);
    stop_ = false;
  }
  reader_ = std::thread([this, t = transport_.get()] { ReaderLoop(t); });
  poller_ = std::thread([this] { PollLoop(); });
}

void GrblClient::StopThreads() {
  {
    std::lock_guard lock(mu_);
    stop_ = true;
  }
  cv_.notify_all();
  if (reader_.joinable()) reader_.join();
  if (poller_.joinable()) poller_.join();
}

void GrblClient::Disconnect() {
  StopThreads();
  std::unique_ptr<Transport> old;
  {
    std::lock_guard lock(mu_);
    VoidAllLocked(GrblReplyKind::kClosed, "client closed");
    connected_ = false;
    trusted_ = false;
    std::lock_guard wlock(write_mu_);
    old = std::move(transport_);
  }
  cv_.notify_all();
  // Close outside the lock (a transport close may block briefly).
  old.reset();
}

GrblMachineInfo GrblClient::Connect() {
  {
    std::lock_guard lock(mu_);
    if (connected_) throw std::logic_error("GrblClient::Connect: already connected");
  }
  StopThreads();
  std::unique_ptr<Transport> transport = factory_();  // TransportError propagates
  if (!transport) throw TransportError("GrblClient: the transport factory returned null");
  {
    std::lock_guard lock(mu_);
    std::lock_guard wlock(write_mu_);
    transport_ = std::move(transport);
  }
  try {
    return Handshake();
  } catch (...) {
    Disconnect();
    throw;
  }
}

bool GrblClient::Reconnect(TransportFactory factory, std::chrono::milliseconds timeout) {
  if (!factory) throw std::invalid_argument("GrblClient::Reconnect: empty transport factory");
  {
    std::lock_guard lock(mu_);
    factory_ = std::move(factory);
  }
  return Reconnect(timeout);
}

bool GrblClient::Reconnect(const std::string& uri, const TransportOptions& transport_options,
                           std::chrono::milliseconds timeout) {
  transport_options.Check();
  return Reconnect([uri, transport_options] { return OpenTransport(uri, transport_options); },
                   timeout);
}

bool GrblClient::Reconnect(std::chrono::milliseconds timeout) {
  const auto deadline = Clock::now() + timeout;
  Disconnect();
  milliseconds backoff = options_.reconnect_backoff_initial;
  int attempt = 0;
  TransportFactory factory;
  {
    std::lock_guard lock(mu_);
    factory = factory_;
  }
  while (true) {
    ++attempt;
    try {
      std::unique_ptr<Transport> transport = factory();
      if (!transport) throw TransportError("the transport factory returned null");
      const std::string what = transport->Describe();
      {
        std::lock_guard lock(mu_);
        std::lock_guard wlock(write_mu_);
        transport_ = std::move(transport);
      }
      Handshake();
      spdlog::info(
          "grbl: reconnected to {} after {} attempt(s); position not trusted until "
          "homed or verified",
          what, attempt);
      return true;
    } catch (const std::exception& e) {
      spdlog::debug("grbl: reconnect attempt {} failed: {}", attempt, e.what());
      Disconnect();
    }
    const auto now = Clock::now();
    if (now >= deadline) break;
    std::this_thread::sleep_for(std::min<Clock::duration>(backoff, deadline - now));
    backoff = std::min(backoff * 2, options_.reconnect_backoff_max);
  }
  spdlog::warn("grbl: reconnect gave up after {} attempt(s) in {} ms", attempt, timeout.count());
  return false;
}

namespace {

// Input left in the port by an earlier session (replies, status reports) would be taken for
// answers to this one: read what is waiting, until 100 ms of silence (1 s and 64 KiB at most),
// before talking. Returns the number of bytes read into `out`.
std::size_t ReadPendingInput(Transport& transport, std::string* out) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(1);
  char buf[256];
  while (std::chrono::steady_clock::now() < deadline && out->size() < (64u << 10)) {
    const std::size_t n = transport.Read(buf, sizeof buf, std::chrono::milliseconds(100));
    if (n == 0) break;
    out->append(buf, n);
  }
  return out->size();
}

}  // namespace

bool GrblClient::Running(const std::string& what) {
  {
    std::lock_guard lock(mu_);
    if (!connected_) throw TransportClosed(what + " closed during the handshake");
  }
  // A controller that did not reset when the port opened is still running, perhaps still moving
  // (its last host died mid-run): a reset now would stop it dead and lose its position. Ask for
  // its status instead; a report means it is alive and its position is what it was.
  WriteRealtime('?');
  std::unique_lock lock(mu_);
  if (!cv_.wait_for(lock, options_.query_timeout,
                    [&] { return latest_status_.has_value() || !connected_; }) ||
      !connected_) {
    return false;
  }
  awaiting_welcome_ = false;
  spdlog::info("grbl: {} answers without a reset ({}): talking to it as it is", what,
               latest_status_->status.state_text);
  return true;
}

bool GrblClient::EndFeedHold(const std::string& what) {
  std::optional<GrblStatusSample> sample = LatestStatus();
  if (!sample || sample->status.state != GrblMachineState::kHold) return false;
  // Hold:1 still decelerates: a reset now would stop the steppers dead and lose the position.
  const auto deadline = Clock::now() + options_.reset_timeout;
  while (!HeldReport(sample) && Clock::now() < deadline) {
    sample = QueryStatus(options_.query_timeout);
  }
  if (!HeldReport(sample)) {
    throw GrblError(what + " is in a feed hold that does not come to a stop (" +
                    (sample ? sample->status.state_text : std::string("no status report")) +
                    " after " + std::to_string(options_.reset_timeout.count()) + " ms)");
  }
  spdlog::warn(
      "grbl: {} stands in a feed hold ({}:{}): a soft reset ends it (a completed hold "
      "keeps the position)",
      what, sample->status.state_text, sample->status.substate);
  if (!SoftReset()) {
    throw GrblError("no welcome from " + what + " after the soft reset that ends its feed hold");
  }
  return true;
}

void GrblClient::DiscardEarlierSessionReplies(milliseconds quiet, milliseconds limit) {
  const auto deadline = Clock::now() + limit;
  std::unique_lock lock(mu_);
  while (connected_ && Clock::now() < deadline && Clock::now() - last_rx_ < quiet) {
    cv_.wait_for(lock, milliseconds(10));
  }
  if (stats_.stray_replies > 0 || latest_status_) {
    spdlog::info("grbl: discarded what an earlier session was sent ({} stray reply lines)",
                 stats_.stray_replies);
  }
  // Nothing of this session is in flight yet: every ok so far was an earlier session's.
  stray_since_welcome_ = 0;
  latest_status_.reset();
}

GrblMachineInfo GrblClient::Handshake() {
  std::uint64_t resets_before = 0;
  const std::string what = BeginSession(&resets_before);
  FeedPendingInput(what);
  StartThreads();
  const bool ended_hold = AwaitWelcome(what, resets_before);
  // $I: build info and, on GRBL 1.1, [OPT:codes,blocks,rx_bytes]; $$: the settings.
  Query("$I", what);
  Query("$$", what);
  return FinishHandshake(what, ended_hold);
}

std::string GrblClient::BeginSession(std::uint64_t* resets_before) {
  std::lock_guard lock(mu_);
  connected_ = true;
  awaiting_welcome_ = true;
  alarmed_ = false;
  reset_required_ = false;
  trusted_ = false;
  stray_since_welcome_ = 0;
  last_alarm_.reset();
  in_flight_bytes_ = 0;
  rx_buffer_bytes_ = options_.default_rx_buffer_bytes;
  latest_status_.reset();
  last_wco_.reset();
  info_ = GrblMachineInfo{};
  *resets_before = stats_.resets;
  return transport_->Describe();
}

void GrblClient::FeedPendingInput(const std::string& what) {
  splitter_.Clear();
  std::string pending;
  const std::size_t read = ReadPendingInput(*transport_, &pending);
  // Everything before the controller's last welcome is an earlier session's; the welcome and
  // what follows it (a board that resets when the port opens) is this one's.
  const std::size_t welcome = pending.rfind("Grbl");
  const std::size_t keep_from = welcome == std::string::npos ? pending.size() : welcome;
  if (keep_from > 0) {
    spdlog::info("grbl: discarded {} stale byte(s) from {} before the handshake: '{}'", keep_from,
                 what, Printable(pending.substr(0, std::min<std::size_t>(keep_from, 120))));
  }
  if (keep_from < read) {
    std::vector<std::string> lines;
    splitter_.Feed(pending.data() + keep_from, read - keep_from, &lines);
    for (const std::string& line : lines) HandleLine(line, Clock::now());
  }
}

bool GrblClient::AwaitWelcome(const std::string& what, std::uint64_t resets_before) {
  auto wait_welcome = [&](milliseconds t) {
    std::unique_lock lock(mu_);
    return cv_.wait_for(lock, t, [&] { return stats_.resets > resets_before || !connected_; }) &&
           connected_;
  };
  const bool welcomed = wait_welcome(options_.welcome_timeout);
  const bool running = !welcomed && Running(what);
  // Nothing is answered in a hold once the planner is full ($I and $$ included): end it first.
  const bool ended_hold = running && EndFeedHold(what);
  if (running && !ended_hold) DiscardEarlierSessionReplies(milliseconds(100), milliseconds(1000));
  if (!welcomed && !running) {
    spdlog::info("grbl: no welcome from {} within {} ms, sending a soft reset", what,
                 options_.welcome_timeout.count());
    WriteRealtime('\x18');
    if (!wait_welcome(options_.reset_timeout)) {
      throw GrblError(
          "no GRBL welcome line from " + what + " within " +
          std::to_string(options_.welcome_timeout.count() + options_.reset_timeout.count()) +
          " ms (even after a soft reset): is this a GRBL controller at the right baud?");
    }
  }
  return ended_hold;
}

void GrblClient::Query(const std::string& line, const std::string& what) {
  const GrblReply reply = Send(line).Wait(options_.query_timeout);
  if (reply.kind == GrblReplyKind::kTimeout) {
    throw GrblError("no reply to " + line + " from " + what + " within " +
                    std::to_string(options_.query_timeout.count()) + " ms");
  }
  if (!reply.Ok()) spdlog::warn("grbl: {} on {}: {}", line, what, reply.Describe());
}

GrblMachineInfo GrblClient::FinishHandshake(const std::string& what, bool ended_hold) {
  std::lock_guard lock(mu_);
  if (!connected_) throw TransportClosed(what + " closed during the handshake");
  info_.rx_buffer_bytes = rx_buffer_bytes_;
  info_.ended_feed_hold = ended_hold;
  if (info_.version.empty()) {
    // No welcome (taken as it was): the version from $I's [VER:1.1h.20190825:].
    const std::size_t second_dot = info_.build.find('.', info_.build.find('.') + 1);
    info_.version = info_.build.substr(0, second_dot);
    if (info_.firmware.empty()) info_.firmware = "GRBL-family controller";
  }
  spdlog::info(
      "grbl: connected to {} {} on {}: RX buffer {} bytes{}, {} planner blocks, {} "
      "settings{}",
      info_.firmware, info_.version, what, info_.rx_buffer_bytes,
      info_.rx_buffer_from_firmware ? "" : " (default: $I gave no [OPT])", info_.planner_blocks,
      info_.settings.size(), alarmed_ ? ", in ALARM" : "");
  return info_;
}

// --- reader ------------------------------------------------------------------------------------

void GrblClient::ReaderLoop(Transport* transport) {
  std::vector<char> buf(4096);
  std::vector<std::string> lines;
  while (true) {
    {
      std::lock_guard lock(mu_);
      if (stop_) return;
    }
    std::size_t n = 0;
    try {
      n = transport->Read(buf.data(), buf.size(), kReadSlice);
    } catch (const TransportError& e) {
      std::lock_guard lock(mu_);
      TransportLostLocked(e.what());
      cv_.notify_all();
      return;
    }
    if (n == 0) continue;
    const auto t = Clock::now();
    {
      std::lock_guard lock(mu_);
      last_rx_ = t;
    }
    lines.clear();
    splitter_.Feed(buf.data(), n, &lines);
    for (const std::string& line : lines) HandleLine(line, t);
  }
}

void GrblClient::AttachMessageLocked(const std::string& raw) {
  if (!in_flight_.empty()) in_flight_.front()->reply.messages.push_back(raw);
}

void GrblClient::HandleLine(const std::string& text, Clock::time_point t) {
  const GrblMessage msg = ParseGrblLine(text);
  std::shared_ptr<MessageListener> listener;
  {
    std::lock_guard lock(mu_);
    listener = listener_;
    switch (msg.kind) {
      case GrblMessageKind::kOk:
      case GrblMessageKind::kError:
        HandleReplyLocked(msg, t);
        break;
      case GrblMessageKind::kAlarm:
        HandleAlarmLocked(msg);
        break;
      case GrblMessageKind::kWelcome:
        HandleWelcomeLocked(msg);
        break;
      case GrblMessageKind::kStatus:
        HandleStatusLocked(msg, t);
        break;
      case GrblMessageKind::kEmpty:
        break;
      case GrblMessageKind::kUnknown:
        ++stats_.unknown_lines;
        if (stats_.unknown_lines <= 20 || stats_.unknown_lines % 1000 == 0) {
          spdlog::warn("grbl: unrecognised line '{}' ignored ({} so far)", Printable(text),
                       stats_.unknown_lines);
        }
        break;
      default:
        HandleInfoLocked(msg);
        break;
    }
  }
  cv_.notify_all();
  if (listener && *listener) (*listener)(msg);
}

void GrblClient::HandleReplyLocked(const GrblMessage& msg, Clock::time_point t) {
  if (in_flight_.empty()) {
    spdlog::warn("grbl: '{}' with no line in flight, ignored", msg.raw);
    ++stats_.stray_replies;
    ++stray_since_welcome_;
    return;
  }
  std::shared_ptr<LineState> line = in_flight_.front();
  in_flight_.pop_front();
  in_flight_bytes_ -= line->bytes;
  ++stats_.replies;
  if (msg.kind == GrblMessageKind::kOk) {
    if (line->traits.home) {
      alarmed_ = false;
      reset_required_ = false;
      trusted_ = true;
    }
    if (line->traits.unlock) {
      alarmed_ = false;
      reset_required_ = false;
    }
    ResolveLocked(line, GrblReplyKind::kOk, "", t);
  } else {
    line->reply.error_code = msg.code;
    spdlog::warn("grbl: '{}' -> error:{} ({})", line->reply.line, msg.code, msg.text);
    ResolveLocked(line, GrblReplyKind::kError, msg.text, t);
  }
  PumpLocked();
}

void GrblClient::HandleAlarmLocked(const GrblMessage& msg) {
  alarmed_ = true;
  last_alarm_ = msg.code;
  ++stats_.alarms;
  if (GrblAlarmLosesPosition(msg.code)) trusted_ = false;
  if (!in_flight_.empty()) in_flight_.front()->reply.alarm_code = msg.code;
  spdlog::error("grbl: ALARM:{} ({}){}", msg.code, msg.text,
                in_flight_.empty()
                    ? std::string()
                    : " while '" + in_flight_.front()->reply.line + "' awaited its reply");
  RefuseQueuedNonSystemLocked("ALARM:" + std::to_string(msg.code) + " (" + msg.text + ")");
}

void GrblClient::HandleWelcomeLocked(const GrblMessage& msg) {
  ++stats_.resets;
  const bool was_awaiting = awaiting_welcome_;
  awaiting_welcome_ = false;
  info_.firmware = msg.name;
  info_.version = msg.version;
  stray_since_welcome_ = 0;
  const std::size_t voided = in_flight_.size() + queue_.size();
  VoidAllLocked(GrblReplyKind::kReset, "controller reset (welcome line) before the reply");
  in_flight_bytes_ = 0;
  trusted_ = false;
  // Reports from before the reset say nothing about the position now.
  latest_status_.reset();
  last_wco_.reset();
  alarmed_ = false;  // an alarm at start-up is announced by [MSG:'$H'|'$X' to unlock]
  reset_required_ = false;
  if (!was_awaiting) {
    spdlog::warn(
        "grbl: unexpected reset ({}); {} line(s) void, position unknown until "
        "re-homed or verified",
        msg.raw, voided);
  } else {
    spdlog::debug("grbl: welcome '{}'", msg.raw);
  }
}

void GrblClient::HandleStatusLocked(const GrblMessage& msg, Clock::time_point t) {
  ++stats_.status_reports;
  if (msg.status.wco) last_wco_ = msg.status.wco;
  GrblStatusSample sample;
  sample.status = msg.status;
  sample.machine_position = msg.status.MachinePosition(last_wco_);
  sample.received_at = t;
  latest_status_ = std::move(sample);
  if (msg.status.state == GrblMachineState::kAlarm) {
    if (!alarmed_) RefuseQueuedNonSystemLocked("machine in Alarm state");
    alarmed_ = true;
  } else if (msg.status.state != GrblMachineState::kUnknown) {
    alarmed_ = false;
  }
}

void GrblClient::HandleInfoLocked(const GrblMessage& msg) {
  AttachMessageLocked(msg.raw);
  switch (msg.kind) {
    case GrblMessageKind::kMessage:
      if (msg.text.find("to unlock") != std::string::npos) {
        alarmed_ = true;
        RefuseQueuedNonSystemLocked("machine in alarm at start-up (" + msg.text + ")");
      }
      if (msg.text.find("Reset to continue") != std::string::npos) reset_required_ = true;
      spdlog::info("grbl: [MSG:{}]", msg.text);
      break;
    case GrblMessageKind::kOptions:
      info_.option_codes = msg.option_codes;
      if (msg.planner_blocks) info_.planner_blocks = *msg.planner_blocks;
      if (msg.rx_buffer_bytes && *msg.rx_buffer_bytes > options_.rx_reserve_bytes + 8) {
        rx_buffer_bytes_ = *msg.rx_buffer_bytes;
        info_.rx_buffer_bytes = rx_buffer_bytes_;
        info_.rx_buffer_from_firmware = true;
      }
      break;
    case GrblMessageKind::kVersion:
      info_.build = msg.version;
      break;
    case GrblMessageKind::kSetting:
      if (msg.setting_value) info_.settings[msg.setting] = *msg.setting_value;
      break;
    default:
      spdlog::debug("grbl: {} '{}'", GrblMessageKindName(msg.kind), msg.raw);
      break;
  }
}

// --- sending -----------------------------------------------------------------------------------

std::size_t GrblClient::CapacityLocked() const {
  return static_cast<std::size_t>(rx_buffer_bytes_ - options_.rx_reserve_bytes);
}

void GrblClient::ResolveLocked(const std::shared_ptr<LineState>& line, GrblReplyKind kind,
                               std::string detail, Clock::time_point t) {
  line->reply.kind = kind;
  line->reply.received_at = t;
  if (!detail.empty()) line->reply.detail = std::move(detail);
  line->promise.set_value(std::move(line->reply));
}

void GrblClient::VoidAllLocked(GrblReplyKind kind, const std::string& detail) {
  const auto t = Clock::now();
  for (auto& line : in_flight_) ResolveLocked(line, kind, detail, t);
  for (auto& line : queue_) ResolveLocked(line, kind, detail, t);
  in_flight_.clear();
  queue_.clear();
  in_flight_bytes_ = 0;
}

void GrblClient::RefuseQueuedNonSystemLocked(const std::string& detail) {
  const auto t = Clock::now();
  std::deque<std::shared_ptr<LineState>> keep;
  for (auto& line : queue_) {
    if (line->traits.system) {
      keep.push_back(line);
    } else {
      ResolveLocked(line, GrblReplyKind::kRefused, "not sent: " + detail, t);
    }
  }
  queue_.swap(keep);
}

void GrblClient::TransportLostLocked(const std::string& why) {
  if (!connected_) return;
  connected_ = false;
  trusted_ = false;
  spdlog::error("grbl: transport lost: {}; {} line(s) in flight, {} queued are void", why,
                in_flight_.size(), queue_.size());
  VoidAllLocked(GrblReplyKind::kDisconnected, "transport lost: " + why);
}

void GrblClient::PumpLocked() {
  while (connected_ && !awaiting_welcome_ && !queue_.empty()) {
    const std::shared_ptr<LineState>& next = queue_.front();
    if (!in_flight_.empty() && in_flight_.front()->traits.exclusive) break;
    if (next->traits.exclusive && !in_flight_.empty()) break;
    if (in_flight_bytes_ + next->bytes > CapacityLocked()) break;
    std::shared_ptr<LineState> line = next;
    queue_.pop_front();
    in_flight_.push_back(line);
    in_flight_bytes_ += line->bytes;
    stats_.max_in_flight_bytes = std::max(stats_.max_in_flight_bytes, in_flight_bytes_);
    ++stats_.lines_sent;
    line->reply.sent_at = Clock::now();
    std::string bytes = line->reply.line;
    bytes.push_back('\n');
    try {
      std::lock_guard wlock(write_mu_);
      transport_->Write(bytes);
    } catch (const TransportError& e) {
      TransportLostLocked(e.what());
      return;
    }
    spdlog::trace("grbl: > {}", line->reply.line);
  }
}

GrblHandle GrblClient::Send(std::string_view line) {
  for (char c : line) {
    const auto u = static_cast<unsigned char>(c);
    if (c == '\n' || c == '\r' || c == '?' || c == '!' || c == '~' || u == 0x18 || u >= 0x80) {
      throw std::invalid_argument("GrblClient::Send: line '" + Printable(line) +
                                  "' contains a line break or a real-time character");
    }
  }
  auto state = std::make_shared<LineState>();
  state->traits = ClassifyLine(line);
  state->bytes = line.size() + 1;
  state->reply.line = std::string(line);
  GrblHandle handle;
  handle.future_ = state->promise.get_future().share();
  handle.line_ = state->reply.line;

  std::lock_guard lock(mu_);
  state->reply.sequence = handle.sequence_ = ++next_sequence_;
  if (state->bytes > CapacityLocked()) {
    throw std::invalid_argument("GrblClient::Send: line '" + state->reply.line + "' (" +
                                std::to_string(state->bytes) +
                                " bytes with its newline) exceeds "
                                "the RX stream budget of " +
                                std::to_string(CapacityLocked()) + " bytes");
  }
  const auto t = Clock::now();
  if (!connected_) {
    ResolveLocked(state, GrblReplyKind::kDisconnected, "not connected", t);
  } else if (awaiting_welcome_) {
    ResolveLocked(state, GrblReplyKind::kRefused,
                  "not sent: waiting for the welcome line after a reset", t);
  } else if (reset_required_) {
    ResolveLocked(state, GrblReplyKind::kRefused,
                  "not sent: the controller requires a reset ([MSG:Reset to continue])", t);
  } else if (alarmed_ && !state->traits.system) {
    ResolveLocked(state, GrblReplyKind::kRefused,
                  "not sent: machine in alarm" +
                      (last_alarm_ ? " (ALARM:" + std::to_string(*last_alarm_) + ": " +
                                         GrblAlarmText(*last_alarm_) + ")"
                                   : std::string()) +
                      "; home ($H) or unlock ($X) first",
                  t);
  } else if (options_.guard_motion && state->traits.motion && !trusted_) {
    ResolveLocked(state, GrblReplyKind::kRefused,
                  "not sent: machine position not trusted (after connect, reset, reconnect or a "
                  "position-losing alarm); Home() or VerifyPosition() first",
                  t);
  } else {
    queue_.push_back(state);
    PumpLocked();
  }
  return handle;
}

GrblReply GrblClient::Home() {
  spdlog::info("grbl: homing ($H)");
  GrblReply r = Send("$H").Wait(options_.homing_timeout);
  if (!r.Ok()) spdlog::error("grbl: homing failed: {}", r.Describe());
  return r;
}

GrblReply GrblClient::Unlock() {
  GrblReply r = Send("$X").Wait(options_.query_timeout);
  if (!r.Ok()) spdlog::warn("grbl: unlock failed: {}", r.Describe());
  return r;
}

bool GrblClient::WriteRealtime(char c) {
  {
    std::lock_guard lock(mu_);
    if (!connected_) return false;
  }
  std::string error;
  try {
    // transport_ changes only under both mu_ and write_mu_.
    std::lock_guard wlock(write_mu_);
    if (!transport_) return false;
    transport_->Write(std::string_view(&c, 1));
    return true;
  } catch (const TransportError& e) {
    error = e.what();
  }
  std::lock_guard lock(mu_);
  TransportLostLocked(error);
  cv_.notify_all();
  return false;
}

bool GrblClient::FeedHold() {
  return WriteRealtime('!');
}

bool GrblClient::CycleStart() {
  return WriteRealtime('~');
}

bool GrblClient::SoftReset() {
  std::uint64_t resets_before = 0;
  {
    std::lock_guard lock(mu_);
    if (!connected_) return false;
    resets_before = stats_.resets;
    // Lines not yet written are void at once. Lines in flight stay: GRBL still answers the line
    // it was executing (e.g. the ok of a soft-limit line comes after the reset that ends the
    // critical alarm), in order; the welcome then voids the rest, which GRBL flushed.
    const auto t = Clock::now();
    for (auto& line : queue_) {
      ResolveLocked(line, GrblReplyKind::kReset, "soft reset before the line was sent", t);
    }
    queue_.clear();
    awaiting_welcome_ = true;
    trusted_ = false;
  }
  cv_.notify_all();
  if (!WriteRealtime('\x18')) return false;
  std::unique_lock lock(mu_);
  const bool welcomed = cv_.wait_for(lock, options_.reset_timeout, [&] {
    return stats_.resets > resets_before || !connected_;
  }) && connected_;
  if (!welcomed && connected_) {
    spdlog::error("grbl: no welcome within {} ms after a soft reset; new lines stay refused",
                  options_.reset_timeout.count());
    VoidAllLocked(GrblReplyKind::kReset, "soft reset without a welcome line");
  }
  return welcomed;
}

GrblReply GrblClient::WaitForOk(const GrblHandle& handle, std::chrono::milliseconds timeout) const {
  return handle.Wait(timeout);
}

// --- status --------------------------------------------------------------------------------------

std::optional<Clock::time_point> GrblClient::RequestStatus(bool wait) {
  const milliseconds interval = options_.status_min_interval;
  std::lock_guard slock(status_request_mu_);
  auto now = Clock::now();
  const auto allowed = last_status_request_ + interval;
  if (last_status_request_ != Clock::time_point{} && now < allowed) {
    if (!wait) return std::nullopt;
    std::this_thread::sleep_until(allowed);
    now = Clock::now();
  }
  last_status_request_ = now;
  if (!WriteRealtime('?')) return std::nullopt;
  std::lock_guard lock(mu_);
  ++stats_.status_requests;
  return now;
}

void GrblClient::PollLoop() {
  if (options_.status_poll_interval.count() == 0) return;
  std::unique_lock lock(mu_);
  auto next = Clock::now() + options_.status_poll_interval;
  while (!stop_) {
    cv_.wait_until(lock, next, [&] { return stop_; });
    if (stop_) return;
    if (Clock::now() < next) continue;
    next += options_.status_poll_interval;
    if (next < Clock::now()) next = Clock::now() + options_.status_poll_interval;
    if (!connected_ || awaiting_welcome_) continue;
    lock.unlock();
    RequestStatus(/*wait=*/false);
    lock.lock();
  }
}

std::optional<GrblStatusSample> GrblClient::LatestStatus() const {
  std::lock_guard lock(mu_);
  return latest_status_;
}

std::optional<GrblStatusSample> GrblClient::QueryStatus(std::chrono::milliseconds timeout) {
  const auto deadline = Clock::now() + timeout;
  const auto sent = RequestStatus(/*wait=*/true);
  if (!sent) return std::nullopt;
  std::unique_lock lock(mu_);
  const bool got = cv_.wait_until(lock, deadline, [&] {
    return !connected_ || (latest_status_ && latest_status_->received_at > *sent);
  });
  if (!got || !connected_) return std::nullopt;
  return latest_status_;
}

bool GrblClient::Held() const {
  std::lock_guard lock(mu_);
  return HeldReport(latest_status_);
}

GrblWaitResult GrblClient::WaitIdle(std::chrono::milliseconds timeout) {
  const auto deadline = Clock::now() + timeout;
  {
    std::unique_lock lock(mu_);
    // Lines held in the planner by a feed hold are never answered: stop waiting at the hold.
    const bool drained = cv_.wait_until(lock, deadline, [&] {
      return !connected_ || alarmed_ || HeldReport(latest_status_) ||
             (in_flight_.empty() && queue_.empty());
    });
    if (!connected_) return GrblWaitResult::kDisconnected;
    if (alarmed_) return GrblWaitResult::kAlarm;
    if (HeldReport(latest_status_)) return GrblWaitResult::kHeld;
    if (!drained) return GrblWaitResult::kTimeout;
  }
  // Two consecutive fresh Idle reports: GRBL may report Idle in the instant between the ok of
  // the last motion line and the start of its motion.
  int idle_reports = 0;
  while (Clock::now() < deadline) {
    const auto left = std::chrono::duration_cast<milliseconds>(deadline - Clock::now());
    const auto sample = QueryStatus(left);
    std::lock_guard lock(mu_);
    if (!connected_) return GrblWaitResult::kDisconnected;
    if (alarmed_) return GrblWaitResult::kAlarm;
    if (!sample) continue;
    if (HeldReport(sample)) return GrblWaitResult::kHeld;
    const bool busy = !in_flight_.empty() || !queue_.empty();
    if (!busy && sample->status.state == GrblMachineState::kIdle) {
      if (++idle_reports >= 2) return GrblWaitResult::kIdle;
    } else {
      idle_reports = 0;
    }
  }
  return GrblWaitResult::kTimeout;
}

GrblVerifyResult GrblClient::VerifyPosition(const Eigen::Vector3d& expected_mpos,
                                            double tolerance_mm,
                                            std::chrono::milliseconds timeout) {
  GrblVerifyResult result;
  if (!(tolerance_mm >= 0.0)) {
    throw std::invalid_argument("VerifyPosition: tolerance_mm must be >= 0, got " +
                                std::to_string(tolerance_mm));
  }
  const GrblWaitResult idle = WaitIdle(timeout);
  if (idle != GrblWaitResult::kIdle) {
    result.detail = "machine not idle: " + std::string(GrblWaitResultName(idle));
    return result;
  }
  std::lock_guard lock(mu_);
  if (!latest_status_ || !latest_status_->machine_position) {
    result.detail = "status report has no machine position (WPos without WCO)";
    return result;
  }
  result.reported = latest_status_->machine_position;
  result.error_mm = (*result.reported - expected_mpos).norm();
  result.ok = result.error_mm <= tolerance_mm;
  if (result.ok) {
    trusted_ = true;
    result.detail = "position verified";
  } else {
    result.detail = "position differs from the expected one by " + std::to_string(result.error_mm) +
                    " mm (tolerance " + std::to_string(tolerance_mm) + " mm)";
    spdlog::warn("grbl: {}", result.detail);
  }
  return result;
}

// --- accessors -----------------------------------------------------------------------------------

bool GrblClient::Connected() const {
  std::lock_guard lock(mu_);
  return connected_;
}

GrblMachineInfo GrblClient::MachineInfo() const {
  std::lock_guard lock(mu_);
  return info_;
}

bool GrblClient::PositionTrusted() const {
  std::lock_guard lock(mu_);
  return trusted_;
}

std::uint64_t GrblClient::StrayRepliesSinceWelcome() const {
  std::lock_guard lock(mu_);
  return stray_since_welcome_;
}

void GrblClient::MarkPositionTrusted() {
  std::lock_guard lock(mu_);
  trusted_ = true;
}

bool GrblClient::ResetRequired() const {
  std::lock_guard lock(mu_);
  return reset_required_;
}

bool GrblClient::Alarmed() const {
  std::lock_guard lock(mu_);
  return alarmed_;
}

std::optional<int> GrblClient::LastAlarm() const {
  std::lock_guard lock(mu_);
  return last_alarm_;
}

std::size_t GrblClient::InFlightLines() const {
  std::lock_guard lock(mu_);
  return in_flight_.size();
}

std::size_t GrblClient::InFlightBytes() const {
  std::lock_guard lock(mu_);
  return in_flight_bytes_;
}

std::size_t GrblClient::QueuedLines() const {
  std::lock_guard lock(mu_);
  return queue_.size();
}

std::size_t GrblClient::StreamCapacity() const {
  std::lock_guard lock(mu_);
  return CapacityLocked();
}

GrblClientStats GrblClient::Stats() const {
  std::lock_guard lock(mu_);
  return stats_;
}

void GrblClient::SetMessageListener(MessageListener listener) {
  std::lock_guard lock(mu_);
  listener_ = std::make_shared<MessageListener>(std::move(listener));
}

// --- press G-code ------------------------------------------------------------------------------

void PressMotion::Check() const {
  auto finite = [](const char* name, const Eigen::Vector3d& v) {
    if (!v.allFinite()) {
      throw std::invalid_argument(std::string("PressMotion.") + name + " is not finite: (" +
                                  std::to_string(v.x()) + ", " + std::to_string(v.y()) + ", " +
                                  std::to_string(v.z()) + ")");
    }
  };
  finite("approach", approach);
  finite("press", press);
  if (!(press_feed_mm_min > 0.0) || !std::isfinite(press_feed_mm_min)) {
    throw std::invalid_argument("PressMotion.press_feed_mm_min must be > 0, got " +
                                std::to_string(press_feed_mm_min));
  }
  if (!(dwell_s >= 0.0) || !std::isfinite(dwell_s)) {
    throw std::invalid_argument("PressMotion.dwell_s must be >= 0, got " + std::to_string(dwell_s));
  }
  if (!(retract_feed_mm_min >= 0.0) || !std::isfinite(retract_feed_mm_min)) {
    throw std::invalid_argument("PressMotion.retract_feed_mm_min must be >= 0 (0 = rapid), got " +
                                std::to_string(retract_feed_mm_min));
  }
}

PressGcode MakePressGcode(const PressMotion& m) {
  m.Check();
  // Built by appending (GCC 12 reports a false -Wrestrict on chains of operator+).
  const std::string g53 = m.machine_coordinates ? "G53 " : "";
  auto move = [&](std::string prefix, const char* motion, const Eigen::Vector3d& p, double feed) {
    std::string s = std::move(prefix);
    s.append(g53).append(motion);
    s.append(" X").append(FormatFixed(p.x(), 3));
    s.append(" Y").append(FormatFixed(p.y(), 3));
    s.append(" Z").append(FormatFixed(p.z(), 3));
    if (feed > 0.0) s.append(" F").append(FormatFixed(feed, 1));
    return s;
  };
  PressGcode g;
  g.approach = move("G90 ", "G0", m.approach, 0.0);
  g.press = move("", "G1", m.press, m.press_feed_mm_min);
  g.dwell = std::string("G4 P").append(FormatFixed(m.dwell_s, 3));
  g.retract = m.retract_feed_mm_min > 0.0 ? move("", "G1", m.approach, m.retract_feed_mm_min)
                                          : move("", "G0", m.approach, 0.0);
  return g;
}

}  // namespace gs360
