#pragma once
// The daemon's live event stream (GET /api/v1/events): progress, state changes, calibration
// stages, alarms, warnings. Publishers (the run's thread, the calibration's thread, the event
// pump) append; each event-stream client waits for events after the last id it has seen.
//
// Ids increase by one from 1. The hub keeps the last `capacity` events, so a client that
// reconnects with Last-Event-ID gets what it missed if it is recent enough (else it starts again
// from the oldest kept one). Thread-safe.

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <mutex>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

namespace gs360 {

struct HubEvent {
  std::int64_t id = 0;
  std::string type;  // progress, state, stage, calibration, alarm, warning, error, log
  nlohmann::json data;
};

class EventHub {
 public:
  explicit EventHub(std::size_t capacity = 4096);

  std::int64_t Publish(std::string type, nlohmann::json data);
  // Events with id > after (oldest first), waiting up to `timeout` for the first one. Empty on
  // timeout or once Close() was called.
  std::vector<HubEvent> WaitAfter(std::int64_t after, std::chrono::milliseconds timeout) const;
  std::int64_t LastId() const;
  // Wakes every waiter and makes further waits return at once (shutdown).
  void Close();
  bool Closed() const;
  // Called (on the publishing thread, after the event is stored) by every Publish and by Close;
  // nullptr: none. Must not publish.
  void SetListener(std::function<void()> listener);

 private:
  void Notify();
  mutable std::mutex mutex_;
  mutable std::condition_variable changed_;
  std::deque<HubEvent> events_;
  std::size_t capacity_;
  std::int64_t last_id_ = 0;
  bool closed_ = false;
  std::function<void()> listener_;  // under listener_mutex_
  mutable std::mutex listener_mutex_;
};

}  // namespace gs360
