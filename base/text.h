#pragma once
// Text from users (run names, log messages) on its way to a terminal: an ESC sequence in a run
// name must not clear the screen of whoever lists the runs. New names are checked where they
// are made (PrintableTextProblem); anything printed that an older database may hold is escaped
// (EscapeControlCharacters).

#include <cstddef>
#include <string>
#include <string_view>

namespace gs360 {

// Empty when `text` is valid UTF-8 of at most `max_chars` characters (code points) with no
// control character (U+0000..U+001F, U+007F..U+009F) and no bidirectional override or isolate
// (U+202A..U+202E, U+2066..U+2069, which reorder what follows on a terminal); otherwise what is
// wrong, e.g. "control character U+001B at character 1", "invalid UTF-8 at byte 4",
// "201 characters".
std::string PrintableTextProblem(std::string_view text, std::size_t max_chars);

// `text` with every byte or character PrintableTextProblem objects to written out: control
// characters as "\e" (ESC), "\n", "\t", "\r" or "\xHH" / "\u{HHHH}", invalid UTF-8 bytes as
// "\xHH", backslashes doubled; printable UTF-8 is kept as it is.
std::string EscapeControlCharacters(std::string_view text);

}  // namespace gs360
