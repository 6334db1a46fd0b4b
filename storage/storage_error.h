#pragma once
// Errors raised by the run database (storage/). Every message names the database file.

#include <filesystem>
#include <stdexcept>
#include <string>
#include <string_view>

namespace gs360 {

// What went wrong, so that callers can react without parsing messages.
enum class StorageErrc {
  kCannotOpen,       // the file or its directory does not exist / cannot be opened
  kNotADatabase,     // the file is not an SQLite database
  kForeignDatabase,  // an SQLite database, but not a gs360 run database
  kNewerSchema,      // written by a newer gs360 (schema version above what this build knows)
  kReadOnly,         // the file or its directory is read-only, or the instance was opened read-only
  kDiskFull,         // disk full or max_page_count reached; the transaction was rolled back
  kBusy,             // another connection held the write lock longer than the busy timeout
  kCorruptDatabase,  // SQLite reports a malformed database file
  kCorruptBlob,      // a stored blob does not match its checksum or does not decode
  kNotFound,         // a run / probe / frame id that does not exist
  kInvalidState,     // an operation the current state forbids (e.g. committing a captured probe)
  kConflict,         // a unique key already exists (e.g. a model name + version)
  kIo,               // any other SQLite or I/O failure
};

std::string_view ToString(StorageErrc code);

class StorageError : public std::runtime_error {
 public:
  // what() is "<database>: <detail>".
  StorageError(StorageErrc code, const std::filesystem::path& database, const std::string& detail);

  StorageErrc code() const noexcept { return code_; }
  const std::filesystem::path& database() const noexcept { return database_; }

 private:
  StorageErrc code_;
  std::filesystem::path database_;
};

}  // namespace gs360
