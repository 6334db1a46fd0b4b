#pragma once
// What the notifier hears: the daemon's event hub (daemon/event_hub.h) read on a thread of its
// own and turned into notifications (daemon/notifier.h). A run's state changes, its session's
// end, machine alarms, convergence and calibrations become the NotifyEvents; everything else
// (progress, stages, log lines) is not sent.
//
// An alarm is followed by the interruption it causes: the interruption is then not sent again
// (it waits a moment for an alarm before it is sent).

#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>

#include "daemon/event_hub.h"
#include "daemon/notifier.h"

namespace gs360 {

// The notification event and its detail line for one hub event, if it is one to send. `alarmed`
// holds the runs whose alarm was sent and whose interruption is pending (updated).
struct FeedItem {
  NotifyEvent event;
  std::int64_t run = 0;
  std::string detail;
};
std::optional<FeedItem> TranslateHubEvent(const HubEvent& e, std::set<std::int64_t>& alarmed);

// "every accuracy target met (6)" or "missed: peak 0.054 mm (target <= 0.050 mm); ...", from a
// calibration's view (GET /api/v1/runs/ID/calibration); "calibration failed: ERROR" when it
// failed.
std::string CalibrationVerdict(const nlohmann::json& calibration);

class NotifyFeed {
 public:
  struct Sources {
    std::function<std::optional<nlohmann::json>(std::int64_t)> run;          // the run's view
    std::function<std::optional<nlohmann::json>(std::int64_t)> calibration;  // its calibration
    std::function<std::string()> dashboard_url;                              // "" until known
    // The run's latest frame as PNG (null: none yet); asked only when a target attaches frames.
    std::function<std::optional<std::vector<std::uint8_t>>(std::int64_t)> latest_frame;
  };
  // Starts reading `hub` from its current end. `unclean_runs`: runs a previous daemon left
  // running, each sent as kUncleanStart first.
  NotifyFeed(EventHub& hub, Notifier& notifier, Sources sources,
             std::vector<std::int64_t> unclean_runs);
  // Stops reading (the hub's Close() also ends it); queued notifications stay with the notifier.
  ~NotifyFeed();
  NotifyFeed(const NotifyFeed&) = delete;
  NotifyFeed& operator=(const NotifyFeed&) = delete;

  // Sends `event` about `run` (0: none) now, through the same path (POST /api/v1/notify/test).
  void Send(NotifyEvent event, std::int64_t run, const std::string& detail);
  // Waits until every event the hub held when called has been read, or `timeout` (shutdown: the
  // last run's end is sent before the hub closes).
  bool Drain(std::chrono::milliseconds timeout);

 private:
  void Loop(std::int64_t after, std::vector<std::int64_t> unclean_runs);
  // The run's latest frame, when a target wants one with `event`.
  std::shared_ptr<const std::vector<std::uint8_t>> Frame(NotifyEvent event, std::int64_t run) const;

  EventHub& hub_;
  Notifier& notifier_;
  Sources sources_;
  std::atomic<bool> stop_{false};
  std::atomic<std::int64_t> read_{0};    // the last hub event read
  std::atomic<std::size_t> pending_{0};  // interruptions waiting for their alarm
  std::atomic<bool> draining_{false};    // shutdown: nothing waits any more
  std::thread thread_;
};

}  // namespace gs360
