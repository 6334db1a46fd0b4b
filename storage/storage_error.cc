#include "storage/storage_error.h"

namespace gs360 {

std::string_view ToString(StorageErrc code) {
  switch (code) {
    case StorageErrc::kCannotOpen:
      return "cannot open";
    case StorageErrc::kNotADatabase:
      return "not a database";
    case StorageErrc::kForeignDatabase:
      return "not a gs360 database";
    case StorageErrc::kNewerSchema:
      return "newer schema";
    case StorageErrc::kReadOnly:
      return "read-only";
    case StorageErrc::kDiskFull:
      return "disk full";
    case StorageErrc::kBusy:
      return "busy";
    case StorageErrc::kCorruptDatabase:
      return "corrupt database";
    case StorageErrc::kCorruptBlob:
      return "corrupt blob";
    case StorageErrc::kNotFound:
      return "not found";
    case StorageErrc::kInvalidState:
      return "invalid state";
    case StorageErrc::kConflict:
      return "conflict";
    case StorageErrc::kIo:
      return "I/O error";
  }
  return "unknown";
}

StorageError::StorageError(StorageErrc code, const std::filesystem::path& database,
                           const std::string& detail)
    : std::runtime_error(database.string() + ": " + detail), code_(code), database_(database) {}

}  // namespace gs360
