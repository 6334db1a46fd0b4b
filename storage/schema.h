#pragma once
// The run database schema: versions and forward migrations.
//
// The schema version lives in SQLite's `PRAGMA user_version`, the file's owner in
// `PRAGMA application_id` (kApplicationId, "GS36"). Migration i (1-based) takes a database from
// version i-1 to version i; RunDatabase applies the missing ones in one transaction on open and
// refuses a file whose version is above kSchemaVersion.
//
// Version 1: runs, probes, frames, events (acquisition).
// Version 2: artifacts, models (calibration stages and exported models).
// Version 5: probes.retry (a failed probe that is not pressed again).

#include <cstdint>
#include <filesystem>
#include <span>
#include <string_view>

namespace gs360 {

inline constexpr int kSchemaVersion = 5;
inline constexpr std::int32_t kApplicationId = 0x47533336;  // "GS36"

struct SchemaMigration {
  int to_version;
  std::string_view sql;  // one or more statements
};

// All migrations, in order; Migrations()[i].to_version == i + 1.
std::span<const SchemaMigration> Migrations();

// Creates (or migrates) the database at `path` only up to `version` (1..kSchemaVersion), with the
// same pragmas as RunDatabase. For migration tests and tools; RunDatabase itself always migrates
// to kSchemaVersion. Throws StorageError (storage/storage_error.h) like RunDatabase's constructor,
// std::invalid_argument for a version out of range.
void CreateDatabaseAtVersion(const std::filesystem::path& path, int version);

}  // namespace gs360
