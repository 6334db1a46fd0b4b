// gs360: the command-line client and the stand-alone commands.

#include <spdlog/spdlog.h>

#include <exception>
#include <iostream>

#include "cli/commands.h"

int main(int argc, char** argv) {
  CLI::App app{"gs360: controller and calibration for a GelSight360 calibration rig"};
  app.set_version_flag("--version", "gs360 0.1.0");
  gs360::cli::CommandContext ctx;
  app.add_flag("-v,--verbose", ctx.verbosity, "More log output (-vv for debug)");
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

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e);
  } catch (const std::exception& e) {
    std::cerr << "gs360: error: " << e.what() << "\n";
    return 1;
  }
  return ctx.exit_code;
}
