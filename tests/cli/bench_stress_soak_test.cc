// `gs360 bench stress` and `gs360 bench soak` as a user runs them: the exit codes, the JSON, and
// a short soak whose faults the run survives with every probe captured exactly once.

#include <catch2/catch.hpp>

#include <unistd.h>

#include <filesystem>
#include <regex>
#include <string>

#include <nlohmann/json.hpp>

#include "tests/cli/run_gs360.h"

using Catch::Contains;
using gs360::test::Gs360;
namespace fs = std::filesystem;

namespace {

fs::path FreshSoakDir(const std::string& name) {
  const fs::path dir =
      fs::temp_directory_path() / ("gs360-" + name + "-" + std::to_string(::getpid()));
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

}  // namespace

TEST_CASE("bench stress prints JSON per case and refuses an unknown stage", "[cli][stress]") {
  const fs::path dir = FreshSoakDir("bench-stress");
  const auto r = Gs360("--json bench stress --only geometry --cache " + dir.string());
  INFO(r.out);
  REQUIRE(r.status == 0);
  const auto json = nlohmann::json::parse(r.out.substr(r.out.find('{')));
  CHECK(json["failed"] == 0);
  CHECK(json["cases"].size() == 4);
  for (const auto& c : json["cases"]) CHECK(c["stage"] == "geometry");
  const auto bad = Gs360("bench stress --only nosuch --cache " + dir.string());
  CHECK(bad.status == 2);
  CHECK_THAT(bad.out, Contains("--only"));
  fs::remove_all(dir);
}

TEST_CASE("bench soak survives a fault every few probes and captures every probe once",
          "[cli][soak]") {
  const fs::path dir = FreshSoakDir("bench-soak");
  const auto r = Gs360("bench soak --candidates 120 --fault-every 8 --seed 3 --dir " +
                       (dir / "soak").string());
  INFO(r.out);
  CHECK(r.status == 0);
  CHECK_THAT(r.out, Contains("every probe captured exactly once, at its press point"));
  std::smatch m;
  REQUIRE(std::regex_search(r.out, m, std::regex(R"((\d+) faults, (\d+) sessions)")));
  CHECK(std::stoi(m[1]) >= 4);
  CHECK(std::stoi(m[2]) >= 1);
  fs::remove_all(dir);
}
