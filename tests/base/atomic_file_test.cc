#include "base/atomic_file.h"

#include <unistd.h>

#include <catch2/catch.hpp>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <stdexcept>
#include <string>

namespace gs360 {
namespace {

namespace fs = std::filesystem;

fs::path FreshAtomicDir(const std::string& name) {
  const fs::path dir =
      fs::temp_directory_path() / ("gs360-atomic-" + name + "-" + std::to_string(::getpid()));
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

std::string ReadWhole(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

TEST_CASE("WriteFileAtomically writes and replaces a whole file and leaves no temporary",
          "[atomic_file]") {
  const fs::path dir = FreshAtomicDir("write");
  const fs::path path = dir / "status.json";
  WriteFileAtomically(path, "first");
  CHECK(ReadWhole(path) == "first");
  const std::string binary("a\0b\nc", 5);
  WriteFileAtomically(path, binary);
  CHECK(ReadWhole(path) == binary);
  WriteFileAtomically(path, "");
  CHECK(fs::file_size(path) == 0);
  CHECK_FALSE(fs::exists(dir / "status.json.tmp"));
  fs::remove_all(dir);
}

TEST_CASE("WriteFileAtomically fails naming the file and leaves what was there", "[atomic_file]") {
  const fs::path dir = FreshAtomicDir("fail");
  // The folder is a regular file: the temporary cannot be opened.
  const fs::path not_a_dir = dir / "plain";
  WriteFileAtomically(not_a_dir, "keep");
  CHECK_THROWS_WITH(
      WriteFileAtomically(not_a_dir / "x.json", "new"),
      Catch::Contains((not_a_dir / "x.json").string()) && Catch::Contains("cannot open"));
  // The target is a folder: the rename fails; the folder and its contents stay, the temporary
  // goes.
  const fs::path target = dir / "model.gs360model";
  fs::create_directories(target / "inside");
  CHECK_THROWS_WITH(WriteFileAtomically(target, "bytes"),
                    Catch::Contains(target.string()) && Catch::Contains("cannot rename"));
  CHECK(fs::is_directory(target / "inside"));
  CHECK_FALSE(fs::exists(dir / "model.gs360model.tmp"));
  CHECK(ReadWhole(not_a_dir) == "keep");
  fs::remove_all(dir);
}

}  // namespace
}  // namespace gs360
