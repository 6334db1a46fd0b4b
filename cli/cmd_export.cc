// `gs360 export RUN --out DIR`: the model of a run's last calibration, from gs360d, to a folder:
// the bundle, the ONNX network, the HTML report and the validation figures. The bundle is read
// back before the command succeeds.

#include <cstdio>
#include <filesystem>

#include "cli/commands.h"
#include "cli/daemon_client.h"
#include "recon/model_bundle.h"

namespace gs360::cli {

void RegisterExportCommand(CLI::App& app, CommandContext& ctx) {
  static std::int64_t run = 0;
  static std::string out;
  auto* cmd = app.add_subcommand(
      "export", "Download a run's calibrated model (bundle, ONNX, report, validation) from gs360d");
  cmd->add_option("run", run, "Run id")->required();
  cmd->add_option("--out", out, "Folder to write into (created)")->required();
  cmd->callback([&ctx] {
    DaemonClient client(ctx.daemon_url, ctx.token);
    const std::string base = "/api/v1/runs/" + std::to_string(run);
    // Before anything is written: the run (3 when there is none) and its finished calibration.
    client.Get(base);
    const nlohmann::json calibration = client.Get(base + "/calibration");
    const std::string state = calibration.value("state", "none");
    const bool validated = calibration.contains("validation") &&
                           calibration["validation"].is_object() &&
                           !calibration["validation"].empty();
    if (state != "done" || !validated) {
      const std::string id = std::to_string(run);
      throw ClientError("run " + id +
                            " has no finished calibration to export (its calibration is " +
                            (state == "none"   ? std::string("not started")
                             : state == "done" ? std::string("done up to a stage before the model")
                                               : state) +
                            "): calibrate it with `gs360 calibrate " + id + "`, then export",
                        kExitNoCalibration);
    }
    std::filesystem::create_directories(out);
    const std::string stem = "run-" + std::to_string(run);
    struct File {
      const char* endpoint;
      std::string name;
    };
    const File files[] = {{"/model", stem + ".gs360model"},
                          {"/model.onnx", stem + ".onnx"},
                          {"/report", stem + "-report.html"},
                          {"/validation.json", stem + "-validation.json"}};
    nlohmann::json written = nlohmann::json::array();
    for (const File& f : files) {
      const auto path = std::filesystem::path(out) / f.name;
      const std::int64_t bytes = client.Download(base + f.endpoint, path);
      written.push_back({{"file", path.string()}, {"bytes", bytes}});
    }
    // What a lab takes home must open: read the bundle back.
    const ModelBundle bundle = ReadModelBundle(std::filesystem::path(out) / (stem + ".gs360model"));
    if (ctx.json) {
      std::printf("%s\n", nlohmann::json{{"run", run},
                                         {"model", bundle.name + "-" + bundle.version},
                                         {"files", written}}
                              .dump(2)
                              .c_str());
      return;
    }
    std::printf("run %lld: model %s %s (%s)\n", static_cast<long long>(run), bundle.name.c_str(),
                bundle.version.c_str(), bundle.sensor.c_str());
    for (const auto& w : written) {
      std::printf("  %-40s %10lld bytes\n", w["file"].get<std::string>().c_str(),
                  w["bytes"].get<long long>());
    }
  });
}

}  // namespace gs360::cli
