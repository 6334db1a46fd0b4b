// `gs360 bench sweep` as a user runs it: a tiny grid on the virtual rig, the CSV and the plot it
// writes, a resumed sweep that runs only what is missing, and a foreign CSV refused.

#include <catch2/catch.hpp>

#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

#include "storage/run_database.h"
#include "tests/cli/run_gs360.h"

using namespace gs360;
using Catch::Contains;
namespace fs = std::filesystem;
using test::Gs360;

namespace {

std::vector<std::vector<std::string>> ReadCsv(const fs::path& path) {
  std::vector<std::vector<std::string>> rows;
  std::ifstream in(path);
  std::string line;
  while (std::getline(in, line)) {
    std::vector<std::string> cells;
    std::stringstream s(line);
    std::string cell;
    while (std::getline(s, cell, ',')) cells.push_back(cell);
    rows.push_back(cells);
  }
  return rows;
}

std::string Column(const std::vector<std::vector<std::string>>& csv, std::size_t row,
                   const std::string& name) {
  for (std::size_t c = 0; c < csv[0].size(); ++c) {
    if (csv[0][c] == name && c < csv[row].size()) return csv[row][c];
  }
  FAIL("no column " << name);
  return {};
}

}  // namespace

TEST_CASE("bench sweep writes a row per configuration and resumes without redoing any",
          "[cli][sweep]") {
  const fs::path dir = fs::temp_directory_path() / ("gs360-sweep-" + std::to_string(::getpid()));
  fs::remove_all(dir);
  fs::create_directories(dir);
  const fs::path csv = dir / "new" / "sweep.csv";  // its folder is made
  const std::string grid =
      "bench sweep --shapes cylinder --probes 40 --seeds 3 --depths 1 "
      "--epochs 2 --out " +
      csv.string();

  test::Gs360Result r = Gs360(grid + " --widths 8,16");
  INFO(r.out);
  REQUIRE(r.status == 0);
  auto rows = ReadCsv(csv);
  REQUIRE(rows.size() == 3);  // header and two rows
  for (std::size_t i = 1; i < rows.size(); ++i) {
    CHECK(rows[i].size() == rows[0].size());
    CHECK(Column(rows, i, "shape") == "cylinder");
    CHECK(std::stoi(Column(rows, i, "kept")) == 40);
    CHECK(std::stod(Column(rows, i, "machine_h")) > 0.0);
    CHECK(std::stod(Column(rows, i, "s_train")) > 0.0);
    const double mean = std::stod(Column(rows, i, "mean_mm"));
    CHECK(std::isfinite(mean));
    CHECK(mean > 0.0);
    // Two epochs on 40 probes cannot meet the targets, and the row says so.
    CHECK(Column(rows, i, "pass") == "0");
    CHECK(std::stod(Column(rows, i, "total_h")) > std::stod(Column(rows, i, "machine_h")));
  }
  CHECK(Column(rows, 1, "width") == "8");
  CHECK(Column(rows, 2, "width") == "16");
  // Both calibrations share one acquisition and its camera stages.
  CHECK(Column(rows, 1, "s_pose") == Column(rows, 2, "s_pose"));
  const cv::Mat plot = cv::imread((dir / "new" / "sweep.png").string());
  CHECK(plot.cols == 1280);
  CHECK(plot.rows == 560);
  CHECK_THAT(r.out, Contains("none of the configurations run meets every target"));

  // A wider grid later: only the new configuration runs, on the kept acquisition.
  r = Gs360("--json " + grid + " --widths 8,16,24");
  REQUIRE(r.status == 0);
  CHECK_THAT(r.out, Contains("2 in " + csv.string() + " already, 1 to run"));
  const auto json = nlohmann::json::parse(r.out.substr(r.out.find("\n{") + 1));
  CHECK(json["rows"].size() == 3);
  const auto again = ReadCsv(csv);
  REQUIRE(again.size() == 4);
  CHECK(again[1] == rows[1]);
  CHECK(again[2] == rows[2]);
  {
    RunDatabaseOptions ro;
    ro.read_only = true;
    RunDatabase db(dir / "new" / "sweep-runs" / "cylinder-p40-s3.db", ro);
    CHECK(db.ListRuns().size() == 1);
  }
  // A narrower grid runs nothing and still plots and advises on every row of the CSV.
  r = Gs360("--json " + grid + " --widths 8");
  REQUIRE(r.status == 0);
  CHECK(nlohmann::json::parse(r.out.substr(r.out.find("\n{") + 1))["rows"].size() == 3);
  r = Gs360(grid + " --widths 8,16,24 --dry-run");
  CHECK(r.status == 0);
  CHECK_THAT(r.out, Contains("3 in " + csv.string() + " already, 0 to run"));

  // Someone else's CSV is never appended to.
  std::ofstream(dir / "other.csv") << "a,b,c\n1,2,3\n";
  r = Gs360("bench sweep --probes 40 --out " + (dir / "other.csv").string());
  CHECK(r.status != 0);
  CHECK_THAT(r.out, Contains("other.csv: line 1 is not this sweep's header"));
  fs::remove_all(dir);
}
