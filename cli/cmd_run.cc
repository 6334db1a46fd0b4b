// `gs360 run start|list|status|pause|resume|cancel|delete|log`: runs on gs360d, through its API.

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <fstream>
#include <optional>
#include <sstream>

#include "base/json_reader.h"
#include "base/text.h"
#include "cli/commands.h"
#include "cli/daemon_client.h"
#include "cli/run_view.h"

namespace gs360::cli {
namespace {

using Json = nlohmann::json;

struct StartArgs {
  std::string request;
  std::string name;
  std::string shape;
  // As typed: the daemon checks every number of a request, in one place, and names its range.
  std::string probes;
  std::string mesh;
  std::string seed;
  bool plan_only = false;
  bool until_converged = false;
  bool watch = false;
  std::string confirm;
};

void PrintJson(const Json& j) {
  std::printf("%s\n", j.dump(2).c_str());
}

// A number flag as the request's value: the number when the text is one (JSON: "40", "-3",
// "2.5", "1e9"), else the text itself, which the daemon refuses naming the field and its range.
Json NumberArgument(const std::string& text) {
  const Json number = Json::parse(text, nullptr, false);
  return number.is_number() ? number : Json(text);
}

// Uploads --mesh FILE; every error names FILE as the user gave it (not the daemon's copy).
Json UploadMesh(DaemonClient& client, const std::string& file) {
  std::error_code ec;
  if (std::filesystem::is_directory(file, ec)) {
    throw ClientError("--mesh " + file + ": is a folder, not a mesh file (STL, OBJ or PLY)",
                      kExitUsage);
  }
  std::string ext = std::filesystem::path(file).extension().string();
  if (!ext.empty()) ext = ext.substr(1);
  for (char& c : ext) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  if (ext != "stl" && ext != "obj" && ext != "ply") {
    throw ClientError("--mesh " + file +
                          ": its extension names the format: expected .stl, .obj "
                          "or .ply, got \"" +
                          std::filesystem::path(file).extension().string() + "\"",
                      kExitUsage);
  }
  std::ifstream in(file, std::ios::binary);
  std::stringstream bytes;
  if (!in) throw ClientError("--mesh: cannot read " + file, kExitUsage);
  bytes << in.rdbuf();
  try {
    return client.PostBytes("/api/v1/meshes?format=" + ext, bytes.str());
  } catch (const ClientError& e) {
    std::string why = e.what();
    const std::string daemons = "the uploaded mesh";  // the daemon's name for its copy
    for (std::size_t at = 0; (at = why.find(daemons, at)) != std::string::npos;) {
      why.replace(at, daemons.size(), file);
      at += file.size();
    }
    if (why.rfind("mesh: ", 0) == 0) why = why.substr(6);
    throw ClientError("--mesh " + file + ": " + why, e.exit_code(), e.http_status(), "mesh");
  }
}

// The request body: the file (an API request, docs/api.md), then the flags on top.
Json StartRequest(DaemonClient& client, const StartArgs& a) {
  Json request = a.request.empty() ? Json::object() : ParseJsonFile(a.request);
  if (!request.is_object()) throw ConfigError(a.request + ": expected a JSON object");
  if (!a.name.empty()) request["name"] = a.name;
  if (!a.shape.empty()) request["shape"] = {{"type", a.shape}};
  if (!a.probes.empty()) request["probes"] = NumberArgument(a.probes);
  if (!a.seed.empty()) request["plan"]["seed"] = NumberArgument(a.seed);
  if (a.plan_only) request["plan_only"] = true;
  if (a.until_converged) request["until_converged"] = true;
  if (!a.mesh.empty()) {
    const Json mesh = UploadMesh(client, a.mesh);
    std::fprintf(stderr, "uploaded %s: mesh %s, %lld triangles\n", a.mesh.c_str(),
                 mesh["id"].get<std::string>().c_str(), mesh["triangles"].get<long long>());
    request["mesh"] = mesh["id"];
    request.erase("shape");
  }
  return request;
}

// `run start 7`: the positional names a created run rather than a request file when it is a
// number (a request file so named is `./7`).
std::optional<std::int64_t> RunIdArgument(const std::string& arg) {
  if (arg.empty() || arg.size() > 18 || arg.find_first_not_of("0123456789") != std::string::npos) {
    return std::nullopt;
  }
  return std::stoll(arg);
}

// Starts run `id`, then prints what the daemon said and follows it with --watch.
void StartRun(DaemonClient& client, CommandContext& ctx, const StartArgs& a, std::int64_t id,
              const Json& created) {
  Json body = Json::object();
  if (!a.confirm.empty()) body["confirm"] = a.confirm;
  Json started;
  try {
    started = client.Post("/api/v1/runs/" + std::to_string(id) + "/start", body);
  } catch (const ClientError& e) {
    if (created.is_null()) throw;
    // The run exists now: say which, and what to do with it, rather than leave it unnamed.
    const std::string ids = std::to_string(id);
    if (ctx.json) {
      PrintJson(
          {{"run", created}, {"start", {{"error", e.what()}, {"http_status", e.http_status()}}}});
    }
    throw ClientError("run " + ids + " created but not started: " + e.what() +
                          ". Start it later with `gs360 run start " + ids +
                          "` or delete it with `gs360 run delete " + ids + "`",
                      e.exit_code(), e.http_status(), e.field());
  }
  if (ctx.json) {
    PrintJson(created.is_null() ? started : Json{{"run", created}, {"start", started}});
  } else {
    std::printf("run %lld %s\n", static_cast<long long>(id),
                started["message"].get<std::string>().c_str());
  }
  if (a.watch) ctx.exit_code = ExitCodeOfRun(WatchRun(client, id, stdout, stderr));
}

void RegisterStart(CLI::App& run, CommandContext& ctx) {
  static StartArgs a;
  auto* start = run.add_subcommand(
      "start", "Plan a new run on the daemon's rig and start it (or only plan it)");
  start->add_option("request", a.request,
                    "A run request (JSON, as POST /api/v1/runs; flags below override it), or the "
                    "id of a created run to start (`run start 7 --confirm position`)");
  start->add_option("--name", a.name, "Run name");
  start->add_option("--shape", a.shape, "Built-in sensor: cylinder, cone or spline");
  start->add_option("--probes", a.probes, "Candidate points sampled on the sensor (1..1000000)");
  start->add_option("--mesh", a.mesh, "Sensor mesh (STL, OBJ, PLY; sensor frame, mm) to upload");
  start->add_option("--seed", a.seed, "Sampling seed (0..18446744073709551615)");
  start->add_flag("--plan-only", a.plan_only, "Plan and print the estimate; store nothing");
  start->add_flag("--until-converged", a.until_converged,
                  "Probe in rounds, calibrate after each in the background, and end the run once "
                  "the held-out error meets every target and has stopped improving");
  start->add_flag("--watch", a.watch, "Follow the run with a progress bar until it stops");
  start
      ->add_option("--confirm", a.confirm,
                   "With a run id: what you have checked, answering the question the run "
                   "asked (`run status` shows it): position or sensor")
      ->check(CLI::IsMember({"position", "sensor"}));
  start->callback([&ctx, start] {
    DaemonClient client(ctx.daemon_url, ctx.token);
    if (const auto id = RunIdArgument(a.request)) {
      for (const char* option : {"--name", "--shape", "--probes", "--mesh", "--seed", "--plan-only",
                                 "--until-converged"}) {
        if (start->count(option) > 0) {
          throw ClientError(std::string(option) + " plans a new run; run " + a.request +
                                " exists: `gs360 run start " + a.request + "` starts it as planned",
                            kExitUsage);
        }
      }
      return StartRun(client, ctx, a, *id, nullptr);
    }
    // Nothing has asked yet: a confirmation here would be refused after the run was created.
    if (!a.confirm.empty()) {
      throw ClientError(
          "--confirm answers what a run asked (`gs360 run status ID` shows it); a "
          "new run has asked nothing. Start it without --confirm, and if it asks, "
          "`gs360 run start ID --confirm " +
              a.confirm + "`",
          kExitUsage);
    }
    const Json created = client.Post("/api/v1/runs", StartRequest(client, a));
    if (a.plan_only) {
      ctx.json ? PrintJson(created) : PrintPlan(stdout, created);
      return;
    }
    const std::int64_t id = created["id"].get<std::int64_t>();
    if (!ctx.json) {
      std::printf("created run %lld (%s)\n", static_cast<long long>(id),
                  created["name"].get<std::string>().c_str());
      PrintPlan(stdout, created["plan"]);
    }
    StartRun(client, ctx, a, id, created);
  });
}

void RegisterStatus(CLI::App& run, CommandContext& ctx) {
  static std::int64_t id = 0;
  static bool watch = false;
  auto* status = run.add_subcommand("status", "Progress of one run, or of every run");
  status->add_option("run", id, "Run id (default: every run)");
  status->add_flag("--watch", watch, "Follow the run with a progress bar until it stops");
  status->callback([&ctx] {
    DaemonClient client(ctx.daemon_url, ctx.token);
    if (id == 0) {
      const Json runs = client.Get("/api/v1/runs");
      if (ctx.json) return PrintJson(runs);
      if (runs["runs"].empty()) std::printf("no runs\n");
      for (const Json& r : runs["runs"]) PrintRun(stdout, r);
      return;
    }
    if (watch) {
      const Json last = WatchRun(client, id, ctx.json ? stderr : stdout, stderr);
      if (ctx.json) PrintJson(last);
      ctx.exit_code = ExitCodeOfRun(last);
      return;
    }
    const Json r = client.Get("/api/v1/runs/" + std::to_string(id));
    ctx.json ? PrintJson(r) : PrintRun(stdout, r);
  });
  auto* list = run.add_subcommand("list", "Every run, one line each");
  list->callback([&ctx] {
    DaemonClient client(ctx.daemon_url, ctx.token);
    const Json runs = client.Get("/api/v1/runs");
    if (ctx.json) return PrintJson(runs);
    if (runs["runs"].empty()) std::printf("no runs\n");
    for (const Json& r : runs["runs"]) PrintRun(stdout, r);
  });
}

// What an accepted resume came to. Without --watch: 0 once the run is pressing probes again;
// a run that stopped at once, above all to ask again what it asked before (the position, the
// sensor), is printed with its question and the command that answers it, and its exit code
// (kExitAwaiting for a question) says so. With --watch: followed to its end, as `run start`.
int FollowResume(DaemonClient& client, const CommandContext& ctx, std::int64_t id, bool watch) {
  std::FILE* out = ctx.json ? stderr : stdout;
  if (watch) return ExitCodeOfRun(WatchRun(client, id, out, stderr));
  const Json run = FollowPastChecks(client, id);
  if (RunIsActive(run)) return kExitOk;
  PrintRun(out, run);
  return ExitCodeOfRun(run);
}

void RegisterAction(CLI::App& run, CommandContext& ctx, const std::string& action,
                    const std::string& help) {
  static std::map<std::string, std::int64_t> ids;
  static std::map<std::string, std::string> confirms;
  static bool watch = false;  // resume only
  auto* cmd = run.add_subcommand(action, help);
  cmd->add_option("run", ids[action], "Run id")->required();
  if (action == "resume") {
    cmd->add_option("--confirm", confirms[action],
                    "What you have checked, answering the run's question (`run status` shows "
                    "it): position or sensor")
        ->check(CLI::IsMember({"position", "sensor"}));
    cmd->add_flag("--watch", watch, "Follow the run with a progress bar until it stops");
  }
  cmd->callback([&ctx, action] {
    DaemonClient client(ctx.daemon_url, ctx.token);
    const std::string path = "/api/v1/runs/" + std::to_string(ids[action]);
    if (action == "delete") {
      client.Delete(path);
      if (ctx.json) return PrintJson({{"id", ids[action]}, {"state", "deleted"}});
      std::printf("run %lld deleted\n", static_cast<long long>(ids[action]));
      return;
    }
    Json body = Json::object();
    if (!confirms[action].empty()) body["confirm"] = confirms[action];
    const Json r = client.Post(path + "/" + action, body);
    if (ctx.json) {
      PrintJson(r);
    } else {
      std::printf("run %lld: %s\n", static_cast<long long>(ids[action]),
                  r["message"].get<std::string>().c_str());
    }
    if (action == "resume") ctx.exit_code = FollowResume(client, ctx, ids[action], watch);
  });
}

// "2025-03-14 09:26:53.589", local time, for a log line.
std::string LocalTime(double unix_s) {
  const auto whole = static_cast<std::time_t>(std::floor(unix_s));
  std::tm tm{};
  localtime_r(&whole, &tm);
  char buf[40];
  const auto ms = static_cast<int>(std::min(999.0, std::floor((unix_s - whole) * 1000.0)));
  const std::size_t n = std::strftime(buf, sizeof buf, "%Y-%m-%d %H:%M:%S", &tm);
  std::snprintf(buf + n, sizeof buf - n, ".%03d", ms);
  return buf;
}

void RegisterLog(CLI::App& run, CommandContext& ctx) {
  static std::int64_t id = 0;
  auto* log = run.add_subcommand("log", "A run's log: state changes, warnings, alarms");
  log->add_option("run", id, "Run id")->required();
  log->callback([&ctx] {
    DaemonClient client(ctx.daemon_url, ctx.token);
    std::int64_t after = 0;
    Json all = Json::array();
    for (;;) {
      const Json page =
          client.Get("/api/v1/runs/" + std::to_string(id) + "/log?after=" + std::to_string(after));
      if (page["events"].empty()) break;
      for (const Json& e : page["events"]) all.push_back(e);
      after = page["events"].back()["id"].get<std::int64_t>();
    }
    if (ctx.json) return PrintJson({{"run", id}, {"events", all}});
    for (const Json& e : all) {
      const double time = e.contains("time") && e["time"].is_number() ? e["time"].get<double>() : 0;
      std::printf("%s %-7s %s\n", LocalTime(time).c_str(), e["level"].get<std::string>().c_str(),
                  EscapeControlCharacters(e["message"].get<std::string>()).c_str());
    }
  });
}

}  // namespace

void RegisterRunCommands(CLI::App& app, CommandContext& ctx) {
  auto* run = app.add_subcommand("run", "Runs on gs360d: start, follow, pause, resume, cancel");
  run->require_subcommand(1);
  RegisterStart(*run, ctx);
  RegisterStatus(*run, ctx);
  RegisterAction(*run, ctx, "pause", "Pause after the current probe (retracted, holding)");
  RegisterAction(*run, ctx, "resume",
                 "Continue a paused or interrupted run (reconnects, re-checks, goes on)");
  RegisterAction(*run, ctx, "cancel", "End a run after the current probe and park; data is kept");
  RegisterAction(*run, ctx, "delete", "Remove a run that is not running, and all its data");
  RegisterLog(*run, ctx);
}

}  // namespace gs360::cli
