#include "daemon/daemon_config.h"

#include <arpa/inet.h>

#include <cmath>
#include <fstream>
#include <sstream>

#include <toml++/toml.h>
#include <nlohmann/json.hpp>

#include "base/json_reader.h"

namespace gs360 {
namespace {

[[noreturn]] void Invalid(const std::string& field, const std::string& value,
                          const std::string& rule) {
  throw ConfigError(field + " " + rule + ", got " + value, field);
}

// TOML -> JSON, recording each key's line so that the strict reader's errors can name it.
nlohmann::json ToJson(const toml::node& node, const std::string& path, SourceLines& lines,
                      const std::string& where) {
  if (!path.empty()) lines.emplace(path, static_cast<int>(node.source().begin.line));
  if (const toml::table* t = node.as_table()) {
    nlohmann::json out = nlohmann::json::object();
    for (const auto& [key, value] : *t) {
      const std::string k(key.str());
      out[k] = ToJson(value, path.empty() ? k : path + "." + k, lines, where);
    }
    return out;
  }
  if (const toml::array* a = node.as_array()) {
    nlohmann::json out = nlohmann::json::array();
    // A table in a list ([[notify]]) is named by its index, so that its keys have their lines.
    std::size_t i = 0;
    for (const toml::node& e : *a) {
      out.push_back(
          ToJson(e, e.is_table() ? path + "[" + std::to_string(i) + "]" : path, lines, where));
      ++i;
    }
    return out;
  }
  if (const auto* v = node.as_integer()) return v->get();
  if (const auto* v = node.as_floating_point()) return v->get();
  if (const auto* v = node.as_boolean()) return v->get();
  if (const auto* v = node.as_string()) return v->get();
  throw ConfigError(where + ":" + std::to_string(node.source().begin.line) + ": " + path +
                        ": dates and times are not used in this file",
                    path);
}

std::filesystem::path Resolve(const std::filesystem::path& base, const std::string& p) {
  if (p.empty() || base.empty()) return p;
  const std::filesystem::path path(p);
  return path.is_absolute() ? path : base / path;
}

// JSON -> TOML for --print-config (the file format users edit).
void PushToml(toml::array& a, const nlohmann::json& v);
void PutToml(toml::table& t, const std::string& k, const nlohmann::json& v) {
  if (v.is_object()) {
    toml::table sub;
    for (const auto& [key, e] : v.items()) PutToml(sub, key, e);
    t.insert(k, std::move(sub));
  } else if (v.is_array()) {
    toml::array sub;
    for (const auto& e : v) PushToml(sub, e);
    t.insert(k, std::move(sub));
  } else if (v.is_boolean()) {
    t.insert(k, v.get<bool>());
  } else if (v.is_number_integer()) {
    t.insert(k, v.get<std::int64_t>());
  } else if (v.is_number()) {
    t.insert(k, v.get<double>());
  } else {
    t.insert(k, v.get<std::string>());
  }
}
void PushToml(toml::array& a, const nlohmann::json& v) {
  if (v.is_array()) {
    toml::array sub;
    for (const auto& e : v) PushToml(sub, e);
    a.push_back(std::move(sub));
  } else if (v.is_number_integer()) {
    a.push_back(v.get<std::int64_t>());
  } else if (v.is_number()) {
    a.push_back(v.get<double>());
  } else if (v.is_boolean()) {
    a.push_back(v.get<bool>());
  } else {
    a.push_back(v.get<std::string>());
  }
}

void ReadDaemon(JsonReader& r, DaemonConfig& c, const std::function<void(JsonReader&)>& read_sim) {
  std::string data_dir = c.data_dir.string();
  r.Get("data_dir", data_dir);
  c.data_dir = data_dir;
  r.Object("server", [&](JsonReader& o) {
    o.Get("listen", c.server.listen);
    o.Get("port", c.server.port);
    o.Get("token", c.server.token);
    o.Get("max_body_bytes", c.server.max_body_bytes);
    o.Get("max_upload_bytes", c.server.max_upload_bytes);
    o.Get("threads", c.server.threads);
    o.Get("max_connections", c.server.max_connections);
    o.Get("max_event_streams", c.server.max_event_streams);
    o.Get("request_timeout_s", c.server.request_timeout_s);
    o.Get("idle_timeout_s", c.server.idle_timeout_s);
  });
  r.Object("log", [&](JsonReader& o) {
    o.Get("level", c.log.level);
    o.Get("file_max_bytes", c.log.file_max_bytes);
    o.Get("files", c.log.files);
  });
  r.Object("limits", [&](JsonReader& o) {
    o.Get("envelope_min", c.limits.envelope_min);
    o.Get("envelope_max", c.limits.envelope_max);
    o.Get("max_press_depth", c.limits.max_press_depth);
    o.Get("max_feed_mm_per_min", c.limits.max_feed_mm_per_min);
  });
  r.Object("calibration", [&](JsonReader& o) {
    o.Get("checkerboards", c.calibration.checkerboards);
    o.Get("threads", c.calibration.threads);
  });
  r.Objects("notify", [&](JsonReader& o, std::size_t) {
    NotifyTarget t;
    o.Get("url", t.url);
    o.Get("command", t.command);
    o.Get("format", t.format);
    o.Get("events", t.events);
    o.Get("timeout_s", t.timeout_s);
    o.Get("retries", t.retries);
    o.Get("backoff_s", t.backoff_s);
    o.Get("queue_size", t.queue_size);
    o.Get("attach_frame", t.attach_frame);
    c.notify.push_back(std::move(t));
  });
  ReadRunConfig(r, c.run);
  if (read_sim) {
    r.Object("sim", read_sim);
  } else {
    r.Raw("sim");  // the virtual rig's, not gs360d's
  }
}

}  // namespace

void ServerConfig::Check() const {
  if (listen.empty()) Invalid("server.listen", "\"\"", "must be an address to bind");
  if (port < 0 || port > 65535) Invalid("server.port", std::to_string(port), "must be in 0..65535");
  if (max_body_bytes < 1024) {
    Invalid("server.max_body_bytes", std::to_string(max_body_bytes), "must be >= 1024");
  }
  if (max_upload_bytes < max_body_bytes) {
    Invalid("server.max_upload_bytes", std::to_string(max_upload_bytes),
            "must be >= server.max_body_bytes (" + std::to_string(max_body_bytes) + ")");
  }
  if (threads < 1 || threads > 256) {
    Invalid("server.threads", std::to_string(threads), "must be in 1..256");
  }
  if (max_connections < 16 || max_connections > 65536) {
    Invalid("server.max_connections", std::to_string(max_connections), "must be in 16..65536");
  }
  if (max_event_streams < 1 || max_event_streams > max_connections) {
    Invalid("server.max_event_streams", std::to_string(max_event_streams),
            "must be in 1..server.max_connections (" + std::to_string(max_connections) + ")");
  }
  if (!(request_timeout_s >= 0.1 && request_timeout_s <= 3600)) {
    Invalid("server.request_timeout_s", std::to_string(request_timeout_s), "must be in 0.1..3600");
  }
  if (idle_timeout_s < 1 || idle_timeout_s > 3600) {
    Invalid("server.idle_timeout_s", std::to_string(idle_timeout_s), "must be in 1..3600");
  }
  if (!token.empty() && token.size() < 16) {
    Invalid("server.token", "a token of " + std::to_string(token.size()) + " characters",
            "must be at least 16 characters");
  }
}

void LogConfig::Check() const {
  if (level != "trace" && level != "debug" && level != "info" && level != "warn" &&
      level != "error") {
    Invalid("log.level", "\"" + level + "\"", "must be trace, debug, info, warn or error");
  }
  if (file_max_bytes < 4096) {
    Invalid("log.file_max_bytes", std::to_string(file_max_bytes), "must be >= 4096");
  }
  if (files < 1 || files > 100) Invalid("log.files", std::to_string(files), "must be in 1..100");
}

void CalibrationDefaults::Check() const {
  if (threads < 1 || threads > 256) {
    Invalid("calibration.threads", std::to_string(threads), "must be in 1..256");
  }
}

void DaemonConfig::Check() const {
  if (data_dir.empty()) Invalid("data_dir", "\"\"", "must name a folder");
  server.Check();
  log.Check();
  limits.Check();
  calibration.Check();
  try {
    CheckNotifyTargets(notify);
  } catch (const std::invalid_argument& e) {
    // "notify[1].url must ...": that field, for the file's line.
    const std::string what = e.what();
    throw ConfigError(what, what.substr(0, what.find_first_of(" :")));
  }
  if (!server.token.empty() || IsLoopbackAddress(server.listen)) {
    // fine
  } else {
    throw ConfigError("server.listen = \"" + server.listen +
                          "\" is not a loopback address: set server.token (or GS360D_TOKEN) "
                          "so that only holders of the token can reach the API",
                      "server.listen");
  }
  // The run defaults without the connection URIs (a daemon may start without a machine).
  RunConfig run_check = run;
  if (run_check.machine.uri.empty()) run_check.machine.uri = "unset";
  if (run_check.camera.uri.empty()) run_check.camera.uri = "unset";
  try {
    run_check.Check();
  } catch (const std::invalid_argument& e) {
    // The field ("machine.baud") lets DaemonConfigFromToml name the file's line.
    throw ConfigError(e.what(), RunConfigField(e.what()));
  }
}

DaemonConfig DaemonConfigFromToml(std::string_view text, const std::string& where,
                                  const std::filesystem::path& base_dir,
                                  const std::function<void(JsonReader&)>& read_sim) {
  toml::table table;
  try {
    table = toml::parse(text, where);
  } catch (const toml::parse_error& e) {
    throw ConfigError(where + ":" + std::to_string(e.source().begin.line) + ":" +
                      std::to_string(e.source().begin.column) +
                      ": invalid TOML: " + std::string(e.description()));
  }
  SourceLines lines;
  const nlohmann::json json = ToJson(table, "", lines, where);
  DaemonConfig c;
  JsonReader r(json, where, "", &lines);
  ReadDaemon(r, c, read_sim);
  r.RejectUnknown();
  c.data_dir = Resolve(base_dir, c.data_dir.string());
  c.run.rig.mesh_path = Resolve(base_dir, c.run.rig.mesh_path).string();
  c.calibration.checkerboards = Resolve(base_dir, c.calibration.checkerboards).string();
  try {
    c.Check();
  } catch (const ConfigError& e) {
    // Name the line of the offending key when the file has it.
    const std::string field = e.field();
    throw ConfigError(WhereField(where, &lines, field) + ": " + e.what(), field);
  }
  return c;
}

DaemonConfig LoadDaemonConfig(const std::filesystem::path& path,
                              const std::function<void(JsonReader&)>& read_sim) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw ConfigError(path.string() + ": cannot open the configuration file");
  std::stringstream ss;
  ss << in.rdbuf();
  return DaemonConfigFromToml(ss.str(), path.string(), path.parent_path(), read_sim);
}

