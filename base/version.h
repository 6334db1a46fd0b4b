#pragma once
// The version of gs360 and the commit this build was made from (generated at build time by
// cmake/Version.cmake).

#include <string>
#include <string_view>

namespace gs360 {

// The project's version, "major.minor.patch" (CMakeLists.txt's project()).
std::string_view Version();
// The commit the build was made from: 12 hex digits, with "-dirty" when the work tree had
// uncommitted changes; "unknown" when built without git (or GS360_COMMIT when set at configure).
std::string_view Commit();
// "<program> <version> (commit <commit>)": the line --version prints.
std::string VersionLine(std::string_view program);

}  // namespace gs360
