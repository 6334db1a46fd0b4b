// base/text.h: which names may reach a terminal, and how the others are written out.

#include <catch2/catch.hpp>

#include "base/text.h"

using namespace gs360;

TEST_CASE("text: printable UTF-8 passes, control characters and broken UTF-8 are named", "[base]") {
  CHECK(PrintableTextProblem("finger-07", 100).empty());
  CHECK(PrintableTextProblem("Fingerspitze \xc3\xa4\xe2\x82\xac \xf0\x9f\x91\x8d", 100).empty());
  CHECK(PrintableTextProblem("", 100).empty());
  CHECK(PrintableTextProblem("\x1b[2J", 100) == "control character U+001B at character 1");
  CHECK(PrintableTextProblem("a\nb", 100) == "control character U+000A at character 2");
  CHECK(PrintableTextProblem("a\x7f", 100) == "control character U+007F at character 2");
  CHECK(PrintableTextProblem("\xc2\x9b"
                             "2J",
                             100) == "control character U+009B at character 1");
  CHECK(PrintableTextProblem("abc\xe2\x80\xae", 100) == "control character U+202E at character 4");
  CHECK(PrintableTextProblem("ab\xff", 100) == "invalid UTF-8 at byte 3");
  CHECK(PrintableTextProblem("\xc0\xaf", 100) == "invalid UTF-8 at byte 1");      // overlong
  CHECK(PrintableTextProblem("\xed\xa0\x80", 100) == "invalid UTF-8 at byte 1");  // surrogate
  CHECK(PrintableTextProblem("\xe2\x82", 100) == "invalid UTF-8 at byte 1");      // truncated
  CHECK(PrintableTextProblem(std::string(101, 'x'), 100) == "101 characters");
  CHECK(PrintableTextProblem(std::string(100, 'x'), 100).empty());
  // Characters, not bytes: 100 two-byte characters fit.
  std::string umlauts;
  for (int i = 0; i < 100; ++i) umlauts += "\xc3\xa4";
  CHECK(PrintableTextProblem(umlauts, 100).empty());
}

TEST_CASE("text: escaping keeps printable text and writes out everything else", "[base]") {
  CHECK(EscapeControlCharacters("finger-07 \xc3\xa4") == "finger-07 \xc3\xa4");
  CHECK(EscapeControlCharacters("\x1b[2Jx") == "\\e[2Jx");
  CHECK(EscapeControlCharacters("a\nb\tc\rd\x01") == "a\\nb\\tc\\rd\\x01");
  CHECK(EscapeControlCharacters("\xc2\x9b\xe2\x80\xae") == "\\u{009b}\\u{202e}");
  CHECK(EscapeControlCharacters("a\xff"
                                "b") == "a\\xffb");
  CHECK(EscapeControlCharacters("back\\slash") == "back\\\\slash");
  // Whatever goes in, nothing below U+0020 comes out.
  std::string all;
  for (int c = 0; c < 256; ++c) all += static_cast<char>(c);
  for (const char c : EscapeControlCharacters(all)) {
    CHECK(static_cast<unsigned char>(c) >= 0x20);
    CHECK(c != '\x7f');
  }
}