std::string DaemonConfigToToml(const DaemonConfig& c, bool keep_secrets) {
  nlohmann::json j = RunConfigToJson(c.run);
  j.erase("name");
  j["data_dir"] = c.data_dir.string();
  j["server"] = {{"listen", c.server.listen},
                 {"port", c.server.port},
                 {"token", keep_secrets || c.server.token.empty() ? c.server.token : "(set)"},
                 {"max_body_bytes", c.server.max_body_bytes},
                 {"max_upload_bytes", c.server.max_upload_bytes},
                 {"threads", c.server.threads},
                 {"max_connections", c.server.max_connections},
                 {"max_event_streams", c.server.max_event_streams},
                 {"request_timeout_s", c.server.request_timeout_s},
                 {"idle_timeout_s", c.server.idle_timeout_s}};
  j["log"] = {
      {"level", c.log.level}, {"file_max_bytes", c.log.file_max_bytes}, {"files", c.log.files}};
  const auto vec = [](const Eigen::Vector3d& v) { return nlohmann::json{v.x(), v.y(), v.z()}; };
  j["limits"] = {{"envelope_min", vec(c.limits.envelope_min)},
                 {"envelope_max", vec(c.limits.envelope_max)},
                 {"max_press_depth", c.limits.max_press_depth},
                 {"max_feed_mm_per_min", c.limits.max_feed_mm_per_min}};
  j["calibration"] = {{"checkerboards", c.calibration.checkerboards},
                      {"threads", c.calibration.threads}};
  // Webhook URLs keep their secrets in the path: unless asked, only the scheme and host.
  toml::array notify;
  for (const NotifyTarget& t : c.notify) {
    toml::table n;
    if (!t.url.empty()) n.insert("url", keep_secrets ? t.url : t.RedactedUrl());
    if (!t.command.empty()) {
      toml::array argv;
      for (const std::string& a : t.command) argv.push_back(a);
      n.insert("command", std::move(argv));
    }
    n.insert("format", t.format);
    toml::array events;
    for (const std::string& e : t.events) events.push_back(e);
    n.insert("events", std::move(events));
    n.insert("timeout_s", t.timeout_s);
    n.insert("retries", t.retries);
    n.insert("backoff_s", t.backoff_s);
    n.insert("queue_size", t.queue_size);
    n.insert("attach_frame", t.attach_frame);
    notify.push_back(std::move(n));
  }
  toml::table root;
  for (const auto& [k, v] : j.items()) PutToml(root, k, v);
  if (!notify.empty()) root.insert("notify", std::move(notify));
  std::ostringstream os;
  os << root << "\n";
  return os.str();
}

bool IsLoopbackAddress(std::string_view address) {
  if (address == "localhost" || address == "::1") return true;
  in_addr v4{};
  const std::string a(address);
  if (inet_pton(AF_INET, a.c_str(), &v4) == 1) {
    return (ntohl(v4.s_addr) >> 24) == 127;
  }
  return false;
}

}  // namespace gs360
