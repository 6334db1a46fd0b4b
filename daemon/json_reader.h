#pragma once
// Strict reading of JSON configuration: every key known, every type checked, every error naming
// the source and the field path. Shared by the rig and run configurations.

#include <Eigen/Core>
#include <functional>
#include <set>
#include <stdexcept>
#include <string>

#include <nlohmann/json.hpp>

namespace gs360 {

class ConfigError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

class JsonReader {
 public:
  // `json` must outlive the reader. `path` is the field path of this object ("" at the root).
  JsonReader(const nlohmann::json& json, std::string where, std::string path = "");

  // Each getter leaves `out` unchanged when the key is absent.
  void Get(const char* key, double& out);
  void Get(const char* key, int& out);
  void Get(const char* key, std::uint64_t& out);
  void Get(const char* key, bool& out);
  void Get(const char* key, std::string& out);
  void Get(const char* key, Eigen::Vector3d& out);
  // Nested object: calls `read` with a reader for it when present.
  void Object(const char* key, const std::function<void(JsonReader&)>& read);
  const nlohmann::json* Raw(const char* key);  // marks the key as known; nullptr if absent

  // Throws ConfigError for keys that no getter asked for (typos must not pass silently).
  void RejectUnknown() const;
  [[noreturn]] void Fail(const std::string& key, const std::string& what) const;
  std::string FieldPath(const std::string& key) const;

 private:
  const nlohmann::json* Find(const char* key);

  const nlohmann::json& json_;
  std::string where_;
  std::string path_;
  std::set<std::string> known_;
};

// Parses a JSON file; syntax errors name the file, line and column. Throws ConfigError.
nlohmann::json ParseJsonFile(const std::string& path);
nlohmann::json ParseJsonText(const std::string& text, const std::string& where);

}  // namespace gs360
