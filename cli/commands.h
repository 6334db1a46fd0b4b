#pragma once
// The gs360 command-line tool: each command registers itself on the CLI11 app. A command's
// callback returns through the exit code stored in `CommandContext::exit_code`.

#include <CLI/CLI.hpp>

namespace gs360::cli {

struct CommandContext {
  int exit_code = 0;
  int verbosity = 0;  // -v / -vv on the top-level app
};

void RegisterSimCommands(CLI::App& app, CommandContext& ctx);       // sim-cnc
void RegisterDemoCommand(CLI::App& app, CommandContext& ctx);       // demo
void RegisterRunCommands(CLI::App& app, CommandContext& ctx);       // run start|resume|status
void RegisterBenchCommands(CLI::App& app, CommandContext& ctx);     // bench acquisition
void RegisterCalibrateCommand(CLI::App& app, CommandContext& ctx);  // calibrate

}  // namespace gs360::cli
