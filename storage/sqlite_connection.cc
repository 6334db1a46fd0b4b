#include "storage/sqlite_connection.h"

#include <sqlite3.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstring>
#include <utility>

#include "storage/schema.h"

namespace gs360::storage_internal {
namespace {

namespace fs = std::filesystem;

double SystemNow() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

StorageErrc CodeFor(int rc) {
  switch (rc & 0xff) {
    case SQLITE_NOTADB:
      return StorageErrc::kNotADatabase;
    case SQLITE_READONLY:
    case SQLITE_PERM:
      return StorageErrc::kReadOnly;
    case SQLITE_FULL:
      return StorageErrc::kDiskFull;
    case SQLITE_BUSY:
    case SQLITE_LOCKED:
      return StorageErrc::kBusy;
    case SQLITE_CORRUPT:
      return StorageErrc::kCorruptDatabase;
    case SQLITE_CANTOPEN:
      return StorageErrc::kCannotOpen;
    case SQLITE_CONSTRAINT:
      return StorageErrc::kConflict;
    default:
      return StorageErrc::kIo;
  }
}

// "file:" URI for a path, percent-encoding what URIs reserve.
std::string FileUri(const fs::path& path, std::string_view query) {
  std::string out = "file:";
  for (unsigned char ch : fs::absolute(path).string()) {
    if (ch == '%' || ch == '?' || ch == '#' || ch < 0x20 || ch >= 0x7f) {
      static constexpr char kHex[] = "0123456789ABCDEF";
      out += '%';
      out += kHex[ch >> 4];
      out += kHex[ch & 0xf];
    } else {
      out += static_cast<char>(ch);
    }
  }
  out += '?';
  out += query;
  return out;
}

// Whether the process may write `p`; if not, `why` gets strerror(errno).
bool Writable(const fs::path& p, std::string* why = nullptr) {
  if (::access(p.c_str(), W_OK) == 0) return true;
  const int err = errno;
  if (why) *why = std::strerror(err);
  return false;
}

fs::path ParentDir(const fs::path& path) {
  const fs::path dir = path.parent_path();
  return dir.empty() ? fs::path(".") : dir;
}

}  // namespace

Stmt::~Stmt() {
  sqlite3_reset(s_);
  sqlite3_clear_bindings(s_);
}

Stmt& Stmt::Int(int i, std::int64_t v) {
  return Check(sqlite3_bind_int64(s_, i, v));
}
Stmt& Stmt::Real(int i, double v) {
  return Check(sqlite3_bind_double(s_, i, v));
}
Stmt& Stmt::OptReal(int i, std::optional<double> v) {
  return v ? Real(i, *v) : Check(sqlite3_bind_null(s_, i));
}
Stmt& Stmt::OptInt(int i, std::optional<std::int64_t> v) {
  return v ? Int(i, *v) : Check(sqlite3_bind_null(s_, i));
}
Stmt& Stmt::Text(int i, std::string_view v) {
  return Check(sqlite3_bind_text64(s_, i, v.data(), v.size(), SQLITE_TRANSIENT, SQLITE_UTF8));
}
Stmt& Stmt::OptText(int i, std::string_view v) {
  return v.empty() ? Check(sqlite3_bind_null(s_, i)) : Text(i, v);
}
Stmt& Stmt::Blob(int i, std::span<const std::uint8_t> v) {
  if (v.empty()) return Check(sqlite3_bind_zeroblob(s_, i, 0));
  return Check(sqlite3_bind_blob64(s_, i, v.data(), v.size(), SQLITE_STATIC));
}
Stmt& Stmt::Vec(int first, const Eigen::Vector3d& v) {
  return Real(first, v.x()).Real(first + 1, v.y()).Real(first + 2, v.z());
}

void Stmt::Run() {
  while (Step()) {
  }
}

bool Stmt::IsNull(int c) const {
  return sqlite3_column_type(s_, c) == SQLITE_NULL;
}
std::int64_t Stmt::GetInt(int c) const {
  return sqlite3_column_int64(s_, c);
}
double Stmt::GetReal(int c) const {
  return sqlite3_column_double(s_, c);
}
std::optional<double> Stmt::GetOptReal(int c) const {
  return IsNull(c) ? std::nullopt : std::optional<double>(GetReal(c));
}
std::optional<std::int64_t> Stmt::GetOptInt(int c) const {
  return IsNull(c) ? std::nullopt : std::optional<std::int64_t>(GetInt(c));
}
std::string Stmt::GetText(int c) const {
  const auto* p = reinterpret_cast<const char*>(sqlite3_column_text(s_, c));
  return p ? std::string(p, static_cast<std::size_t>(sqlite3_column_bytes(s_, c))) : "";
}
Eigen::Vector3d Stmt::GetVec(int c) const {
  return {GetReal(c), GetReal(c + 1), GetReal(c + 2)};
}
std::vector<std::uint8_t> Stmt::GetBlob(int c) const {
  const auto* p = static_cast<const std::uint8_t*>(sqlite3_column_blob(s_, c));
  const int n = sqlite3_column_bytes(s_, c);
  return p ? std::vector<std::uint8_t>(p, p + n) : std::vector<std::uint8_t>{};
}

Connection::Connection(fs::path path, RunDatabaseOptions options)
    : path_(std::move(path)), options_(std::move(options)) {}

Connection::~Connection() {
  for (auto& [sql, stmt] : cache_) sqlite3_finalize(stmt);
  if (db_) sqlite3_close(db_);
}

double Connection::Now() const {
  return options_.clock ? options_.clock() : SystemNow();
}

void Connection::Exec(const std::string& sql, std::string_view what) const {
  char* err = nullptr;
  const int rc = sqlite3_exec(db_, sql.c_str(), nullptr, nullptr, &err);
  sqlite3_free(err);
  if (rc != SQLITE_OK) Fail(rc, what);
}

Stmt Connection::Prepare(std::string_view sql) const {
  auto it = cache_.find(sql);
  if (it == cache_.end()) {
    sqlite3_stmt* stmt = nullptr;
    const int rc = sqlite3_prepare_v3(db_, sql.data(), static_cast<int>(sql.size()),
                                      SQLITE_PREPARE_PERSISTENT, &stmt, nullptr);
    if (rc != SQLITE_OK) Fail(rc, "preparing '" + std::string(sql.substr(0, 80)) + "'");
    it = cache_.emplace(sql, stmt).first;
  }
  return Stmt(*this, it->second);
}

std::int64_t Connection::ScalarInt(std::string_view sql) const {
  Stmt s = Prepare(sql);
  return s.Step() ? s.GetInt(0) : 0;
}

std::int64_t Connection::LastInsertId() const {
  return sqlite3_last_insert_rowid(db_);
}

std::int64_t Connection::Changes() const {
  return sqlite3_changes(db_);
}

bool Connection::InTransaction() const {
  return sqlite3_get_autocommit(db_) == 0;
}

void Connection::RollbackNoThrow() const noexcept {
  if (InTransaction()) sqlite3_exec(db_, "ROLLBACK", nullptr, nullptr, nullptr);
}

bool Stmt::Step() {
  const int rc = sqlite3_step(s_);
  if (rc == SQLITE_ROW) return true;
  if (rc == SQLITE_DONE) return false;
  conn_.Fail(rc, std::string("running '") + std::string(sqlite3_sql(s_)).substr(0, 80) + "'");
}

Stmt& Stmt::Check(int rc) {
  if (rc != SQLITE_OK) conn_.Fail(rc, "binding a parameter");
  return *this;
}

void Connection::Fail(int rc, std::string_view what) const {
  const StorageErrc code = CodeFor(rc);
  std::string msg(what);
  msg += ": ";
  msg += db_ ? sqlite3_errmsg(db_) : sqlite3_errstr(rc);
  switch (code) {
    case StorageErrc::kDiskFull:
      msg += " (disk full";
      if (options_.max_page_count > 0) {
        msg += " or max_page_count=" + std::to_string(options_.max_page_count) + " reached";
      }
      msg += "; the transaction was rolled back, earlier commits are intact)";
      break;
    case StorageErrc::kBusy:
      msg += " (another connection held the lock longer than busy_timeout_ms=" +
             std::to_string(options_.busy_timeout_ms) + ")";
      break;
    case StorageErrc::kReadOnly:
      msg += options_.read_only ? " (opened read-only)"
                                : " (the file or its directory is not writable)";
      break;
    case StorageErrc::kNotADatabase:
      msg += " (the file is not an SQLite database)";
      break;
    default:
      break;
  }
  throw StorageError(code, path_, msg);
}

void Connection::OpenHandle(const std::string& name, int flags) {
  const int rc = sqlite3_open_v2(name.c_str(), &db_, flags | SQLITE_OPEN_NOMUTEX, nullptr);
  if (rc != SQLITE_OK) {
    const std::string err = db_ ? sqlite3_errmsg(db_) : sqlite3_errstr(rc);
    sqlite3_close(db_);
    db_ = nullptr;
    Throw(CodeFor(rc) == StorageErrc::kIo ? StorageErrc::kCannotOpen : CodeFor(rc),
          "cannot open the database: " + err);
  }
  sqlite3_extended_result_codes(db_, 1);
  sqlite3_busy_timeout(db_, options_.busy_timeout_ms);
}

void Connection::Open(int target_version) {
  std::error_code ec;
  const bool exists = fs::exists(path_, ec);
  const fs::path dir = ParentDir(path_);
  if (!exists) {
    if (options_.read_only || !options_.create) {
      Throw(StorageErrc::kCannotOpen,
            std::string("no such database file") +
                (options_.read_only ? " (opened read-only)" : " (create=false)"));
    }
    if (!fs::is_directory(dir, ec)) {
      Throw(StorageErrc::kCannotOpen,
            "cannot create the database: directory " + dir.string() + " does not exist");
    }
    if (std::string why; !Writable(dir, &why)) {
      Throw(StorageErrc::kReadOnly, "cannot create the database: directory " + dir.string() +
                                        " is not writable (" + why + ")");
    }
  } else if (fs::is_directory(path_, ec)) {
    Throw(StorageErrc::kCannotOpen, "is a directory, not a database file");
  } else if (!options_.read_only) {
    if (std::string why; !Writable(path_, &why)) {
      Throw(StorageErrc::kReadOnly, "the database file is not writable (" + why + ")");
    }
    if (std::string why; !Writable(dir, &why)) {
      Throw(StorageErrc::kReadOnly,
            "directory " + dir.string() + " is not writable (" + why +
                "): SQLite needs to create the -wal and -shm files beside the database; open it "
                "with read_only to read what it holds");
    }
  }

  if (options_.read_only) {
    OpenHandle(path_.string(), SQLITE_OPEN_READONLY);
  } else {
    OpenHandle(path_.string(), SQLITE_OPEN_READWRITE | (options_.create ? SQLITE_OPEN_CREATE : 0));
  }

  // The first read of the header: a file that is not SQLite fails here.
  try {
    ScalarInt("SELECT count(*) FROM sqlite_master");
  } catch (const StorageError& e) {
    // A read-only WAL database in a read-only directory cannot create its -shm file. When no
    // -wal file holds uncheckpointed commits, the file alone is the whole database: open it
    // immutable so that what it holds stays readable.
    fs::path wal = path_;
    wal += "-wal";
    const bool no_wal = !fs::exists(wal, ec) || fs::file_size(wal, ec) == 0;
    if (!options_.read_only || e.code() == StorageErrc::kNotADatabase || !no_wal || Writable(dir)) {
      throw;
    }
    for (auto& [sql, stmt] : cache_) sqlite3_finalize(stmt);
    cache_.clear();
    sqlite3_close(db_);
    db_ = nullptr;
    OpenHandle(FileUri(path_, "immutable=1"), SQLITE_OPEN_READONLY | SQLITE_OPEN_URI);
    ScalarInt("SELECT count(*) FROM sqlite_master");
  }
  if (!options_.read_only && sqlite3_db_readonly(db_, "main") == 1) {
    Throw(StorageErrc::kReadOnly, "the database file is read-only");
  }
  CheckIdentity();
  ApplyPragmas();
  if (options_.read_only) {
    if (schema_version_ < kSchemaVersion) {
      Throw(StorageErrc::kReadOnly, "schema version " + std::to_string(schema_version_) +
                                        " needs migrating to " + std::to_string(kSchemaVersion) +
                                        ", which a read-only open cannot do");
    }
    return;
  }
  Migrate(target_version);
}

void Connection::CheckIdentity() {
  const std::int64_t app_id = ScalarInt("PRAGMA application_id");
  const std::int64_t version = ScalarInt("PRAGMA user_version");
  const std::int64_t tables = ScalarInt("SELECT count(*) FROM sqlite_master");
  if (app_id != 0 && app_id != kApplicationId) {
    Throw(StorageErrc::kForeignDatabase,
          "an SQLite database of another application (application_id " + std::to_string(app_id) +
              "), not a gs360 run database; refusing to touch it");
  }
  if (app_id == 0 && tables > 0) {
    Throw(StorageErrc::kForeignDatabase,
          "an SQLite database with " + std::to_string(tables) +
              " schema objects but no gs360 application_id, not a gs360 run database; refusing "
              "to touch it");
  }
  if (version > kSchemaVersion) {
    Throw(StorageErrc::kNewerSchema, "schema version " + std::to_string(version) +
                                         " was written by a newer gs360; this "
                                         "build supports up to version " +
                                         std::to_string(kSchemaVersion) +
                                         ". Upgrade gs360 to open it (the file was not modified)");
  }
  schema_version_ = static_cast<int>(version);
}

void Connection::ApplyPragmas() {
  if (!options_.read_only) {
    // Pages of 16 KiB for a new file (no effect on an existing one): frames are ~400 kB blobs,
    // and bigger pages mean fewer overflow pages and WAL frames per commit (bench_storage).
    Exec("PRAGMA page_size = 16384", "setting page_size");
    Stmt s = Prepare("PRAGMA journal_mode = WAL");
    const std::string mode = s.Step() ? s.GetText(0) : "";
    if (mode != "wal") {
      Throw(StorageErrc::kIo, "cannot switch to WAL journal mode (got '" + mode + "')");
    }
    Exec(options_.synchronous == SyncMode::kFull ? "PRAGMA synchronous = FULL"
                                                 : "PRAGMA synchronous = NORMAL",
         "setting synchronous");
    // Keep the WAL from growing without bound after a long transaction.
    Exec("PRAGMA journal_size_limit = 67108864", "setting journal_size_limit");
  }
  Exec("PRAGMA foreign_keys = ON", "enabling foreign keys");
  if (options_.max_page_count > 0) {
    Exec("PRAGMA max_page_count = " + std::to_string(options_.max_page_count),
         "setting max_page_count");
  }
}

void Connection::Migrate(int target_version) {
  if (schema_version_ >= target_version) return;
  Exec("BEGIN IMMEDIATE", "starting the schema migration");
  try {
    // Re-read under the write lock: another process may have migrated in the meantime.
    CheckIdentity();
    for (const SchemaMigration& m : Migrations()) {
      if (m.to_version <= schema_version_ || m.to_version > target_version) continue;
      Exec(std::string(m.sql), "migrating the schema to version " + std::to_string(m.to_version));
    }
    const int reached = std::max(schema_version_, target_version);
    Exec("PRAGMA application_id = " + std::to_string(kApplicationId), "setting application_id");
    Exec("PRAGMA user_version = " + std::to_string(reached), "setting user_version");
    Exec("COMMIT", "committing the schema migration");
    schema_version_ = reached;
  } catch (...) {
    if (!sqlite3_get_autocommit(db_)) sqlite3_exec(db_, "ROLLBACK", nullptr, nullptr, nullptr);
    throw;
  }
}

Transaction::Transaction(const Connection& conn, Kind kind) : conn_(conn) {
  if (conn.InTransaction()) {
    nested_ = true;
    return;
  }
  conn.Exec(kind == kWrite ? "BEGIN IMMEDIATE" : "BEGIN", "starting a transaction");
}

Transaction::~Transaction() {
  if (!nested_ && !committed_) conn_.RollbackNoThrow();
}

void Transaction::Commit() {
  if (nested_) return;
  conn_.Exec("COMMIT", "committing");
  committed_ = true;
}

}  // namespace gs360::storage_internal
