#include "daemon/event_hub.h"

namespace gs360 {

EventHub::EventHub(std::size_t capacity) : capacity_(capacity < 16 ? 16 : capacity) {}

std::int64_t EventHub::Publish(std::string type, nlohmann::json data) {
  std::int64_t id = 0;
  {
    std::lock_guard lock(mutex_);
    id = ++last_id_;
    events_.push_back({id, std::move(type), std::move(data)});
    while (events_.size() > capacity_) events_.pop_front();
  }
  changed_.notify_all();
  Notify();
  return id;
}

std::vector<HubEvent> EventHub::WaitAfter(std::int64_t after,
                                          std::chrono::milliseconds timeout) const {
  std::unique_lock lock(mutex_);
  changed_.wait_for(lock, timeout, [&] { return closed_ || last_id_ > after; });
  std::vector<HubEvent> out;
  if (closed_) return out;
  for (const HubEvent& e : events_) {
    if (e.id > after) out.push_back(e);
  }
  return out;
}

std::int64_t EventHub::LastId() const {
  std::lock_guard lock(mutex_);
  return last_id_;
}

void EventHub::Close() {
  {
    std::lock_guard lock(mutex_);
    closed_ = true;
  }
  changed_.notify_all();
  Notify();
}

void EventHub::SetListener(std::function<void()> listener) {
  std::lock_guard lock(listener_mutex_);
  listener_ = std::move(listener);
}

void EventHub::Notify() {
  std::lock_guard lock(listener_mutex_);
  if (listener_) listener_();
}

bool EventHub::Closed() const {
  std::lock_guard lock(mutex_);
  return closed_;
}

}  // namespace gs360
