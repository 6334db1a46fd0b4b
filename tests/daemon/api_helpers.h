#pragma once
// Small helpers for tests that talk to gs360d's HTTP API with a real client.

#include <chrono>
#include <string>

#include <catch2/catch.hpp>
#include <nlohmann/json.hpp>

#include "daemon_fixture.h"
#include "tests/wait.h"

namespace gs360::test {

inline const httplib::Headers kNone;

inline nlohmann::json Body(const httplib::Result& r) {
  REQUIRE(r);
  return nlohmann::json::parse(r->body, nullptr, false);
}

inline httplib::Result PostJson(httplib::Client& c, const std::string& path,
                                const nlohmann::json& body,
                                const httplib::Headers& headers = kNone) {
  return c.Post(path.c_str(), headers, body.dump(), "application/json");
}

// Polls GET /runs/ID until `pred` holds (or `limit` passes); returns the last view.
template <typename Pred>
nlohmann::json WaitRun(httplib::Client& c, std::int64_t id, Pred pred,
                       std::chrono::seconds limit = std::chrono::seconds(60)) {
  nlohmann::json run;
  const auto done = [&] {
    run = Body(c.Get(("/api/v1/runs/" + std::to_string(id)).c_str()));
    return pred(run);
  };
  if (!WaitUntil(done, limit)) {
    FAIL("timed out waiting; last view " << run.dump());
  }
  return run;
}

}  // namespace gs360::test
