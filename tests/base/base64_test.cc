#include "base/base64.h"

#include <catch2/catch.hpp>
#include <string>
#include <vector>

namespace gs360 {
namespace {

std::string Encode(const std::string& text) {
  const std::vector<std::uint8_t> bytes(text.begin(), text.end());
  return Base64Encode(bytes);
}

TEST_CASE("Base64Encode gives RFC 4648's test vectors", "[base64]") {
  CHECK(Encode("") == "");
  CHECK(Encode("f") == "Zg==");
  CHECK(Encode("fo") == "Zm8=");
  CHECK(Encode("foo") == "Zm9v");
  CHECK(Encode("foob") == "Zm9vYg==");
  CHECK(Encode("fooba") == "Zm9vYmE=");
  CHECK(Encode("foobar") == "Zm9vYmFy");
}

TEST_CASE("Base64Encode uses the whole alphabet and every bit of a byte", "[base64]") {
  CHECK(Base64Encode(std::vector<std::uint8_t>{0xfb, 0xff, 0xbf}) == "+/+/");
  CHECK(Base64Encode(std::vector<std::uint8_t>{0x00, 0x10, 0x83}) == "ABCD");
  CHECK(Base64Encode(std::vector<std::uint8_t>{0xff}) == "/w==");
}

}  // namespace
}  // namespace gs360
