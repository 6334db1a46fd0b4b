#include "daemon/notifier.h"

#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <spawn.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <condition_variable>
#include <cstdlib>
#include <cstring>
#include <deque>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <random>
#include <stdexcept>
#include <thread>

#include <httplib.h>
#include <spdlog/spdlog.h>

#include "base/base64.h"
#include "base/field_error.h"
#include "base/format.h"

extern char** environ;

namespace gs360 {
namespace {

using Json = nlohmann::json;
using Clock = std::chrono::steady_clock;

constexpr std::array<std::pair<NotifyEvent, std::string_view>, 14> kEventNames{{
    {NotifyEvent::kCreated, "created"},
    {NotifyEvent::kStarted, "started"},
    {NotifyEvent::kPaused, "paused"},
    {NotifyEvent::kResumed, "resumed"},
    {NotifyEvent::kAwaitingConfirmation, "awaiting_confirmation"},
    {NotifyEvent::kInterrupted, "interrupted"},
    {NotifyEvent::kAlarm, "alarm"},
    {NotifyEvent::kFailed, "failed"},
    {NotifyEvent::kCancelled, "cancelled"},
    {NotifyEvent::kDone, "done"},
    {NotifyEvent::kConverged, "converged"},
    {NotifyEvent::kCalibrationDone, "calibration_done"},
    {NotifyEvent::kUncleanStart, "unclean_start"},
    {NotifyEvent::kTest, "test"},
}};

double UnixSeconds() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

// "https://user:pw@ntfy.sh:443/topic?x" -> {"https://ntfy.sh:443", "/topic?x"}; throws for
// anything but http(s)://host[:port][/...].
struct SplitUrl {
  std::string origin;  // scheme://host[:port], no user info
  std::string target;  // path and query, at least "/"
};
SplitUrl Split(const std::string& url) {
  const auto scheme_end = url.find("://");
  const std::string scheme = scheme_end == std::string::npos ? "" : url.substr(0, scheme_end);
  if (scheme != "http" && scheme != "https") {
    throw std::invalid_argument("notify.url must start with http:// or https://, got \"" +
                                url.substr(0, std::min<std::size_t>(url.size(), 8)) + "...\"");
  }
  const std::size_t host_start = scheme_end + 3;
  std::size_t path_start = url.find_first_of("/?#", host_start);
  if (path_start == std::string::npos) path_start = url.size();
  std::string authority = url.substr(host_start, path_start - host_start);
  if (const auto at = authority.rfind('@'); at != std::string::npos) authority.erase(0, at + 1);
  if (authority.empty()) throw std::invalid_argument("notify.url has no host");
  std::string target = url.substr(path_start);
  if (const auto hash = target.find('#'); hash != std::string::npos) target.erase(hash);
  if (target.empty() || target[0] != '/') target.insert(0, "/");
  return {scheme + "://" + authority, target};
}

std::string DurationText(const Json& run, const char* key) {
  return run.is_object() && run.contains(key) && run[key].is_number()
             ? FormatDuration(run[key].get<double>())
             : std::string();
}

// "812 of 2,011 probes, 3 failed, ETA 1h 02m".
std::string ProgressLine(const Json& run) {
  if (!run.is_object() || !run.contains("probes_total")) return "";
  std::string line = std::to_string(run.value("probes_done", 0)) + " of " +
                     std::to_string(run.value("probes_total", 0)) + " probes";
  if (run.value("probes_failed", 0) > 0) {
    line += ", " + std::to_string(run.value("probes_failed", 0)) + " failed";
  }
  const std::string eta = DurationText(run, "eta_s");
  if (!eta.empty() && run.value("state", "") != "done") line += ", ETA " + eta;
  return line;
}

// The command that answers, for the events that need a person.
std::string ActionFor(NotifyEvent event, const Json& run, std::int64_t id) {
  const std::string n = std::to_string(id);
  switch (event) {
    case NotifyEvent::kAwaitingConfirmation: {
      const std::string what = run.is_object() && run.value("awaiting", Json()).is_string()
                                   ? run["awaiting"].get<std::string>()
                                   : "position";
      return "gs360 run resume " + n + " --confirm " + what;
    }
    case NotifyEvent::kInterrupted:
    case NotifyEvent::kAlarm:
    case NotifyEvent::kUncleanStart:
      return "gs360 run resume " + n;
    case NotifyEvent::kFailed:
      return "gs360 run log " + n;
    case NotifyEvent::kDone:
    case NotifyEvent::kConverged:
      return "gs360 calibrate " + n;
    case NotifyEvent::kCalibrationDone:
      return "gs360 export " + n + " --out model/";
    default:
      return "";
  }
}

std::string HeadlineFor(NotifyEvent event) {
  switch (event) {
    case NotifyEvent::kAwaitingConfirmation:
      return "waits for you to confirm";
    case NotifyEvent::kInterrupted:
      return "interrupted";
    case NotifyEvent::kAlarm:
      return "machine alarm";
    case NotifyEvent::kUncleanStart:
      return "was running when gs360d stopped uncleanly";
    case NotifyEvent::kCalibrationDone:
      return "calibration done";
    case NotifyEvent::kTest:
      return "test notification";
    default:
      return std::string(ToString(event));
  }
}

bool Urgent(NotifyEvent e) {
  return e == NotifyEvent::kAlarm || e == NotifyEvent::kFailed || e == NotifyEvent::kInterrupted ||
         e == NotifyEvent::kAwaitingConfirmation || e == NotifyEvent::kUncleanStart;
}

// The text of the Slack, Discord and ntfy bodies: the message, then the action.
std::string PlainText(const Notification& n, bool with_title) {
  std::string text = with_title ? n.title + "\n" : "";
  text += n.message;
  if (!n.dashboard_url.empty()) text += "\n" + n.dashboard_url;
  return text;
}

}  // namespace

std::string_view ToString(NotifyEvent event) {
  for (const auto& [e, name] : kEventNames) {
    if (e == event) return name;
  }
  return "unknown";
}

std::optional<NotifyEvent> NotifyEventFromString(std::string_view name) {
  for (const auto& [e, n] : kEventNames) {
    if (n == name) return e;
  }
  return std::nullopt;
}

const std::vector<NotifyEvent>& AllNotifyEvents() {
  static const std::vector<NotifyEvent> all = [] {
    std::vector<NotifyEvent> v;
    for (const auto& [e, name] : kEventNames) v.push_back(e);
    return v;
  }();
  return all;
}

void NotifyTarget::Check() const {
  if (url.empty() == command.empty()) {
    throw std::invalid_argument("notify: give exactly one of url and command");
  }
  if (!url.empty()) {
    // A space or control character would end the request line early or start a header.
    if (std::any_of(url.begin(), url.end(),
                    [](unsigned char c) { return c <= 0x20 || c == 0x7f; })) {
      throw std::invalid_argument("notify.url must not contain spaces or control characters");
    }
    Split(url);
  }
  if (!command.empty() && command[0].empty()) {
    throw std::invalid_argument("notify.command: the program's name is empty");
  }
  if (format != "json" && format != "ntfy" && format != "slack" && format != "discord") {
    throw std::invalid_argument("notify.format must be json, ntfy, slack or discord, got \"" +
                                format + "\"");
  }
  for (const std::string& e : events) {
    if (!NotifyEventFromString(e)) {
      std::string names;
      for (const auto& [ev, name] : kEventNames)
        names += (names.empty() ? "" : ", ") + std::string(name);
      throw std::invalid_argument("notify.events: unknown event \"" + e + "\" (expected one of " +
                                  names + ")");
    }
  }
  if (!(timeout_s > 0.0 && timeout_s <= 600.0)) {
    ThrowFieldError("notify.timeout_s", timeout_s, "must be in (0, 600] s");
  }
  if (retries < 0 || retries > 20) ThrowFieldError("notify.retries", retries, "must be in [0, 20]");
  if (!(backoff_s >= 0.0 && backoff_s <= 3600.0)) {
    ThrowFieldError("notify.backoff_s", backoff_s, "must be in [0, 3600] s");
  }
  if (queue_size < 1 || queue_size > 100000) {
    ThrowFieldError("notify.queue_size", queue_size, "must be in [1, 100000]");
  }
  if (attach_frame && !url.empty() && format == "slack") {
    throw std::invalid_argument(
        "notify.attach_frame: Slack's incoming webhooks take no files (use format \"json\", "
        "\"ntfy\" or \"discord\", or attach_frame = false)");
  }
}

bool NotifyTarget::Wants(NotifyEvent event) const {
  if (event == NotifyEvent::kTest || events.empty()) return true;
  return std::find(events.begin(), events.end(), ToString(event)) != events.end();
}

std::string NotifyTarget::RedactedUrl() const {
  try {
    const SplitUrl split = Split(url);
    return split.origin + (split.target == "/" ? "/" : "/...");
  } catch (const std::invalid_argument&) {
    return "(an invalid url)";
  }
}

std::string NotifyTarget::Describe() const {
  if (!url.empty()) return RedactedUrl() + " (" + format + ")";
  return command.empty() ? "nothing" : "command " + command[0];
}

void CheckNotifyTargets(const std::vector<NotifyTarget>& targets) {
  for (std::size_t i = 0; i < targets.size(); ++i) {
    try {
      targets[i].Check();
    } catch (const std::invalid_argument& e) {
      std::string what = e.what();
      const std::string indexed = "notify[" + std::to_string(i) + "]";
      if (what.rfind("notify", 0) == 0) what.replace(0, 6, indexed);
      throw std::invalid_argument(what);
    }
  }
}

Json Notification::ToJson() const {
  return {{"event", std::string(ToString(event))},
          {"run", run == 0 ? Json(nullptr) : Json(run)},
          {"run_name", run_name},
          {"title", title},
          {"message", message},
          {"action", action.empty() ? Json(nullptr) : Json(action)},
          {"dashboard_url", dashboard_url},
          {"progress", progress},
          {"last_error", last_error.empty() ? Json(nullptr) : Json(last_error)},
          {"time", time}};
}

Notification MakeNotification(NotifyEvent event, const Json& run, const std::string& detail,
                              const std::string& dashboard_url) {
  Notification n;
  n.event = event;
  n.time = UnixSeconds();
  const bool has_run = run.is_object() && run.contains("id");
  n.run = has_run ? run["id"].get<std::int64_t>() : 0;
  n.run_name = has_run ? run.value("name", "") : "";
  n.title = has_run ? "gs360 run " + std::to_string(n.run) +
                          (n.run_name.empty() ? "" : " (" + n.run_name + ")") + ": " +
                          HeadlineFor(event)
                    : "gs360: " + HeadlineFor(event);
  n.dashboard_url = dashboard_url;
  if (has_run && !dashboard_url.empty()) n.dashboard_url += "#run=" + std::to_string(n.run);
  std::vector<std::string> lines;
  if (!detail.empty()) lines.push_back(detail);
  if (has_run) {
    n.progress = {{"probes_done", run.value("probes_done", 0)},
                  {"probes_total", run.value("probes_total", 0)},
                  {"probes_failed", run.value("probes_failed", 0)},
                  {"eta_s", run.value("eta_s", Json())}};
    if (const std::string p = ProgressLine(run); !p.empty()) lines.push_back(p);
    if (run.value("last_error", Json()).is_string()) {
      n.last_error = run["last_error"].get<std::string>();
      if (n.last_error != detail) lines.push_back("Last error: " + n.last_error);
    }
  }
  n.action = has_run ? ActionFor(event, run, n.run) : "";
  if (!n.action.empty()) lines.push_back("To go on: " + n.action);
  for (const std::string& line : lines) n.message += (n.message.empty() ? "" : "\n") + line;
  if (n.message.empty()) n.message = n.title;
  return n;
}

namespace {

// A header's value on one line: ntfy turns "\n" back into a newline; other control characters
// become spaces (they would end the header or start another).
std::string HeaderValue(const std::string& text) {
  std::string out;
  for (const char c : text) {
    if (c == '\n') {
      out += "\\n";
    } else if (static_cast<unsigned char>(c) < 0x20 || c == 0x7f) {
      out += ' ';
    } else {
      out += c;
    }
  }
  return out;
}

// ntfy with the frame: the PNG is the body (an attachment), the text goes in a header.
WebhookRequest NtfyWithFrame(const Notification& n, WebhookRequest r) {
  r.headers.emplace_back("Message", HeaderValue(PlainText(n, false)));
  r.headers.emplace_back("Filename", "gs360-run-" + std::to_string(n.run) + "-frame.png");
  r.content_type = "image/png";
  r.body.assign(n.frame_png->begin(), n.frame_png->end());
  return r;
}

// Discord with the frame: multipart/form-data, the message in payload_json, the PNG in files[0].
WebhookRequest DiscordWithFrame(const Notification& n) {
  std::mt19937_64 rng(std::random_device{}());
  const std::string boundary = "gs360-" + std::to_string(rng()) + std::to_string(rng());
  std::string body = "--" + boundary +
                     "\r\nContent-Disposition: form-data; name=\"payload_json\"\r\n"
                     "Content-Type: application/json\r\n\r\n" +
                     Json{{"content", PlainText(n, true)}}.dump() + "\r\n--" + boundary +
                     "\r\nContent-Disposition: form-data; name=\"files[0]\"; "
                     "filename=\"frame.png\"\r\nContent-Type: image/png\r\n\r\n";
  body.append(n.frame_png->begin(), n.frame_png->end());
  body += "\r\n--" + boundary + "--\r\n";
  return {"multipart/form-data; boundary=" + boundary, std::move(body), {}};
}

}  // namespace

WebhookRequest FormatWebhook(const Notification& n, std::string_view format, bool attach_frame) {
  const bool frame = attach_frame && n.frame_png && !n.frame_png->empty();
  if (format == "ntfy") {
    // ntfy reads its title, priority and tags from headers; the body is the message.
    WebhookRequest r{"text/plain; charset=utf-8", PlainText(n, false), {}};
    r.headers = {{"Title", n.title},
                 {"Priority", Urgent(n.event) ? "high" : "default"},
                 {"Tags", std::string(ToString(n.event))}};
    if (!n.dashboard_url.empty()) r.headers.emplace_back("Click", n.dashboard_url);
    return frame ? NtfyWithFrame(n, std::move(r)) : r;
  }
  if (format == "slack") return {"application/json", Json{{"text", PlainText(n, true)}}.dump(), {}};
  if (format == "discord") {
    if (frame) return DiscordWithFrame(n);
    return {"application/json", Json{{"content", PlainText(n, true)}}.dump(), {}};
  }
  Json body = n.ToJson();
  if (frame) body["frame_png_base64"] = Base64Encode(*n.frame_png);
  return {"application/json", body.dump(), {}};
}

namespace {

// One attempt at a webhook: empty on a 2xx answer, else what went wrong (never the URL's path).
std::string PostWebhook(const NotifyTarget& t, const Notification& n) {
  const SplitUrl url = Split(t.url);
  const WebhookRequest req = FormatWebhook(n, t.format, t.attach_frame);
  httplib::Client client(url.origin);
  const auto timeout = std::chrono::duration<double>(t.timeout_s);
  const auto sec = static_cast<time_t>(timeout.count());
  const auto usec = static_cast<time_t>((timeout.count() - static_cast<double>(sec)) * 1e6);
  client.set_connection_timeout(sec, usec);
  client.set_read_timeout(sec, usec);
  client.set_write_timeout(sec, usec);
  httplib::Headers headers;
  for (const auto& [k, v] : req.headers) headers.emplace(k, v);
  headers.emplace("User-Agent", "gs360d");
  const auto res = client.Post(url.target, headers, req.body, req.content_type);
  if (!res) return "no answer (" + httplib::to_string(res.error()) + ")";
  if (res->status < 200 || res->status >= 300) return "HTTP " + std::to_string(res->status);
  return "";
}

// A command's copy of the frame: a file of its own (mode 0600) in the temp folder, removed when
// the attempt ends.
class FrameFile {
 public:
  explicit FrameFile(const Notification& n) {
    if (!n.frame_png || n.frame_png->empty()) return;
    std::string pattern =
        (std::filesystem::temp_directory_path() / "gs360-frame-XXXXXX.png").string();
    const int fd = ::mkstemps(pattern.data(), 4);
    if (fd < 0) throw std::runtime_error("cannot create a file for the frame in " + pattern);
    path_ = pattern;
    const std::uint8_t* p = n.frame_png->data();
    std::size_t left = n.frame_png->size();
    while (left > 0) {
      const ssize_t w = ::write(fd, p, left);
      if (w <= 0) break;
      p += w;
      left -= static_cast<std::size_t>(w);
    }
    ::close(fd);
    if (left > 0) throw std::runtime_error("cannot write the frame to " + path_);
  }
  ~FrameFile() {
    if (!path_.empty()) ::unlink(path_.c_str());
  }
  FrameFile(const FrameFile&) = delete;
  FrameFile& operator=(const FrameFile&) = delete;
  const std::string& path() const { return path_; }

