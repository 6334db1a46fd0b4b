// Bad input: files that are not (our) databases, newer schemas, read-only locations, a full
// disk, corrupt blobs. Each must be a clear error naming the file, and lose nothing committed.

#include <catch2/catch.hpp>

#include <sys/wait.h>
#include <unistd.h>

#include <fstream>
#include <iterator>
#include <sstream>

#include "storage/run_database.h"
#include "storage/schema.h"
#include "tests/storage/storage_test_util.h"

namespace gs360 {
namespace {

namespace fs = std::filesystem;

std::string ReadFileBytes(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

// Opens `path` and returns the StorageError it raises (fails the test if none).
StorageError OpenError(const fs::path& path, RunDatabaseOptions options = {}) {
  try {
    RunDatabase db(path, std::move(options));
  } catch (const StorageError& e) {
    return e;
  }
  FAIL("opening " << path << " did not throw StorageError");
  throw std::logic_error("unreachable");
}

std::vector<ProbePlanEntry> Plan(int n) {
  std::vector<ProbePlanEntry> plan(n);
  for (int i = 0; i < n; ++i) plan[i].press_machine = {1.0 * i, 2.0, -3.0};
  return plan;
}

CaptureReport ReportAt(double t) {
  return {{1, 2, 3}, t, t + 0.1};
}

TEST_CASE("a file that is not SQLite is refused and left untouched", "[storage][errors]") {
  test::TempDir dir;
  const fs::path path = dir / "notes.gs360db";
  {
    std::ofstream out(path, std::ios::binary);
    for (int i = 0; i < 200; ++i) out << "line " << i << ": this is a text file, not a database\n";
  }
  const std::string before = ReadFileBytes(path);
  const StorageError e = OpenError(path);
  CHECK(e.code() == StorageErrc::kNotADatabase);
  CHECK_THAT(e.what(), Catch::Contains(path.string()) && Catch::Contains("not an SQLite"));
  CHECK(e.database() == path);
  CHECK(ReadFileBytes(path) == before);
  CHECK_FALSE(fs::exists(dir / "notes.gs360db-wal"));
  CHECK(OpenError(path, {.read_only = true}).code() == StorageErrc::kNotADatabase);
}

TEST_CASE("another application's SQLite database is refused and left untouched",
          "[storage][errors]") {
  test::TempDir dir;
  const fs::path path = dir / "photos.db";
  {
    test::RawDb raw(path);
    raw.Exec("CREATE TABLE photos (id INTEGER PRIMARY KEY, name TEXT)");
    raw.Exec("INSERT INTO photos (name) VALUES ('cat.jpg')");
  }
  const StorageError e = OpenError(path);
  CHECK(e.code() == StorageErrc::kForeignDatabase);
  CHECK_THAT(e.what(), Catch::Contains(path.string()) && Catch::Contains("not a gs360"));
  test::RawDb raw(path);
  CHECK(raw.Text("SELECT name FROM photos") == "cat.jpg");
  CHECK(raw.Int("PRAGMA user_version") == 0);
  CHECK(raw.Int("SELECT count(*) FROM sqlite_master WHERE name = 'runs'") == 0);
  CHECK(raw.Text("PRAGMA journal_mode") == "delete");

  // Same with an explicit foreign application_id.
  const fs::path other = dir / "other.db";
  test::RawDb(other).Exec("PRAGMA application_id = 1234");
  CHECK(OpenError(other).code() == StorageErrc::kForeignDatabase);
}

TEST_CASE("a database from a newer gs360 is refused clearly and not modified",
          "[storage][errors]") {
  test::TempDir dir;
  const fs::path path = dir / "rig.gs360db";
  std::int64_t run = 0;
  {
    RunDatabase db(path);
    run = db.CreateRun(R"({"k": 1})", "h");
  }
  const int newer = kSchemaVersion + 3;
  test::RawDb(path).Exec("PRAGMA user_version = " + std::to_string(newer));
  for (const bool read_only : {false, true}) {
    CAPTURE(read_only);
    const StorageError e = OpenError(path, {.read_only = read_only});
    CHECK(e.code() == StorageErrc::kNewerSchema);
    CHECK_THAT(e.what(), Catch::Contains(path.string()) &&
                             Catch::Contains("version " + std::to_string(newer)) &&
                             Catch::Contains("up to version " + std::to_string(kSchemaVersion)));
  }
  test::RawDb raw(path);
  CHECK(raw.Int("PRAGMA user_version") == newer);
  CHECK(raw.Text("SELECT config_json FROM runs WHERE id = " + std::to_string(run)) ==
        R"({"k": 1})");
}

TEST_CASE("an older database is migrated forward on open, keeping its data", "[storage][errors]") {
  test::TempDir dir;
  const fs::path path = dir / "v1.gs360db";
  CreateDatabaseAtVersion(path, 1);
  {
    test::RawDb raw(path);
    REQUIRE(raw.Int("PRAGMA user_version") == 1);
    REQUIRE(raw.Int("SELECT count(*) FROM sqlite_master WHERE name = 'artifacts'") == 0);
    raw.Exec(
        "INSERT INTO runs (id, config_json, mesh_hash, created_at, updated_at) "
        "VALUES (7, '{\"old\": true}', 'm', 1.0, 2.0)");
    raw.Exec(
        "INSERT INTO probes (run_id, plan_index, point_x, point_y, point_z, normal_x, normal_y, "
        "normal_z, approach_x, approach_y, approach_z, press_x, press_y, press_z, retract_x, "
        "retract_y, retract_z) VALUES (7, 0, 1,2,3, 0,0,1, 4,5,6, 7,8,9, 10,11,12)");
  }
  // A read-only open cannot migrate and says so.
  const StorageError e = OpenError(path, {.read_only = true});
  CHECK(e.code() == StorageErrc::kReadOnly);
  CHECK_THAT(e.what(), Catch::Contains("migrat"));

  RunDatabase db(path);
  CHECK(db.schema_version() == kSchemaVersion);
  CHECK(db.GetRun(7)->config_json == R"({"old": true})");
  CHECK(db.GetProbeByIndex(7, 0)->plan.press_machine == Eigen::Vector3d(7, 8, 9));
  db.PutArtifact(7, "pose", "abc", std::vector<std::uint8_t>{1, 2});
  CHECK(db.GetArtifact(7, "pose", "abc"));
  CHECK(test::RawDb(path).Int("PRAGMA user_version") == kSchemaVersion);

  CHECK_THROWS_AS(CreateDatabaseAtVersion(dir / "x.db", 0), std::invalid_argument);
  CHECK_THROWS_AS(CreateDatabaseAtVersion(dir / "x.db", kSchemaVersion + 1), std::invalid_argument);
}

TEST_CASE("missing files and directories are clear errors", "[storage][errors]") {
  test::TempDir dir;
  const fs::path missing_dir = dir / "no" / "such" / "rig.gs360db";
  StorageError e = OpenError(missing_dir);
  CHECK(e.code() == StorageErrc::kCannotOpen);
  CHECK_THAT(e.what(), Catch::Contains(missing_dir.string()) && Catch::Contains("does not exist"));
  e = OpenError(dir / "absent.gs360db", {.read_only = true});
  CHECK(e.code() == StorageErrc::kCannotOpen);
  CHECK_FALSE(fs::exists(dir / "absent.gs360db"));
  e = OpenError(dir / "absent.gs360db", {.create = false});
  CHECK(e.code() == StorageErrc::kCannotOpen);
  CHECK_FALSE(fs::exists(dir / "absent.gs360db"));
  e = OpenError(dir.path());
  CHECK(e.code() == StorageErrc::kCannotOpen);
}

TEST_CASE("a read-only instance refuses writes and names the file", "[storage][errors]") {
  test::TempDir dir;
  const fs::path path = dir / "rig.gs360db";
  RunDatabase writer(path);
  const std::int64_t run = writer.CreateRun("{}", "h");
  RunDatabase reader(path, {.read_only = true});
  CHECK(reader.GetRun(run));
  try {
    reader.CreateRun("{}", "h");
    FAIL("expected StorageError");
  } catch (const StorageError& e) {
    CHECK(e.code() == StorageErrc::kReadOnly);
    CHECK_THAT(e.what(), Catch::Contains(path.string()));
  }
  CHECK(writer.ListRuns().size() == 1);
}

// Runs `body` in a child process without root privileges (as nobody when the test runs as root,
// since root ignores file permissions) and returns what it printed.
template <typename Body>
std::string RunUnprivileged(Body body) {
  int fds[2];
  REQUIRE(::pipe(fds) == 0);
  const pid_t pid = ::fork();
  REQUIRE(pid >= 0);
  if (pid == 0) {
    ::close(fds[0]);
    std::string out;
    if (::geteuid() == 0 && (::setgid(65534) != 0 || ::setuid(65534) != 0)) {
      out = "cannot drop root privileges";
    } else {
      try {
        out = body();
      } catch (const std::exception& e) {
        out += std::string("unexpected exception: ") + e.what();
      }
    }
    const ssize_t n = ::write(fds[1], out.data(), out.size());
    ::_exit(n == static_cast<ssize_t>(out.size()) ? 0 : 1);
  }
  ::close(fds[1]);
  std::string out;
  char buf[4096];
  ssize_t n;
  while ((n = ::read(fds[0], buf, sizeof buf)) > 0) out.append(buf, static_cast<std::size_t>(n));
  ::close(fds[0]);
  int status = 0;
  ::waitpid(pid, &status, 0);
  CHECK(WIFEXITED(status));
  return out;
}

std::string Outcome(const std::function<void()>& f) {
  try {
    f();
    return "ok";
  } catch (const StorageError& e) {
    return std::string(ToString(e.code())) + "|" + e.what();
  }
}

TEST_CASE("a read-only location is a clear error and committed data stays readable",
          "[storage][errors]") {
  test::TempDir dir;
  const fs::path ro_dir = dir / "ro";
  fs::create_directories(ro_dir);
  const fs::path path = ro_dir / "rig.gs360db";
  const cv::Mat image = test::NoisyFrame(4, 64, 48);
  std::int64_t run = 0, frame = 0;
  {
    RunDatabase db(path);
    run = db.CreateRun("{}", "h");
    const std::vector<std::int64_t> ids = db.InsertPlan(run, Plan(3));
    frame = db.CommitCapture(ids[0], image, ReportAt(1));
  }  // closing checkpoints the WAL into the file and removes -wal / -shm
  REQUIRE_FALSE(fs::exists(ro_dir / "rig.gs360db-wal"));
  fs::permissions(path, fs::perms::owner_read | fs::perms::group_read | fs::perms::others_read);
  fs::permissions(ro_dir, fs::perms::owner_read | fs::perms::owner_exec | fs::perms::group_read |
                              fs::perms::group_exec | fs::perms::others_read |
                              fs::perms::others_exec);

  const std::string report = RunUnprivileged([&] {
    std::ostringstream out;
    out << "new=" << Outcome([&] { RunDatabase db(ro_dir / "new.gs360db"); }) << "\n";
    out << "write=" << Outcome([&] { RunDatabase db(path); }) << "\n";
    out << "read=" << Outcome([&] {
      RunDatabase db(path, {.read_only = true});
      const RunStatus st = db.GetRunStatus(run);
      if (st.probes.captured != 1 || st.probes.total != 3) throw std::runtime_error("counts");
      if (!test::SameImage(db.LoadFrame(frame), image)) throw std::runtime_error("frame");
    }) << "\n";
    return out.str();
  });
  INFO(report);
  CHECK_THAT(report, Catch::Contains("new=read-only|" + (ro_dir / "new.gs360db").string()));
  CHECK_THAT(report, Catch::Contains("is not writable"));
  CHECK_THAT(report, Catch::Contains("write=read-only|" + path.string()));
  CHECK_THAT(report, Catch::Contains("read=ok"));
  CHECK_FALSE(fs::exists(ro_dir / "new.gs360db"));

  // Once the location is writable again the run continues where it was.
  fs::permissions(ro_dir, fs::perms::owner_all, fs::perm_options::add);
  fs::permissions(path, fs::perms::owner_write, fs::perm_options::add);
  RunDatabase db(path);
  CHECK(db.CountProbes(run).captured == 1);
  CHECK(db.NextPendingProbe(run)->plan_index == 1);
}

TEST_CASE("a full disk rolls back the failing commit and keeps earlier ones", "[storage][errors]") {
  test::TempDir dir;
  const fs::path path = dir / "rig.gs360db";
  RunDatabaseOptions options;
  options.max_page_count = 200;  // 3.2 MB with 16 KiB pages
  RunDatabase db(path, options);
  const std::int64_t run = db.CreateRun("{}", "h");
  const std::vector<std::int64_t> ids = db.InsertPlan(run, Plan(200));

  std::vector<cv::Mat> committed;
  std::optional<StorageError> error;
  for (std::size_t i = 0; i < ids.size() && !error; ++i) {
    const cv::Mat image = test::NoisyFrame(static_cast<int>(i), 320, 240);  // ~200 kB as PNG
    try {
      db.CommitCapture(ids[i], image, ReportAt(static_cast<double>(i)));
      committed.push_back(image);
    } catch (const StorageError& e) {
      error = e;
    }
  }
  REQUIRE(error);
  CHECK(error->code() == StorageErrc::kDiskFull);
  CHECK_THAT(error->what(), Catch::Contains(path.string()) &&
                                Catch::Contains("max_page_count=200") &&
                                Catch::Contains("rolled back"));
  const std::size_t n = committed.size();
  REQUIRE(n >= 3);
  REQUIRE(n < ids.size());

  // The failed probe is untouched, earlier commits are intact, and the instance still reads.
  const ProbeRecord failed = *db.GetProbe(ids[n]);
  CHECK(failed.state == ProbeState::kPlanned);
  CHECK(failed.attempts == 0);
  const RunStatus st = db.GetRunStatus(run);
  CHECK(st.probes.captured == static_cast<std::int64_t>(n));
  CHECK(db.ListFrames(run, FrameKind::kPress).size() == n);
  CHECK(db.IntegrityCheck().empty());
  const std::vector<CapturedProbe> captured = db.ListCapturedProbes(run);
  REQUIRE(captured.size() == n);
  for (std::size_t i = 0; i < n; ++i) {
    CHECK(test::SameImage(db.LoadFrame(captured[i].frame_id), committed[i]));
  }

  // With room again (a new connection without the cap), the same probe commits.
  RunDatabase roomy(path);
  roomy.CommitCapture(ids[n], test::NoisyFrame(999, 320, 240), ReportAt(1000));
  CHECK(roomy.CountProbes(run).captured == static_cast<std::int64_t>(n + 1));
  CHECK(test::RawDb(path).Text("PRAGMA integrity_check") == "ok");
}

TEST_CASE("a corrupt frame blob is an error naming the file, frame and probe",
          "[storage][errors]") {
  test::TempDir dir;
  const fs::path path = dir / "rig.gs360db";
  RunDatabase db(path);
  const std::int64_t run = db.CreateRun("{}", "h");
  const std::vector<std::int64_t> ids = db.InsertPlan(run, Plan(3));
  const cv::Mat good = test::NoisyFrame(1, 64, 48);
  const std::int64_t f0 = db.CommitCapture(ids[0], test::NoisyFrame(0, 64, 48), ReportAt(1));
  const std::int64_t f1 = db.CommitCapture(ids[1], good, ReportAt(2));
  const std::int64_t f2 = db.CommitCapture(ids[2], test::NoisyFrame(2, 64, 48), ReportAt(3));

  test::RawDb raw(path);
  const std::string where = " WHERE id = " + std::to_string(f0);
  std::vector<std::uint8_t> blob = raw.Blob("SELECT png FROM frames" + where);
  blob[blob.size() / 2] ^= 0x40;
  raw.ExecWithBlob("UPDATE frames SET png = ?1" + where, blob);

  for (const bool png_only : {false, true}) {
    try {
      if (png_only) {
        db.LoadFramePng(f0);
      } else {
        db.LoadFrame(f0);
      }
      FAIL("expected StorageError");
    } catch (const StorageError& e) {
      CHECK(e.code() == StorageErrc::kCorruptBlob);
      CHECK_THAT(e.what(), Catch::Contains(path.string()) &&
                               Catch::Contains("frame " + std::to_string(f0)) &&
                               Catch::Contains("probe " + std::to_string(ids[0])) &&
                               Catch::Contains("checksum mismatch"));
    }
  }
  // A blob stored corrupt (checksum of the bad bytes) fails to decode: also named.
  std::vector<std::uint8_t> junk(5000, 0x33);
  raw.ExecWithBlob("UPDATE frames SET png = ?1, size = 5000, checksum = '" + BlobChecksum(junk) +
                       "' WHERE id = " + std::to_string(f2),
                   junk);
  try {
    db.LoadFrame(f2);
    FAIL("expected StorageError");
  } catch (const StorageError& e) {
    CHECK(e.code() == StorageErrc::kCorruptBlob);
    CHECK_THAT(e.what(), Catch::Contains("frame " + std::to_string(f2)) &&
                             Catch::Contains("does not decode"));
  }
  // Nothing else is lost: the good frame loads and the probes are still listed.
  CHECK(test::SameImage(db.LoadFrame(f1), good));
  CHECK(db.ListCapturedProbes(run).size() == 3);
  try {
    db.LoadFrame(f2 + 10);
    FAIL("expected StorageError");
  } catch (const StorageError& e) {
    CHECK(e.code() == StorageErrc::kNotFound);
  }

  // Artifacts and models are verified the same way.
  db.PutArtifact(run, "render", "k", std::vector<std::uint8_t>(100, 7));
  db.PutModel("m", "1", std::vector<std::uint8_t>(100, 8));
  raw.Exec("UPDATE artifacts SET blob = zeroblob(100)");
  raw.Exec("UPDATE models SET blob = zeroblob(100)");
  try {
    db.GetArtifact(run, "render", "k");
    FAIL("expected StorageError");
  } catch (const StorageError& e) {
    CHECK(e.code() == StorageErrc::kCorruptBlob);
    CHECK_THAT(e.what(), Catch::Contains(path.string()) && Catch::Contains("render"));
  }
  CHECK_THROWS_AS(db.GetModel("m", "1"), StorageError);
}

}  // namespace
}  // namespace gs360
