#include "daemon/notify_feed.h"

#include <spdlog/spdlog.h>

#include <map>
#include <utility>

#include "base/format.h"

namespace gs360 {
namespace {

using Json = nlohmann::json;
using Clock = std::chrono::steady_clock;

std::int64_t RunOf(const Json& data) {
  return data.is_object() && data.contains("run") && data["run"].is_number_integer()
             ? data["run"].get<std::int64_t>()
             : 0;
}

// A state change from the database carries "from"; the daemon's own "created" does not.
std::optional<NotifyEvent> FromState(const std::string& state, const std::string& from) {
  if (state == "created" && from.empty()) return NotifyEvent::kCreated;
  if (from.empty()) return std::nullopt;  // the daemon's echo of a change the database sends
  if (state == "running") return from == "created" ? NotifyEvent::kStarted : NotifyEvent::kResumed;
  if (state == "paused") return NotifyEvent::kPaused;
  if (state == "done") return NotifyEvent::kDone;
  if (state == "cancelled") return NotifyEvent::kCancelled;
  return std::nullopt;  // interrupted and failed: the session's end says why (run_end)
}

}  // namespace

std::optional<FeedItem> TranslateHubEvent(const HubEvent& e, std::set<std::int64_t>& alarmed) {
  const std::int64_t run = RunOf(e.data);
  const auto text = [&](const char* key) {
    return e.data.is_object() && e.data.contains(key) && e.data[key].is_string()
               ? e.data[key].get<std::string>()
               : std::string();
  };
  if (e.type == "state") {
    const auto event = FromState(text("state"), text("from"));
    // A new session: its alarm, if it has one, is news again.
    if (event == NotifyEvent::kStarted || event == NotifyEvent::kResumed) alarmed.erase(run);
    if (event) return FeedItem{*event, run, ""};
  } else if (e.type == "alarm") {
    // One alarm per session: the controller's later lines about it add nothing at 02:00.
    if (!alarmed.insert(run).second) return std::nullopt;
    return FeedItem{NotifyEvent::kAlarm, run, text("message")};
  } else if (e.type == "run_end") {
    const std::string outcome = text("outcome");
    if (outcome == "awaiting confirmation") {
      return FeedItem{NotifyEvent::kAwaitingConfirmation, run, text("message")};
    }
    // A session that failed leaves its run failed, or interrupted (resumable: an alarm, a camera
    // that stopped); the latter is an interruption, not sent again after its alarm.
    if (outcome == "failed" && text("state") == "failed") {
      return FeedItem{NotifyEvent::kFailed, run, text("message")};
    }
    if ((outcome == "stopped" || outcome == "failed") && alarmed.count(run) == 0) {
      return FeedItem{NotifyEvent::kInterrupted, run, text("message")};
    }
  } else if (e.type == "convergence") {
    if (e.data.value("converged", false)) {
      return FeedItem{NotifyEvent::kConverged, run, text("verdict")};
    }
  } else if (e.type == "calibration") {
    const std::string state = text("state");
    if (state == "done" || state == "failed") {
      return FeedItem{NotifyEvent::kCalibrationDone, run, state == "failed" ? text("error") : ""};
    }
  }
  return std::nullopt;
}

std::string CalibrationVerdict(const Json& calibration) {
  if (!calibration.is_object()) return "";
  if (calibration.value("state", "") == "failed") {
    return "calibration failed: " + calibration.value("error", std::string("unknown error"));
  }
  std::string missed;
  int met = 0;
  for (const Json& t : calibration.value("targets", Json::array())) {
    if (!t.is_object()) continue;
    if (t.value("pass", false)) {
      ++met;
      continue;
    }
    if (!t["value"].is_number()) continue;  // a band with no data
    missed += (missed.empty() ? "" : "; ") + t.value("name", std::string()) + " " +
              FormatFixed(t["value"].get<double>(), 3) + " " + t.value("unit", std::string()) +
              " (target <= " + FormatFixed(t.value("target", 0.0), 3) + ")";
  }
  if (!missed.empty()) return "accuracy targets missed: " + missed;
  return "every accuracy target met (" + std::to_string(met) + ")";
}

NotifyFeed::NotifyFeed(EventHub& hub, Notifier& notifier, Sources sources,
                       std::vector<std::int64_t> unclean_runs)
    : hub_(hub), notifier_(notifier), sources_(std::move(sources)) {
  const std::int64_t after = hub_.LastId();
  read_ = after;
  thread_ = std::thread(
      [this, after, runs = std::move(unclean_runs)]() mutable { Loop(after, std::move(runs)); });
}

NotifyFeed::~NotifyFeed() {
  stop_ = true;
  thread_.join();
}

void NotifyFeed::Send(NotifyEvent event, std::int64_t run, const std::string& detail) {
  if (notifier_.size() == 0) return;  // nobody to tell: no run view to read
  Json view = nullptr;
  std::string line = detail;
  try {
    if (run != 0 && sources_.run) {
      if (auto v = sources_.run(run)) view = std::move(*v);
    }
    if (event == NotifyEvent::kCalibrationDone && line.empty() && sources_.calibration) {
      if (auto c = sources_.calibration(run)) line = CalibrationVerdict(*c);
    }
  } catch (const std::exception& e) {
    // The run's view is the message's detail, not a reason to lose the notification.
    spdlog::debug("notify: run {}: {}", run, e.what());
  }
  if (view.is_null() && run != 0) view = Json{{"id", run}};
  Notification n =
      MakeNotification(event, view, line, sources_.dashboard_url ? sources_.dashboard_url() : "");
  n.frame_png = Frame(event, run);
  notifier_.Send(n);
}

std::shared_ptr<const std::vector<std::uint8_t>> NotifyFeed::Frame(NotifyEvent event,
                                                                   std::int64_t run) const {
  if (run == 0 || !sources_.latest_frame || !notifier_.WantsFrame(event)) return nullptr;
  try {
    if (auto png = sources_.latest_frame(run)) {
      return std::make_shared<const std::vector<std::uint8_t>>(std::move(*png));
    }
  } catch (const std::exception& e) {
    // A frame that cannot be read leaves the notification without one, nothing more.
    spdlog::debug("notify: run {}: no frame: {}", run, e.what());
  }
  return nullptr;
}

void NotifyFeed::Loop(std::int64_t after, std::vector<std::int64_t> unclean_runs) {
  for (std::int64_t run : unclean_runs) {
    Send(NotifyEvent::kUncleanStart, run,
         "gs360d started after a stop that left this run running (a crash or a power cut); "
         "the machine was not moved since");
  }
  std::set<std::int64_t> alarmed;
  // An interruption waits a moment for the alarm that may have caused it: the alarm reaches the
  // hub through the run log, up to a pump period after the session's end.
  std::map<std::int64_t, std::pair<Clock::time_point, FeedItem>> pending;
  constexpr auto kAlarmGrace = std::chrono::milliseconds(1500);
  while (!stop_ && !hub_.Closed()) {
    for (const HubEvent& e : hub_.WaitAfter(after, std::chrono::milliseconds(100))) {
      after = e.id;
      if (const auto item = TranslateHubEvent(e, alarmed)) {
        if (item->event == NotifyEvent::kInterrupted) {
          pending.insert_or_assign(item->run, std::pair{Clock::now() + kAlarmGrace, *item});
        } else {
          if (item->event == NotifyEvent::kAlarm) pending.erase(item->run);
          Send(item->event, item->run, item->detail);
        }
      }
    }
    for (auto it = pending.begin(); it != pending.end();) {
      if (draining_ || Clock::now() >= it->second.first) {
        Send(it->second.second.event, it->second.second.run, it->second.second.detail);
        it = pending.erase(it);
      } else {
        ++it;
      }
    }
    pending_ = pending.size();
    read_ = after;
  }
}

bool NotifyFeed::Drain(std::chrono::milliseconds timeout) {
  const std::int64_t target = hub_.LastId();
  draining_ = true;
  const auto deadline = Clock::now() + timeout;
  while (read_ < target || pending_ > 0) {
    if (Clock::now() >= deadline) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  return true;
}

}  // namespace gs360
