#pragma once
// Helpers for the storage tests: temporary directories, synthetic frames, and raw SQLite access
// that is independent of RunDatabase (to inspect and damage files behind its back).

#include <cstdint>
#include <filesystem>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include <opencv2/core/mat.hpp>

namespace gs360::test {

// A fresh directory under the system temp dir, removed (permissions restored) on destruction.
class TempDir {
 public:
  TempDir();
  ~TempDir();
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;
  const std::filesystem::path& path() const { return path_; }
  std::filesystem::path operator/(const std::string& name) const { return path_ / name; }

 private:
  std::filesystem::path path_;
};

// A smooth colour field plus Gaussian noise (sigma in grey levels), quantised: like a lit gel.
// type: CV_8UC3, CV_8UC1, CV_16UC1 or CV_16UC3 (16-bit values are scaled by 256).
cv::Mat NoisyFrame(int seed, int width, int height, int type = 0, double sigma = 1.7);

// True if both images have the same size, type and pixels.
bool SameImage(const cv::Mat& a, const cv::Mat& b);

// A plain SQLite connection without gs360's checks, for inspecting and corrupting files.
class RawDb {
 public:
  explicit RawDb(const std::filesystem::path& path);
  ~RawDb();
  RawDb(const RawDb&) = delete;
  RawDb& operator=(const RawDb&) = delete;

  void Exec(const std::string& sql);
  std::int64_t Int(const std::string& sql);                 // first column of the first row
  std::string Text(const std::string& sql);                 // first column of the first row
  std::vector<std::string> Column(const std::string& sql);  // first column of every row
  std::vector<std::uint8_t> Blob(const std::string& sql);   // first column of the first row
  // Runs `sql` with one blob parameter bound as ?1.
  void ExecWithBlob(const std::string& sql, std::span<const std::uint8_t> blob);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace gs360::test
