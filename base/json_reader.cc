#include "base/json_reader.h"

#include <charconv>
#include <cmath>
#include <fstream>
#include <limits>
#include <sstream>

namespace gs360 {
namespace {

// `v` as a person writes it: whole numbers below 1e15 in full ("100000", not "1e+05"), others
// in the shortest decimal that reads back as `v` ("0.5", "1e+300").
std::string Shortest(double v) {
  char buf[64];
  const bool whole = std::abs(v) < 1e15 && v == std::floor(v);
  const auto [end, ec] = whole ? std::to_chars(buf, buf + sizeof(buf), v, std::chars_format::fixed)
                               : std::to_chars(buf, buf + sizeof(buf), v);
  return ec == std::errc() ? std::string(buf, end) : std::to_string(v);
}

}  // namespace

std::string IntRange::Text() const {
  return std::to_string(min) + ".." + std::to_string(max);
}

std::string NumberRange::Text() const {
  std::string s = (min_open ? "(" : "[") + Shortest(min) + ", " + Shortest(max) + "]";
  if (*unit != '\0') s += std::string(" ") + unit;
  return s;
}

std::string WhereField(const std::string& where, const SourceLines* lines,
                       const std::string& path) {
  if (lines == nullptr) return where;
  std::string p = path;
  for (;;) {
    const auto it = lines->find(p);
    if (it != lines->end()) return where + ":" + std::to_string(it->second);
    const auto dot = p.rfind('.');
    if (p.empty()) return where;
    p = dot == std::string::npos ? std::string() : p.substr(0, dot);
  }
}

JsonReader::JsonReader(const nlohmann::json& json, std::string where, std::string path,
                       const SourceLines* lines)
    : json_(json), where_(std::move(where)), path_(std::move(path)), lines_(lines) {
  if (!json_.is_object()) {
    throw ConfigError(WhereField(where_, lines_, path_) + ": " +
                          (path_.empty() ? std::string("the configuration") : path_) +
                          ": expected an object, got " + json_.type_name(),
                      path_);
  }
}

std::string JsonReader::FieldPath(const std::string& key) const {
  return path_.empty() ? key : path_ + "." + key;
}

void JsonReader::Fail(const std::string& key, const std::string& what) const {
  const std::string field = FieldPath(key);
  throw ConfigError(WhereField(where_, lines_, field) + ": " + field + ": " + what, field);
}

const nlohmann::json* JsonReader::Find(const char* key) {
  known_.insert(key);
  const auto it = json_.find(key);
  return it == json_.end() ? nullptr : &*it;
}

const nlohmann::json* JsonReader::Raw(const char* key) {
  return Find(key);
}

void JsonReader::Get(const char* key, double& out) {
  const auto* v = Find(key);
  if (!v) return;
  if (!v->is_number()) Fail(key, std::string("expected a number, got ") + v->dump());
  const double d = v->get<double>();
  if (!std::isfinite(d)) Fail(key, "expected a finite number");
  out = d;
}

void JsonReader::Get(const char* key, int& out) {
  Get(key, out, IntRange{std::numeric_limits<int>::min(), std::numeric_limits<int>::max()});
}

void JsonReader::Get(const char* key, int& out, const IntRange& range) {
  const auto* v = Find(key);
  if (!v) return;
  // An unsigned value above INT64_MAX would wrap if read as signed: it is out of range anyway.
  const bool fits =
      v->is_number_integer() &&
      !(v->is_number_unsigned() && v->get<std::uint64_t>() > static_cast<std::uint64_t>(range.max));
  if (!fits || v->get<std::int64_t>() < range.min || v->get<std::int64_t>() > range.max) {
    Fail(key, "expected an integer in " + range.Text() + ", got " + v->dump());
  }
  out = static_cast<int>(v->get<std::int64_t>());
}

void JsonReader::Get(const char* key, double& out, const NumberRange& range) {
  const auto* v = Find(key);
  if (!v) return;
  const double d = v->is_number() ? v->get<double>() : std::nan("");
  const bool low_ok = range.min_open ? d > range.min : d >= range.min;
  if (!v->is_number() || !std::isfinite(d) || !low_ok || !(d <= range.max)) {
    Fail(key, "expected a number in " + range.Text() + ", got " + v->dump());
  }
  out = d;
}

void JsonReader::Get(const char* key, Eigen::Vector3d& out, const NumberRange& range) {
  const auto* v = Find(key);
  if (!v) return;
  bool ok = v->is_array() && v->size() == 3;
  for (std::size_t i = 0; ok && i < 3; ++i) {
    const auto& e = (*v)[i];
    const double d = e.is_number() ? e.get<double>() : std::nan("");
    ok = std::isfinite(d) && (range.min_open ? d > range.min : d >= range.min) && d <= range.max;
  }
  if (!ok) Fail(key, "expected [x, y, z], each in " + range.Text() + ", got " + v->dump());
  for (int i = 0; i < 3; ++i) out[i] = (*v)[static_cast<std::size_t>(i)].get<double>();
}

void JsonReader::Get(const char* key, std::int64_t& out) {
  const auto* v = Find(key);
  if (!v) return;
  if (!v->is_number_integer()) Fail(key, std::string("expected an integer, got ") + v->dump());
  if (v->is_number_unsigned() &&
      v->get<std::uint64_t>() >
          static_cast<std::uint64_t>(std::numeric_limits<std::int64_t>::max())) {
    Fail(key, "integer out of range: " + v->dump());
  }
  out = v->get<std::int64_t>();
}

void JsonReader::Get(const char* key, std::uint64_t& out) {
  const auto* v = Find(key);
  if (!v) return;
  if (!v->is_number_unsigned() && !(v->is_number_integer() && v->get<std::int64_t>() >= 0)) {
    Fail(key, "expected an integer in 0.." +
                  std::to_string(std::numeric_limits<std::uint64_t>::max()) + ", got " + v->dump());
  }
  out = v->get<std::uint64_t>();
}

void JsonReader::Get(const char* key, bool& out) {
  const auto* v = Find(key);
  if (!v) return;
  if (!v->is_boolean()) Fail(key, std::string("expected true or false, got ") + v->dump());
  out = v->get<bool>();
}

void JsonReader::Get(const char* key, std::string& out) {
  const auto* v = Find(key);
  if (!v) return;
  if (!v->is_string()) Fail(key, std::string("expected a string, got ") + v->dump());
  out = v->get<std::string>();
}

void JsonReader::Get(const char* key, Eigen::Vector3d& out) {
  const auto* v = Find(key);
  if (!v) return;
  if (!v->is_array() || v->size() != 3) Fail(key, "expected [x, y, z], got " + v->dump());
  for (int i = 0; i < 3; ++i) {
    const auto& e = (*v)[static_cast<std::size_t>(i)];
    if (!e.is_number() || !std::isfinite(e.get<double>())) {
      Fail(key, "expected three finite numbers, got " + v->dump());
    }
    out[i] = e.get<double>();
  }
}

void JsonReader::Get(const char* key, std::vector<double>& out) {
  const auto* v = Find(key);
  if (!v) return;
  if (!v->is_array()) Fail(key, "expected a list of numbers, got " + v->dump());
  std::vector<double> values;
  for (const auto& e : *v) {
    if (!e.is_number() || !std::isfinite(e.get<double>())) {
      Fail(key, "expected a list of finite numbers, got " + v->dump());
    }
    values.push_back(e.get<double>());
  }
  out = std::move(values);
}

void JsonReader::Get(const char* key, std::vector<int>& out) {
  const auto* v = Find(key);
  if (!v) return;
  if (!v->is_array()) Fail(key, "expected a list of integers, got " + v->dump());
  std::vector<int> values;
  for (const auto& e : *v) {
    if (!e.is_number_integer() || e.get<long long>() < std::numeric_limits<int>::min() ||
        e.get<long long>() > std::numeric_limits<int>::max()) {
      Fail(key, "expected a list of integers, got " + v->dump());
    }
    values.push_back(e.get<int>());
  }
  out = std::move(values);
}

void JsonReader::Get(const char* key, std::vector<std::string>& out) {
  const auto* v = Find(key);
  if (!v) return;
  if (!v->is_array()) Fail(key, "expected a list of strings, got " + v->dump());
  std::vector<std::string> values;
  for (const auto& e : *v) {
    if (!e.is_string()) Fail(key, "expected a list of strings, got " + v->dump());
    values.push_back(e.get<std::string>());
  }
  out = std::move(values);
}

void JsonReader::Objects(const char* key,
                         const std::function<void(JsonReader&, std::size_t)>& read) {
  const auto* v = Find(key);
  if (!v) return;
  if (!v->is_array()) Fail(key, std::string("expected a list of tables, got ") + v->type_name());
  for (std::size_t i = 0; i < v->size(); ++i) {
    const std::string path = FieldPath(key) + "[" + std::to_string(i) + "]";
    if (!(*v)[i].is_object()) {
      throw ConfigError(WhereField(where_, lines_, path) + ": " + path +
                            ": expected a table, got " + (*v)[i].type_name(),
                        path);
    }
    JsonReader child((*v)[i], where_, path, lines_);
    read(child, i);
    child.RejectUnknown();
  }
}

void JsonReader::Object(const char* key, const std::function<void(JsonReader&)>& read) {
  const auto* v = Find(key);
  if (!v) return;
  if (!v->is_object()) Fail(key, std::string("expected an object, got ") + v->type_name());
  JsonReader child(*v, where_, FieldPath(key), lines_);
  read(child);
  child.RejectUnknown();
}

void JsonReader::RejectUnknown() const {
  for (const auto& [key, value] : json_.items()) {
    if (!known_.count(key)) {
      std::string known;
      for (const auto& k : known_) known += (known.empty() ? "" : ", ") + k;
      Fail(key, "unknown key (known here: " + known + ")");
    }
  }
}

nlohmann::json ParseJsonText(const std::string& text, const std::string& where) {
  try {
    return nlohmann::json::parse(text);
  } catch (const nlohmann::json::parse_error& e) {
    // Turn nlohmann's byte offset into a line and column a person can go to.
    const std::size_t at = std::min<std::size_t>(e.byte > 0 ? e.byte - 1 : 0, text.size());
    int line = 1, col = 1;
    for (std::size_t i = 0; i < at; ++i) {
      if (text[i] == '\n') {
        ++line;
        col = 1;
      } else {
        ++col;
      }
    }
    std::string msg = e.what();
    const auto pos = msg.find("parse error");
    if (pos != std::string::npos) msg = msg.substr(pos);
    throw ConfigError(where + ":" + std::to_string(line) + ":" + std::to_string(col) +
                      ": invalid JSON: " + msg);
  }
}

nlohmann::json ParseJsonFile(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw ConfigError(path + ": cannot open the configuration file");
  std::stringstream ss;
  ss << in.rdbuf();
  return ParseJsonText(ss.str(), path);
}

}  // namespace gs360
