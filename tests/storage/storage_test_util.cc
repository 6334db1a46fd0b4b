#include "tests/storage/storage_test_util.h"

#include <sqlite3.h>
#include <unistd.h>

#include <atomic>
#include <cmath>
#include <random>
#include <stdexcept>

#include <opencv2/core.hpp>

namespace gs360::test {

namespace fs = std::filesystem;

TempDir::TempDir() {
  static std::atomic<int> counter{0};
  path_ = fs::temp_directory_path() /
          ("gs360_storage_test_" + std::to_string(::getpid()) + "_" + std::to_string(counter++));
  fs::remove_all(path_);
  fs::create_directories(path_);
  fs::permissions(path_, fs::perms::owner_all | fs::perms::group_read | fs::perms::group_exec |
                             fs::perms::others_read | fs::perms::others_exec);
}

TempDir::~TempDir() {
  std::error_code ec;
  // Tests may leave read-only files and directories behind; make everything removable.
  for (auto it = fs::recursive_directory_iterator(path_, ec);
       !ec && it != fs::recursive_directory_iterator(); it.increment(ec)) {
    fs::permissions(it->path(), fs::perms::owner_all, fs::perm_options::add, ec);
  }
  fs::permissions(path_, fs::perms::owner_all, fs::perm_options::add, ec);
  fs::remove_all(path_, ec);
}

cv::Mat NoisyFrame(int seed, int width, int height, int type, double sigma) {
  if (type == 0) type = CV_8UC3;
  const int channels = CV_MAT_CN(type);
  const bool wide = CV_MAT_DEPTH(type) == CV_16U;
  const double scale = wide ? 256.0 : 1.0;
  const double max_value = wide ? 65535.0 : 255.0;
  std::mt19937 rng(static_cast<unsigned>(seed) * 7919u + 17u);
  std::normal_distribution<double> noise(0.0, sigma * scale);
  std::uniform_real_distribution<double> phase(0.0, 6.28);
  const double p0 = phase(rng), p1 = phase(rng), p2 = phase(rng);
  cv::Mat out(height, width, type);
  for (int y = 0; y < height; ++y) {
    for (int x = 0; x < width; ++x) {
      const double u = (x - 0.5 * width) / width, v = (y - 0.5 * height) / height;
      const double r2 = u * u + v * v;
      const double base[3] = {120 + 70 * std::cos(3 * r2 + p0) + 15 * std::sin(6 * u + p1),
                              90 + 50 * std::sin(4 * v + p1),
                              70 + 80 * std::exp(-6 * r2) + 10 * std::cos(5 * u + p2)};
      for (int c = 0; c < channels; ++c) {
        const double value = std::clamp(std::round(base[c] * scale + noise(rng)), 0.0, max_value);
        if (wide) {
          out.ptr<std::uint16_t>(y)[x * channels + c] = static_cast<std::uint16_t>(value);
        } else {
          out.ptr<std::uint8_t>(y)[x * channels + c] = static_cast<std::uint8_t>(value);
        }
      }
    }
  }
  return out;
}

bool SameImage(const cv::Mat& a, const cv::Mat& b) {
  if (a.size() != b.size() || a.type() != b.type()) return false;
  if (a.empty()) return true;
  cv::Mat diff;
  cv::absdiff(a, b, diff);
  return cv::countNonZero(diff.reshape(1)) == 0;
}

struct RawDb::Impl {
  sqlite3* db = nullptr;
  std::string path;

  [[noreturn]] void Fail(const std::string& sql) const {
    throw std::runtime_error("RawDb " + path + ": " + sql + ": " + sqlite3_errmsg(db));
  }
  sqlite3_stmt* Prepare(const std::string& sql) const {
    sqlite3_stmt* s = nullptr;
    if (sqlite3_prepare_v2(db, sql.c_str(), -1, &s, nullptr) != SQLITE_OK) Fail(sql);
    return s;
  }
};

RawDb::RawDb(const fs::path& path) : impl_(std::make_unique<Impl>()) {
  impl_->path = path.string();
  if (sqlite3_open(impl_->path.c_str(), &impl_->db) != SQLITE_OK) impl_->Fail("open");
  sqlite3_busy_timeout(impl_->db, 5000);
}

RawDb::~RawDb() {
  sqlite3_close(impl_->db);
}

void RawDb::Exec(const std::string& sql) {
  if (sqlite3_exec(impl_->db, sql.c_str(), nullptr, nullptr, nullptr) != SQLITE_OK) {
    impl_->Fail(sql);
  }
}

std::int64_t RawDb::Int(const std::string& sql) {
  sqlite3_stmt* s = impl_->Prepare(sql);
  const int rc = sqlite3_step(s);
  const std::int64_t v = rc == SQLITE_ROW ? sqlite3_column_int64(s, 0) : 0;
  sqlite3_finalize(s);
  if (rc != SQLITE_ROW && rc != SQLITE_DONE) impl_->Fail(sql);
  return v;
}

std::string RawDb::Text(const std::string& sql) {
  const std::vector<std::string> rows = Column(sql);
  return rows.empty() ? "" : rows.front();
}

std::vector<std::string> RawDb::Column(const std::string& sql) {
  sqlite3_stmt* s = impl_->Prepare(sql);
  std::vector<std::string> out;
  int rc;
  while ((rc = sqlite3_step(s)) == SQLITE_ROW) {
    const auto* p = reinterpret_cast<const char*>(sqlite3_column_text(s, 0));
    out.emplace_back(p ? p : "");
  }
  sqlite3_finalize(s);
  if (rc != SQLITE_DONE) impl_->Fail(sql);
  return out;
}

std::vector<std::uint8_t> RawDb::Blob(const std::string& sql) {
  sqlite3_stmt* s = impl_->Prepare(sql);
  std::vector<std::uint8_t> out;
  const int rc = sqlite3_step(s);
  if (rc == SQLITE_ROW) {
    const auto* p = static_cast<const std::uint8_t*>(sqlite3_column_blob(s, 0));
    out.assign(p, p + sqlite3_column_bytes(s, 0));
  }
  sqlite3_finalize(s);
  if (rc != SQLITE_ROW && rc != SQLITE_DONE) impl_->Fail(sql);
  return out;
}

void RawDb::ExecWithBlob(const std::string& sql, std::span<const std::uint8_t> blob) {
  sqlite3_stmt* s = impl_->Prepare(sql);
  sqlite3_bind_blob64(s, 1, blob.data(), blob.size(), SQLITE_TRANSIENT);
  const int rc = sqlite3_step(s);
  sqlite3_finalize(s);
  if (rc != SQLITE_DONE && rc != SQLITE_ROW) impl_->Fail(sql);
}

}  // namespace gs360::test
