#pragma once
// Notifications of a run's life to the people who left it running: HTTP(S) webhooks and
// commands, the `[[notify]]` tables of gs360d.toml (docs/daemon.md, "Notifications").
//
// Each target has a bounded queue and a thread of its own: Send() never blocks and never fails,
// so a slow, dead or failing receiver never delays a probe. A delivery that fails (no
// connection, a time-out, an HTTP status other than 2xx, a command that exits non-zero) is tried
// again after `backoff_s`, doubling, up to `retries` more times; then it is dropped, counted and
// logged. A notification that finds its queue full is dropped and counted at once. Logs and
// View() name a webhook by its scheme and host only: receivers keep their secrets in the path
// and the query (ntfy topics, Slack and Discord webhook tokens) and in user info.

#include <chrono>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include <nlohmann/json.hpp>

namespace gs360 {

// What happened. Their names (ToString) are the config's `events` and the payload's `event`.
enum class NotifyEvent {
  kCreated,
  kStarted,
  kPaused,
  kResumed,
  kAwaitingConfirmation,
  kInterrupted,
  kAlarm,
  kFailed,
  kCancelled,
  kDone,
  kConverged,
  kCalibrationDone,
  kUncleanStart,  // gs360d started after a stop that left a run running (a crash, a power cut)
  kTest,          // POST /api/v1/notify/test
};
std::string_view ToString(NotifyEvent event);
std::optional<NotifyEvent> NotifyEventFromString(std::string_view name);
// Every event, in declaration order.
const std::vector<NotifyEvent>& AllNotifyEvents();

// One `[[notify]]` table: exactly one of `url` and `command`.
struct NotifyTarget {
  std::string url;                   // http:// or https:// webhook
  std::vector<std::string> command;  // a program (searched on PATH) and its arguments; no shell
  // Webhook bodies: "json" (the notification as JSON), "ntfy" (text with Title, Priority and Tags
  // headers), "slack" ({"text"}), "discord" ({"content"}). Commands always get JSON on stdin.
  std::string format = "json";
  std::vector<std::string> events;  // names of NotifyEvent; empty: every event
  double timeout_s = 10.0;          // one attempt: connect and answer, or the command's run
  int retries = 3;                  // further attempts after a failed one
  double backoff_s = 2.0;           // before the first retry; doubles each time
  int queue_size = 64;              // notifications waiting; more are dropped
  // The run's latest camera frame (PNG) with each notification about a run: "frame_png_base64" in
  // the JSON body, an attachment for ntfy (the text then in a Message header) and Discord
  // (multipart), a file for a command (GS360_FRAME, "frame_path"; removed after the command).
  // Not with format "slack": its incoming webhooks take no files.
  bool attach_frame = false;
  // Throws std::invalid_argument naming the field ("notify.url ...") and the value.
  void Check() const;
  bool Wants(NotifyEvent event) const;
  // For logs and the API, without secrets: "https://ntfy.sh/... (ntfy)", "command apprise".
  std::string Describe() const;
  // The URL's scheme and host, "/..." for its path and query: "https://ntfy.sh/...".
  std::string RedactedUrl() const;
};

// Checks each target; a failure's message names its table: "notify[1].retries must be ...".
// Throws std::invalid_argument.
void CheckNotifyTargets(const std::vector<NotifyTarget>& targets);

// One notification, as a person reads it at 02:00 and as a script parses it.
struct Notification {
  NotifyEvent event = NotifyEvent::kTest;
  std::int64_t run = 0;  // 0: not about one run
  std::string run_name;
  std::string title;    // "gs360 run 3 (finger-07): alarm"
  std::string message;  // what happened, progress and ETA, the last error, what to do
  std::string action;   // the command that answers, if one does ("gs360 run resume 3 ...")
  std::string dashboard_url;
  nlohmann::json progress = nullptr;  // probes_done, probes_total, probes_failed, eta_s
  std::string last_error;
  double time = 0.0;  // Unix seconds
  // The run's latest frame as PNG, for the targets with attach_frame (null: none). Shared: one
  // encoding for every target; ToJson() leaves it out.
  std::shared_ptr<const std::vector<std::uint8_t>> frame_png;
  nlohmann::json ToJson() const;
};

// The notification for `event` about the run whose API view (GET /api/v1/runs/ID) is `run`
// (null: none), with `detail` (the alarm's text, the calibration's verdict) and the dashboard's
// base URL.
Notification MakeNotification(NotifyEvent event, const nlohmann::json& run,
                              const std::string& detail, const std::string& dashboard_url);

// A webhook's request for a notification in `format` (NotifyTarget::format).
struct WebhookRequest {
  std::string content_type;
  std::string body;
  std::vector<std::pair<std::string, std::string>> headers;
};
// With `attach_frame` and a frame in `n`, the frame goes with it (NotifyTarget::attach_frame).
WebhookRequest FormatWebhook(const Notification& n, std::string_view format,
                             bool attach_frame = false);

class Notifier {
 public:
  // Checks every target (throws std::invalid_argument naming "notify[i].field") and starts one
  // thread per target.
  explicit Notifier(std::vector<NotifyTarget> targets);
  // Stops the threads: a delivery under way ends within its time-out; what is still queued is
  // dropped and counted.
  ~Notifier();
  Notifier(const Notifier&) = delete;
  Notifier& operator=(const Notifier&) = delete;

  // Queues `n` for every target that wants its event (with its frame only for those that
  // attach one). Never blocks.
  void Send(const Notification& n);
  // Whether a target that wants `event` attaches the frame: only then is one encoded.
  bool WantsFrame(NotifyEvent event) const;
  // The targets (described, with their events and counts: queued, delivered, failed, dropped)
  // and the last deliveries and failures, newest first.
  nlohmann::json View() const;
  std::size_t size() const { return workers_.size(); }
  // Waits until every queue is empty and no delivery is under way, or `timeout` (tests, shutdown).
  bool WaitIdle(std::chrono::milliseconds timeout) const;

 private:
  class Worker;
  std::vector<std::unique_ptr<Worker>> workers_;
};

}  // namespace gs360
