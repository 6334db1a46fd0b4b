// gs360: the command-line client of gs360d and the stand-alone commands (demo, sim-rig, bench).
// Exit codes: docs/cli.md (cli/daemon_client.h ExitCode).

#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include <cstdio>
#include <exception>
#include <iostream>

#include "base/json_reader.h"
#include "base/version.h"
#include "cli/commands.h"
#include "cli/daemon_client.h"

int main(int argc, char** argv) {
  // Lines reach a pipe as they are printed ("created run 3" before the run ends).
  std::setvbuf(stdout, nullptr, _IOLBF, 0);
  // Logs go to stderr only: stdout carries a command's output (--json stays parseable with -v).
  spdlog::set_default_logger(spdlog::stderr_color_mt("gs360"));

  CLI::App app{"gs360: controller and calibration for a GelSight360 calibration rig"};
  app.set_version_flag("--version", gs360::VersionLine("gs360"));
  app.fallthrough();  // global options may come after the command too
  gs360::cli::CommandContext ctx;
  ctx.daemon_url = gs360::cli::DaemonClient::DefaultUrl();
  ctx.token = gs360::cli::DaemonClient::DefaultToken();
  app.add_flag("-v,--verbose", ctx.verbosity, "More log output on stderr (-vv for debug)");
  app.add_option("--daemon", ctx.daemon_url,
                 "gs360d's URL (default: $GS360_DAEMON, else "
                 "http://127.0.0.1:7360)");
  app.add_option("--token", ctx.token, "gs360d's token (default: $GS360_TOKEN)");
  app.add_flag("--json", ctx.json, "Print the daemon's JSON instead of text (read commands)");
  app.require_subcommand(1);
  app.parse_complete_callback([&] {
    spdlog::set_level(ctx.verbosity >= 2   ? spdlog::level::debug
                      : ctx.verbosity == 1 ? spdlog::level::info
                                           : spdlog::level::warn);
  });

  gs360::cli::RegisterSimCommands(app, ctx);
  gs360::cli::RegisterDemoCommand(app, ctx);
  gs360::cli::RegisterRunCommands(app, ctx);
  gs360::cli::RegisterBenchCommands(app, ctx);
  gs360::cli::RegisterCalibrateCommand(app, ctx);
  gs360::cli::RegisterExportCommand(app, ctx);
  gs360::cli::RegisterReconCommand(app, ctx);

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    const int code = app.exit(e);
    return code == 0 ? 0 : gs360::cli::kExitUsage;
  } catch (const gs360::cli::ClientError& e) {
    std::cerr << "gs360: " << e.what() << "\n";
    return e.exit_code();
  } catch (const gs360::ConfigError& e) {
    std::cerr << "gs360: " << e.what() << "\n";
    return gs360::cli::kExitUsage;
  } catch (const std::exception& e) {
    std::cerr << "gs360: error: " << e.what() << "\n";
    return gs360::cli::kExitError;
  }
  return ctx.exit_code;
}
