// `gs360 run start|list|status|pause|resume|cancel|delete|log`: runs on gs360d, through its API.

#include <cstdio>
#include <fstream>
#include <sstream>

#include "base/json_reader.h"
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
  int probes = 0;
  std::string mesh;
  std::int64_t seed = -1;
  bool plan_only = false;
  bool until_converged = false;
  bool watch = false;
  std::string confirm;
};

void PrintJson(const Json& j) {
  std::printf("%s\n", j.dump(2).c_str());
}

// The request body: the file (an API request, docs/api.md), then the flags on top.
Json StartRequest(DaemonClient& client, const StartArgs& a) {
  Json request = a.request.empty() ? Json::object() : ParseJsonFile(a.request);
  if (!request.is_object()) throw ConfigError(a.request + ": expected a JSON object");
  if (!a.name.empty()) request["name"] = a.name;
  if (!a.shape.empty()) request["shape"] = {{"type", a.shape}};
  if (a.probes > 0) request["probes"] = a.probes;
  if (a.seed >= 0) request["plan"]["seed"] = a.seed;
  if (a.plan_only) request["plan_only"] = true;
  if (a.until_converged) request["until_converged"] = true;
  if (!a.mesh.empty()) {
    std::ifstream in(a.mesh, std::ios::binary);
    if (!in) throw ClientError("--mesh: cannot read " + a.mesh, kExitUsage);
    std::stringstream bytes;
    bytes << in.rdbuf();
    std::string ext = std::filesystem::path(a.mesh).extension().string();
    if (!ext.empty()) ext = ext.substr(1);
    for (char& c : ext) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
    const Json mesh = client.PostBytes("/api/v1/meshes?format=" + ext, bytes.str());
    std::fprintf(stderr, "uploaded %s: mesh %s, %lld triangles\n", a.mesh.c_str(),
                 mesh["id"].get<std::string>().c_str(), mesh["triangles"].get<long long>());
    request["mesh"] = mesh["id"];
    request.erase("shape");
  }
  return request;
}

void RegisterStart(CLI::App& run, CommandContext& ctx) {
  static StartArgs a;
  auto* start = run.add_subcommand(
      "start", "Plan a new run on the daemon's rig and start it (or only plan it)");
  start->add_option("request", a.request,
                    "A run request (JSON, as POST /api/v1/runs; flags below override it)");
  start->add_option("--name", a.name, "Run name");
  start->add_option("--shape", a.shape, "Built-in sensor: cylinder, cone or spline");
  start->add_option("--probes", a.probes, "Candidate points sampled on the sensor");
  start->add_option("--mesh", a.mesh, "Sensor mesh (STL, OBJ, PLY; sensor frame, mm) to upload");
  start->add_option("--seed", a.seed, "Sampling seed");
  start->add_flag("--plan-only", a.plan_only, "Plan and print the estimate; store nothing");
  start->add_flag("--until-converged", a.until_converged,
                  "Probe in rounds, calibrate after each in the background, and end the run once "
                  "the held-out error meets every target and has stopped improving");
  start->add_flag("--watch", a.watch, "Follow the run with a progress bar until it stops");
  start
      ->add_option("--confirm", a.confirm,
                   "What you have checked, when the run asks (e.g. on a machine without "
                   "homing: position)")
      ->check(CLI::IsMember({"position", "sensor"}));
  start->callback([&ctx] {
    DaemonClient client(ctx.daemon_url, ctx.token);
    const Json created = client.Post("/api/v1/runs", StartRequest(client, a));
    if (a.plan_only) {
      ctx.json ? PrintJson(created) : PrintPlan(stdout, created);
      return;
    }
    const std::int64_t id = created["id"].get<std::int64_t>();
    Json body = Json::object();
    if (!a.confirm.empty()) body["confirm"] = a.confirm;
    const Json started = client.Post("/api/v1/runs/" + std::to_string(id) + "/start", body);
    if (ctx.json) {
      PrintJson({{"run", created}, {"start", started}});
    } else {
      std::printf("created run %lld (%s)\n", static_cast<long long>(id),
                  created["name"].get<std::string>().c_str());
      PrintPlan(stdout, created["plan"]);
      std::printf("run %lld %s\n", static_cast<long long>(id),
                  started["message"].get<std::string>().c_str());
    }
    if (a.watch) ctx.exit_code = ExitCodeOfRun(WatchRun(client, id, stdout, stderr));
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

void RegisterAction(CLI::App& run, CommandContext& ctx, const std::string& action,
                    const std::string& help) {
  static std::map<std::string, std::int64_t> ids;
  static std::map<std::string, std::string> confirms;
  auto* cmd = run.add_subcommand(action, help);
  cmd->add_option("run", ids[action], "Run id")->required();
  if (action == "resume") {
    cmd->add_option("--confirm", confirms[action],
                    "What you have checked, answering the run's question (`run status` shows "
                    "it): position or sensor")
        ->check(CLI::IsMember({"position", "sensor"}));
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
    if (ctx.json) return PrintJson(r);
    std::printf("run %lld: %s\n", static_cast<long long>(ids[action]),
                r["message"].get<std::string>().c_str());
  });
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
      std::printf("%-7s %s\n", e["level"].get<std::string>().c_str(),
                  e["message"].get<std::string>().c_str());
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
