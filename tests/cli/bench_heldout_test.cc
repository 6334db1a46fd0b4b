// `gs360 bench heldout`: the rigs it draws (cli/heldout_rigs.h) are valid rigs a lab could hand
// over, the same seed draws the same rig, and the benchmark runs them end to end and resumes.

#include <catch2/catch.hpp>

#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <map>
#include <set>
#include <sstream>
#include <string>

#include <nlohmann/json.hpp>

#include "cli/heldout_rigs.h"
#include "plan/plan.h"
#include "sim/lighting.h"
#include "sim/rig_model.h"
#include "sim/virtual_rig.h"
#include "tests/cli/run_gs360.h"

using namespace gs360;
using Catch::Contains;
namespace fs = std::filesystem;
using test::Gs360;

namespace {

fs::path FreshDir(const std::string& name) {
  const fs::path dir = fs::temp_directory_path() / (name + "-" + std::to_string(::getpid()));
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

std::string Slurp(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

}  // namespace

TEST_CASE("held-out rigs: every seed draws a rig the planner and the virtual rig accept",
          "[cli][heldout]") {
  const fs::path dir = FreshDir("gs360-heldout-rigs");
  std::set<std::string> families;
  int closed = 0, metres = 0;
  for (std::uint64_t seed = 1; seed <= 40; ++seed) {
    const cli::HeldoutRig rig = cli::DrawHeldoutRig(seed, dir);
    INFO("seed " << seed << ": " << rig.description);
    families.insert(rig.family);
    closed += rig.description.find("closed solid") != std::string::npos;
    metres += rig.description.find(" in m,") != std::string::npos;
    cli::SimArgs sim;
    std::uint64_t sim_seed = 0;
    const RunConfig config = cli::LoadHeldoutRig(rig, &sim, &sim_seed);
    CHECK(sim_seed == seed);
    CHECK(config.plan.machine_hours > 0.0);  // gs360d's default: sized in machine time
    CHECK(rig.mesh.empty() == config.rig.mesh_path.empty());
    // The planner's geometry and the simulator's rig, LEDs included, build from it.
    CHECK_NOTHROW(MakeRigGeometry(config.rig));
    VirtualRigOptions options;
    options.rig.rig = config.rig;
    options.rig.seed = seed;
    REQUIRE_NOTHROW(cli::ApplySimArgs(sim, &options));
    const SimRig sim_rig(options.rig);
    CHECK_NOTHROW(Lighting(options.camera.lighting, sim_rig.profile(), sim_rig.fin_options()));
    // The same seed, the same files.
    const std::string toml = Slurp(rig.config);
    const cli::HeldoutRig again = cli::DrawHeldoutRig(seed, dir / "again");
    CHECK(Slurp(again.config) == toml);
    if (!rig.mesh.empty()) CHECK(Slurp(again.mesh) == Slurp(rig.mesh));
  }
  // The distribution reaches every family, closed solids and files in metres.
  CHECK(families.size() == 7);
  CHECK(closed > 0);
  CHECK(metres > 0);
}

TEST_CASE("bench heldout runs each rig end to end, one row each, and resumes", "[cli][heldout]") {
  const fs::path dir = FreshDir("gs360-heldout-bench");
  const std::string args =
      "--json bench heldout --seeds 3,7 --machine-hours 0.03 --max-epochs 2 --out " +
      (dir / "rows.jsonl").string();
  const auto first = Gs360(args);
  INFO(first.out);
  REQUIRE(first.status == 0);
  CHECK_THAT(first.out, Contains("[1/2] rig-3") && Contains("[2/2] rig-7"));
  const auto json_start = first.out.find("{\n");
  REQUIRE(json_start != std::string::npos);
  const nlohmann::json out = nlohmann::json::parse(first.out.substr(json_start));
  REQUIRE(out["rows"].size() == 2);
  for (const nlohmann::json& row : out["rows"]) {
    INFO(row.dump());
    CHECK_FALSE(row.contains("error"));
    CHECK(row["planned"].get<int>() > 20);
    CHECK(row["captured"].get<int>() + row["failed"].get<int>() == row["planned"].get<int>());
    // Of the failed presses, those that left no usable mark even without noise (the
    // simulator's noise-free frames), and each one's mark.
    CHECK(row["failed_no_mark"].get<int>() >= 0);
    CHECK(row["failed_no_mark"].get<int>() <= row["failed"].get<int>());
    CHECK(static_cast<int>(row["failed_mark_dn"].size()) ==
          row["failed_by_reason"].value("impression", 0));
    // Sized to the machine time asked for.
    CHECK(row["machine_h"].get<double>() <= 0.03);
    CHECK(row["machine_h"].get<double>() > 0.02);
    CHECK(row["targets"].contains("peak indentation error"));
    CHECK(row["targets"]["camera position"]["value"].is_number());
    CHECK(row["rigid_targets"]["mean depth error"]["value"].is_number());
    CHECK(fs::exists(row["config"].get<std::string>()));
  }
  // Rig 3 is a dome: nothing on it is seen past 50 deg, which is no data, not a miss.
  CHECK(out["rows"][0]["targets"]["depth error seen > 50 deg"]["no_data"] == true);
  // Run again: every rig is in the file, nothing runs; the table has both.
  const auto again =
      Gs360("bench heldout --seeds 3,7 --markdown --out " + (dir / "rows.jsonl").string());
  INFO(again.out);
  REQUIRE(again.status == 0);
  CHECK_THAT(again.out, !Contains("[1/") && Contains("| rig-3 |") && Contains("| rig-7 |") &&
                            Contains("of 2 rigs meet every target") &&
                            Contains("of those that left a usable mark"));
  // A bad seed list is a usage error naming it.
  const auto bad = Gs360("bench heldout --seeds 4-x --out " + (dir / "bad.jsonl").string());
  CHECK(bad.status != 0);
  CHECK_THAT(bad.out, Contains("4-x"));
}