 private:
  std::string path_;
};

// The child's environment: gs360d's, with the notification's fields as GS360_*.
std::vector<std::string> CommandEnvironment(const Notification& n, const std::string& frame) {
  std::vector<std::string> env;
  for (char** e = environ; e != nullptr && *e != nullptr; ++e) {
    if (std::string_view(*e).rfind("GS360_", 0) != 0) env.emplace_back(*e);
  }
  env.push_back("GS360_EVENT=" + std::string(ToString(n.event)));
  env.push_back("GS360_RUN=" + (n.run == 0 ? std::string() : std::to_string(n.run)));
  env.push_back("GS360_RUN_NAME=" + n.run_name);
  env.push_back("GS360_TITLE=" + n.title);
  env.push_back("GS360_MESSAGE=" + n.message);
  env.push_back("GS360_ACTION=" + n.action);
  env.push_back("GS360_DASHBOARD=" + n.dashboard_url);
  if (!frame.empty()) env.push_back("GS360_FRAME=" + frame);
  return env;
}

std::vector<char*> Pointers(std::vector<std::string>& strings) {
  std::vector<char*> p;
  for (std::string& s : strings) p.push_back(s.data());
  p.push_back(nullptr);
  return p;
}

// Writes `data` to the child's stdin, reads up to 2 kB of its output, and waits for it until the
// deadline; the child is killed past it. Returns the exit status or an error text.
std::string WaitForChild(pid_t pid, int fd, const std::string& data, Clock::time_point deadline) {
  std::size_t sent = 0;
  while (sent < data.size()) {
    const ssize_t n = ::send(fd, data.data() + sent, data.size() - sent, MSG_NOSIGNAL);
    if (n <= 0) break;  // the program does not read its stdin: fine
    sent += static_cast<std::size_t>(n);
  }
  ::shutdown(fd, SHUT_WR);
  std::string output;
  for (;;) {
    const auto left =
        std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now());
    if (left.count() <= 0) break;
    pollfd p{fd, POLLIN, 0};
    if (::poll(&p, 1, static_cast<int>(std::min<long long>(left.count(), 100))) <= 0) continue;
    char buf[512];
    const ssize_t n = ::recv(fd, buf, sizeof buf, 0);
    if (n <= 0) break;
    if (output.size() < 2048) output.append(buf, static_cast<std::size_t>(n));
  }
  int status = 0;
  for (;;) {
    const pid_t r = ::waitpid(pid, &status, WNOHANG);
    if (r == pid) break;
    if (r < 0) return "waitpid failed";
    if (Clock::now() >= deadline) {
      ::kill(pid, SIGKILL);
      ::waitpid(pid, &status, 0);
      return "timed out; killed";
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  if (WIFEXITED(status) && WEXITSTATUS(status) == 0) return "";
  std::string what = WIFEXITED(status) ? "exit code " + std::to_string(WEXITSTATUS(status))
                                       : "killed by signal " + std::to_string(WTERMSIG(status));
  while (!output.empty() && (output.back() == '\n' || output.back() == '\r')) output.pop_back();
  if (const auto nl = output.rfind('\n'); nl != std::string::npos) output.erase(0, nl + 1);
  return output.empty() ? what : what + ": " + output.substr(0, 200);
}

// One attempt at a command: the notification as JSON on stdin and in GS360_* variables; stdout
// and stderr are read (the last line names a failure). Empty on exit code 0.
std::string RunCommand(const NotifyTarget& t, const Notification& n) {
  const FrameFile frame(n);
  Json stdin_json = n.ToJson();
  if (!frame.path().empty()) stdin_json["frame_path"] = frame.path();
  int fds[2];
  if (::socketpair(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0, fds) != 0) return "socketpair failed";
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_adddup2(&actions, fds[1], 0);
  posix_spawn_file_actions_adddup2(&actions, fds[1], 1);
  posix_spawn_file_actions_adddup2(&actions, fds[1], 2);
  posix_spawnattr_t attr;
  posix_spawnattr_init(&attr);
  // gs360d blocks SIGTERM and SIGINT for its signal thread; the child gets them back.
  sigset_t none;
  sigemptyset(&none);
  posix_spawnattr_setsigmask(&attr, &none);
  posix_spawnattr_setflags(&attr, POSIX_SPAWN_SETSIGMASK);
  std::vector<std::string> argv_s = t.command;
  std::vector<std::string> env_s = CommandEnvironment(n, frame.path());
  std::vector<char*> argv = Pointers(argv_s);
  std::vector<char*> envp = Pointers(env_s);
  pid_t pid = 0;
  const int rc = ::posix_spawnp(&pid, argv[0], &actions, &attr, argv.data(), envp.data());
  posix_spawn_file_actions_destroy(&actions);
  posix_spawnattr_destroy(&attr);
  ::close(fds[1]);
  if (rc != 0) {
    ::close(fds[0]);
    return "cannot run " + t.command[0] + ": " + std::strerror(rc);
  }
  const auto deadline = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                           std::chrono::duration<double>(t.timeout_s));
  std::string result = WaitForChild(pid, fds[0], stdin_json.dump() + "\n", deadline);
  ::close(fds[0]);
  return result;
}

}  // namespace

// One target's queue and thread.
class Notifier::Worker {
 public:
  explicit Worker(NotifyTarget target) : target_(std::move(target)) {
    thread_ = std::thread([this] { Loop(); });
  }
  ~Worker() {
    {
      std::lock_guard lock(mutex_);
      stop_ = true;
      dropped_ += static_cast<std::int64_t>(queue_.size());
      queue_.clear();
    }
    wake_.notify_all();
    thread_.join();
  }

