#include "base/version.h"

namespace gs360 {

// Version() and Commit() are defined in the build folder's version_info.cc (cmake/Version.cmake).

std::string VersionLine(std::string_view program) {
  return std::string(program) + " " + std::string(Version()) + " (commit " + std::string(Commit()) +
         ")";
}

}  // namespace gs360
