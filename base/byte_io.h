#pragma once
// Binary blobs as gs360's serialisers write them (the MLP, the surface map, the training
// checkpoint): trivially copyable values and arrays appended as they lie in memory, so
// little-endian on every platform gs360 builds on, and read back with a length check of every
// read. The formats themselves (magic, version, checksum) are the callers'.

#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <type_traits>
#include <vector>

namespace gs360 {

// True when `bytes` start with the 8-byte PNG signature. Callers that expect a PNG check this
// before OpenCV's decoder, which otherwise tries every format it knows (its DICOM reader aborts
// the process on some malformed input: found by tests/fuzz).
bool HasPngSignature(std::span<const std::uint8_t> bytes);

class ByteWriter {
 public:
  explicit ByteWriter(std::size_t reserve = 0) { bytes_.reserve(reserve); }
  void Bytes(const void* data, std::size_t n);
  template <typename T>
  void Put(const T& v) {
    static_assert(std::is_trivially_copyable_v<T>);
    Bytes(&v, sizeof(T));
  }
  template <typename T>
  void PutArray(const T* data, std::size_t n) {
    static_assert(std::is_trivially_copyable_v<T>);
    Bytes(data, n * sizeof(T));
  }
  std::vector<std::uint8_t>& bytes() { return bytes_; }

 private:
  std::vector<std::uint8_t> bytes_;
};

// Reads `bytes` (not owned: they must outlive the reader) from the front. Every read that would
// pass the end throws std::runtime_error "<context>: truncated input: <what> needs N bytes at
// offset P, only L left".
class ByteReader {
 public:
  ByteReader(std::span<const std::uint8_t> bytes, std::string context)
      : bytes_(bytes), context_(std::move(context)) {}
  void Bytes(void* out, std::size_t n, const char* what);
  template <typename T>
  T Get(const char* what) {
    static_assert(std::is_trivially_copyable_v<T>);
    T v;
    Bytes(&v, sizeof(T), what);
    return v;
  }
  template <typename T>
  void GetArray(T* out, std::size_t n, const char* what) {
    static_assert(std::is_trivially_copyable_v<T>);
    Bytes(out, n * sizeof(T), what);
  }
  std::size_t pos() const { return pos_; }
  std::size_t remaining() const { return bytes_.size() - pos_; }

 private:
  std::span<const std::uint8_t> bytes_;
  std::string context_;
  std::size_t pos_ = 0;
};

}  // namespace gs360
