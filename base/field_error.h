#pragma once
// The one form of an invalid option: std::invalid_argument naming the field, the rule and the
// value, e.g. "PoseOptions.huber_px must be > 0, got -1". Options structs' Check() functions
// throw it; the CLI and the daemon pass the message on unchanged.

#include <string>
#include <string_view>

namespace gs360 {

// "<field> <rule>, got <value>"; the value in its shortest exact decimal form ("0.1", "5",
// "nan", "inf").
std::string FieldErrorMessage(std::string_view field, double value, std::string_view rule);

[[noreturn]] void ThrowFieldError(std::string_view field, double value, std::string_view rule);

}  // namespace gs360
