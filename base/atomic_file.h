#pragma once
// Whole-file writes that a reader (or a crash) never sees half done.

#include <filesystem>
#include <string_view>

namespace gs360 {

// Writes `bytes` to `path` as one step for any reader: they go to `path` + ".tmp" beside it, which
// then replaces `path` by a rename (atomic on one file system). The folder must exist. Throws
// std::runtime_error naming `path` and what failed (cannot open, a short write: "disk full?",
// cannot rename); the temporary file is removed then and `path` is left as it was.
void WriteFileAtomically(const std::filesystem::path& path, std::string_view bytes);

}  // namespace gs360