  const NotifyTarget& target() const { return target_; }

  void Send(const Notification& n) {
    {
      std::lock_guard lock(mutex_);
      if (stop_) return;
      if (queue_.size() >= static_cast<std::size_t>(target_.queue_size)) {
        ++dropped_;
        spdlog::warn("notify {}: queue full ({}): dropped the {} notification", target_.Describe(),
                     target_.queue_size, ToString(n.event));
        return;
      }
      queue_.push_back(n);
      // Only a target that attaches frames keeps one (memory, and no PNG in its queue).
      if (!target_.attach_frame) queue_.back().frame_png.reset();
      ++queued_;
    }
    wake_.notify_all();
  }

  bool Idle() const {
    std::lock_guard lock(mutex_);
    return queue_.empty() && !busy_;
  }

  Json View() const {
    std::lock_guard lock(mutex_);
    Json events = Json::array();
    for (const std::string& e : target_.events) events.push_back(e);
    Json recent = Json::array();
    for (const Json& r : recent_) recent.push_back(r);
    return {{"target", target_.Describe()},
            {"kind", target_.url.empty() ? "command" : "webhook"},
            {"format", target_.url.empty() ? "json" : target_.format},
            {"attach_frame", target_.attach_frame},
            {"events", target_.events.empty() ? Json("all") : events},
            {"queued", queued_},
            {"delivered", delivered_},
            {"failed", failed_},
            {"dropped", dropped_},
            {"waiting", queue_.size()},
            {"recent", recent}};
  }

