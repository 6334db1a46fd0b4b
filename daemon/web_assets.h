#pragma once
// The dashboard's files (daemon/web/), compiled into gs360d by cmake/EmbedFiles.cmake: served as
// they are, with no build step and nothing fetched from the internet.

#include <string_view>
#include <vector>

namespace gs360 {

struct WebAsset {
  std::string_view path;  // "/index.html", "/app.js", ...
  std::string_view type;  // Content-Type
  std::string_view content;
};

const std::vector<WebAsset>& WebAssets();

}  // namespace gs360
