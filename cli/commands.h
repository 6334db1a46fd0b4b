#pragma once
// The gs360 command-line tool: each command registers itself on the CLI11 app. A command's
// callback returns through the exit code stored in `CommandContext::exit_code` (docs/cli.md).

#include <CLI/CLI.hpp>
#include <string>

namespace gs360::cli {

struct CommandContext {
  int exit_code = 0;
  int verbosity = 0;       // -v / -vv on the top-level app
  std::string daemon_url;  // --daemon, else $GS360_DAEMON, else http://127.0.0.1:7360
  std::string token;       // --token, else $GS360_TOKEN
  bool json = false;       // --json: machine-readable output on stdout
};

void RegisterSimCommands(CLI::App& app, CommandContext& ctx);       // sim-cnc, sim-rig
void RegisterDemoCommand(CLI::App& app, CommandContext& ctx);       // demo
void RegisterRunCommands(CLI::App& app, CommandContext& ctx);       // run start|status|...
void RegisterBenchCommands(CLI::App& app, CommandContext& ctx);     // bench acquisition
void RegisterCalibrateCommand(CLI::App& app, CommandContext& ctx);  // calibrate
void RegisterExportCommand(CLI::App& app, CommandContext& ctx);     // export
void RegisterReconCommand(CLI::App& app, CommandContext& ctx);      // recon

}  // namespace gs360::cli