 private:
  void Loop() {
    std::unique_lock lock(mutex_);
    for (;;) {
      wake_.wait(lock, [&] { return stop_ || !queue_.empty(); });
      if (stop_) return;
      Notification n = std::move(queue_.front());
      queue_.pop_front();
      busy_ = true;
      lock.unlock();
      Deliver(n);
      lock.lock();
      busy_ = false;
    }
  }

  // Tries, backs off, tries again; an attempt's wait for the next ends early on shutdown.
  void Deliver(const Notification& n) {
    std::string error;
    int attempt = 0;
    double backoff = target_.backoff_s;
    for (; attempt <= target_.retries; ++attempt) {
      if (attempt > 0) {
        std::unique_lock lock(mutex_);
        if (wake_.wait_for(lock, std::chrono::duration<double>(backoff), [&] { return stop_; })) {
          break;
        }
        backoff *= 2.0;
      }
      try {
        error = target_.url.empty() ? RunCommand(target_, n) : PostWebhook(target_, n);
      } catch (const std::exception& e) {
        error = e.what();
      }
      if (error.empty()) break;
      spdlog::debug("notify {}: {} attempt {} failed: {}", target_.Describe(), ToString(n.event),
                    attempt + 1, error);
    }
    Record(n, error, std::min(attempt + 1, target_.retries + 1));
  }

