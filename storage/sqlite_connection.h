#pragma once
// storage/'s own RAII wrapper around SQLite (internal to storage/: the run database's .cc files
// include it; SQLite's C API stays in sqlite_connection.cc). One connection per thread.
//
// Connection: opens (or creates) a database file with the run database's options, checks that
// it is gs360's (application_id, schema version), applies the pragmas (WAL, synchronous,
// busy timeout, page limit), migrates it, and keeps a cache of prepared statements. Every
// SQLite failure becomes a StorageError with a code and a message naming the file and what was
// being done (disk full, busy, read-only, not a database...).

#include <Eigen/Core>
#include <cstdint>
#include <filesystem>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <unordered_map>
#include <vector>

#include "storage/run_database.h"
#include "storage/storage_error.h"

struct sqlite3;
struct sqlite3_stmt;

namespace gs360::storage_internal {

class Connection;

// A cached prepared statement in use; resets it (and clears its bindings) when done. Binders
// throw StorageError; indices are SQLite's (parameters from 1, columns from 0).
class Stmt {
 public:
  Stmt(const Connection& conn, sqlite3_stmt* s) : conn_(conn), s_(s) {}
  ~Stmt();
  Stmt(const Stmt&) = delete;
  Stmt& operator=(const Stmt&) = delete;

  Stmt& Int(int i, std::int64_t v);
  Stmt& Real(int i, double v);
  Stmt& OptReal(int i, std::optional<double> v);
  Stmt& OptInt(int i, std::optional<std::int64_t> v);
  Stmt& Text(int i, std::string_view v);
  Stmt& OptText(int i, std::string_view v);  // "" binds NULL
  // The bytes must stay alive until the statement has run (they are not copied).
  Stmt& Blob(int i, std::span<const std::uint8_t> v);
  Stmt& Vec(int first, const Eigen::Vector3d& v);  // three REAL parameters

  // True while there is a row.
  bool Step();
  // Runs a statement that returns no rows of interest.
  void Run();

  bool IsNull(int c) const;
  std::int64_t GetInt(int c) const;
  double GetReal(int c) const;
  std::optional<double> GetOptReal(int c) const;
  std::optional<std::int64_t> GetOptInt(int c) const;
  std::string GetText(int c) const;
  Eigen::Vector3d GetVec(int c) const;
  std::vector<std::uint8_t> GetBlob(int c) const;

 private:
  Stmt& Check(int rc);

  const Connection& conn_;
  sqlite3_stmt* s_;
};

class Connection {
 public:
  Connection(std::filesystem::path path, RunDatabaseOptions options);
  ~Connection();
  Connection(const Connection&) = delete;
  Connection& operator=(const Connection&) = delete;

  // Opens the file and migrates it to `target_version` (read-write only).
  void Open(int target_version);

  const std::filesystem::path& path() const { return path_; }
  const RunDatabaseOptions& options() const { return options_; }
  int schema_version() const { return schema_version_; }
  double Now() const;  // options().clock, or the system clock (Unix seconds)

  [[noreturn]] void Throw(StorageErrc code, const std::string& detail) const {
    throw StorageError(code, path_, detail);
  }
  // Throws the StorageError for an SQLite result code; `what` says what was being done.
  [[noreturn]] void Fail(int rc, std::string_view what) const;

  void Exec(const std::string& sql, std::string_view what) const;
  // `sql` must have static storage (a literal): it keys the statement cache.
  Stmt Prepare(std::string_view sql) const;
  std::int64_t ScalarInt(std::string_view sql) const;
  std::int64_t LastInsertId() const;
  std::int64_t Changes() const;  // rows changed by the latest statement
  bool InTransaction() const;
  void RollbackNoThrow() const noexcept;  // for destructors: errors are ignored

 private:
  void OpenHandle(const std::string& name, int flags);
  void CheckIdentity();
  void ApplyPragmas();
  void Migrate(int target_version);

  std::filesystem::path path_;
  RunDatabaseOptions options_;
  sqlite3* db_ = nullptr;
  int schema_version_ = 0;
  mutable std::unordered_map<std::string_view, sqlite3_stmt*> cache_;
};

// A transaction; nested ones join the outer one. Rolls back unless committed.
class Transaction {
 public:
  enum Kind { kRead, kWrite };
  Transaction(const Connection& conn, Kind kind);
  ~Transaction();
  Transaction(const Transaction&) = delete;
  Transaction& operator=(const Transaction&) = delete;

  void Commit();

 private:
  const Connection& conn_;
  bool nested_ = false;
  bool committed_ = false;
};

}  // namespace gs360::storage_internal
