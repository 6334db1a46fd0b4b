#pragma once
// Strict reading of JSON configuration and requests: every key known, every type checked, every
// error naming the source, the field path and, when the document came from a file whose lines
// are known (a TOML file converted to JSON, see SourceLines), the line.

#include <Eigen/Core>
#include <functional>
#include <map>
#include <set>
#include <stdexcept>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

namespace gs360 {

// A configuration or request that cannot be used. field() is the dotted field path ("" when the
// problem is the document as a whole); what() is the whole message, naming the source and field.
class ConfigError : public std::runtime_error {
 public:
  explicit ConfigError(const std::string& message, std::string field = "")
      : std::runtime_error(message), field_(std::move(field)) {}
  const std::string& field() const { return field_; }

 private:
  std::string field_;
};

// Line numbers of the fields of a document that was not JSON text (a TOML file): dotted field
// path -> 1-based line. A path absent from the map falls back to its nearest listed parent.
using SourceLines = std::map<std::string, int>;

// The values a numeric field accepts: [min, max], or (min, max] when min_open; `unit` ("mm") is
// named in the error. Text(): "1..1000000" for integers, "(0, 100] mm" for numbers.
struct IntRange {
  int min = 0;
  int max = 0;
  std::string Text() const;
};
struct NumberRange {
  double min = 0.0;
  double max = 0.0;
  bool min_open = false;
  const char* unit = "";
  std::string Text() const;
};

class JsonReader {
 public:
  // `json` (and `lines`, if given) must outlive the reader. `path` is the field path of this
  // object ("" at the root).
  JsonReader(const nlohmann::json& json, std::string where, std::string path = "",
             const SourceLines* lines = nullptr);

  // Each getter leaves `out` unchanged when the key is absent.
  void Get(const char* key, double& out);
  void Get(const char* key, int& out);
  void Get(const char* key, std::int64_t& out);
  void Get(const char* key, std::uint64_t& out);
  void Get(const char* key, bool& out);
  void Get(const char* key, std::string& out);
  void Get(const char* key, Eigen::Vector3d& out);
  void Get(const char* key, std::vector<double>& out);
  void Get(const char* key, std::vector<int>& out);
  void Get(const char* key, std::vector<std::string>& out);
  // A number from a user, in its field's range: anything else (a string, a fraction or a float
  // such as 2e9 for an integer, a value outside) fails naming the range, e.g. "plan.probe_count:
  // expected an integer in 1..1000000, got 2000000000". Checked here, as the value is read, so
  // that no out-of-range value reaches code that allocates or loops by it.
  void Get(const char* key, int& out, const IntRange& range);
  void Get(const char* key, double& out, const NumberRange& range);
  void Get(const char* key, Eigen::Vector3d& out, const NumberRange& range);  // each coordinate
  // Nested object: calls `read` with a reader for it when present.
  void Object(const char* key, const std::function<void(JsonReader&)>& read);
  // A list of objects (TOML's [[key]] tables): calls `read` with a reader for each and its index;
  // their fields are named "key[i].field".
  void Objects(const char* key, const std::function<void(JsonReader&, std::size_t)>& read);
  const nlohmann::json* Raw(const char* key);  // marks the key as known; nullptr if absent

  // Throws ConfigError for keys that no getter asked for (typos must not pass silently).
  void RejectUnknown() const;
  [[noreturn]] void Fail(const std::string& key, const std::string& what) const;
  std::string FieldPath(const std::string& key) const;
  const std::string& where() const { return where_; }

 private:
  const nlohmann::json* Find(const char* key);

  const nlohmann::json& json_;
  std::string where_;
  std::string path_;
  const SourceLines* lines_;
  std::set<std::string> known_;
};

// "where:LINE" for a field path of a document with known lines, else "where".
std::string WhereField(const std::string& where, const SourceLines* lines, const std::string& path);

// Parses a JSON file; syntax errors name the file, line and column. Throws ConfigError.
nlohmann::json ParseJsonFile(const std::string& path);
nlohmann::json ParseJsonText(const std::string& text, const std::string& where);

}  // namespace gs360
