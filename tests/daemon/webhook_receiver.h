#pragma once
// A webhook receiver for the notification tests: a real HTTP server on a free loopback port.

#include <atomic>
#include <chrono>
#include <map>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include <httplib.h>
#include <nlohmann/json.hpp>

namespace gs360::test {

// A webhook receiver on a free loopback port: records each request; `status` is what it
// answers, `delay` how long it takes to.
class Receiver {
 public:
  Receiver() {
    server_.Post(".*", [this](const httplib::Request& req, httplib::Response& res) {
      {
        std::lock_guard lock(mutex_);
        bodies_.push_back(req.body);
        paths_.push_back(req.path);
        titles_.push_back(req.get_header_value("Title"));
        headers_.push_back(req.headers);
        std::map<std::string, std::string> parts;
        for (const auto& [name, file] : req.files) parts[name] = file.content;
        parts_.push_back(std::move(parts));
      }
      if (delay_ms > 0) std::this_thread::sleep_for(std::chrono::milliseconds(delay_ms.load()));
      res.status = status.load();
      res.set_content("ok", "text/plain");
    });
    port_ = server_.bind_to_any_port("127.0.0.1");
    thread_ = std::thread([this] { server_.listen_after_bind(); });
    while (!server_.is_running()) std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  ~Receiver() {
    server_.stop();
    thread_.join();
  }
  std::string Url(const std::string& path) const {
    return "http://127.0.0.1:" + std::to_string(port_) + path;
  }
  std::size_t Count() const {
    std::lock_guard lock(mutex_);
    return bodies_.size();
  }
  std::string Body(std::size_t i) const {
    std::lock_guard lock(mutex_);
    return bodies_.at(i);
  }
  std::string Path(std::size_t i) const {
    std::lock_guard lock(mutex_);
    return paths_.at(i);
  }
  // The "event" of each JSON body received, in order.
  std::vector<std::string> Events() const {
    std::lock_guard lock(mutex_);
    std::vector<std::string> events;
    for (const std::string& b : bodies_) {
      const auto j = nlohmann::json::parse(b, nullptr, false);
      events.push_back(j.is_object() ? j.value("event", "?") : "?");
    }
    return events;
  }
  std::string Title(std::size_t i) const {
    std::lock_guard lock(mutex_);
    return titles_.at(i);
  }
  // Request i's header `name` ("" if it had none).
  std::string Header(std::size_t i, const std::string& name) const {
    std::lock_guard lock(mutex_);
    const auto& h = headers_.at(i);
    const auto it = h.find(name);
    return it == h.end() ? std::string() : it->second;
  }
  // The part `name` of request i's multipart/form-data body ("" if none).
  std::string Part(std::size_t i, const std::string& name) const {
    std::lock_guard lock(mutex_);
    const auto& p = parts_.at(i);
    const auto it = p.find(name);
    return it == p.end() ? std::string() : it->second;
  }
  std::atomic<int> status{200};
  std::atomic<int> delay_ms{0};

 private:
  httplib::Server server_;
  int port_ = 0;
  std::thread thread_;
  mutable std::mutex mutex_;
  std::vector<std::string> bodies_, paths_, titles_;
  std::vector<httplib::Headers> headers_;
  std::vector<std::map<std::string, std::string>> parts_;
};

}  // namespace gs360::test