  void Record(const Notification& n, const std::string& error, int attempts) {
    if (error.empty()) {
      spdlog::info("notify {}: {} delivered", target_.Describe(), ToString(n.event));
    } else {
      spdlog::warn("notify {}: {} dropped after {} attempt{}: {}", target_.Describe(),
                   ToString(n.event), attempts, attempts == 1 ? "" : "s", error);
    }
    std::lock_guard lock(mutex_);
    (error.empty() ? delivered_ : failed_) += 1;
    recent_.push_front({{"event", std::string(ToString(n.event))},
                        {"run", n.run == 0 ? Json(nullptr) : Json(n.run)},
                        {"time", UnixSeconds()},
                        {"ok", error.empty()},
                        {"attempts", attempts},
                        {"error", error.empty() ? Json(nullptr) : Json(error)}});
    if (recent_.size() > 20) recent_.pop_back();
  }

  const NotifyTarget target_;
  mutable std::mutex mutex_;
  std::condition_variable wake_;
  std::deque<Notification> queue_;
  std::deque<Json> recent_;
  std::int64_t queued_ = 0, delivered_ = 0, failed_ = 0, dropped_ = 0;
  bool busy_ = false;
  bool stop_ = false;
  std::thread thread_;
};

Notifier::Notifier(std::vector<NotifyTarget> targets) {
  CheckNotifyTargets(targets);
  for (NotifyTarget& t : targets) workers_.push_back(std::make_unique<Worker>(std::move(t)));
}

Notifier::~Notifier() = default;

void Notifier::Send(const Notification& n) {
  for (const auto& w : workers_) {
    if (w->target().Wants(n.event)) w->Send(n);
  }
}

bool Notifier::WantsFrame(NotifyEvent event) const {
  return std::any_of(workers_.begin(), workers_.end(), [&](const auto& w) {
    return w->target().attach_frame && w->target().Wants(event);
  });
}

Json Notifier::View() const {
  Json targets = Json::array();
  for (const auto& w : workers_) targets.push_back(w->View());
  Json events = Json::array();
  for (NotifyEvent e : AllNotifyEvents()) events.push_back(std::string(ToString(e)));
  return {{"notifiers", targets}, {"events", events}};
}

bool Notifier::WaitIdle(std::chrono::milliseconds timeout) const {
  const auto deadline = Clock::now() + timeout;
  for (;;) {
    bool idle = true;
    for (const auto& w : workers_) idle = idle && w->Idle();
    if (idle) return true;
    if (Clock::now() >= deadline) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
}

}  // namespace gs360
