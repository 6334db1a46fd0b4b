// `gs360 sim-cnc` and `gs360 sim-rig`: the virtual rig as processes any sender can talk to.

#include <unistd.h>

#include <csignal>
#include <cstdio>
#include <filesystem>
#include <thread>

#include "base/hash.h"
#include "base/json_reader.h"
#include "cli/commands.h"
#include "cli/daemon_client.h"
#include "cli/sim_args.h"
#include "cli/sim_bridge.h"
#include "daemon/instance_lock.h"
#include "rig/rig_config.h"
#include "sim/virtual_cnc.h"
#include "sim/virtual_rig.h"

namespace gs360::cli {
namespace {

volatile std::sig_atomic_t g_stop = 0;
extern "C" void OnSignal(int) {
  g_stop = 1;
}

// A virtual rig's paths (the CNC's symlink, the frame socket) belong to one rig at a time: a
// second rig on the same path would take it over, and the first would delete it when it ends.
// The lock (daemon/instance_lock.h: in the temp folder, named after the path's absolute form)
// is released by the kernel however its holder ends, so nothing stale is left to refuse.
InstanceLock LockSimPath(const std::string& path, const std::string& what, const char* option,
                         const char* command) {
  const std::string absolute = std::filesystem::absolute(path).lexically_normal().string();
  const auto lock_file = std::filesystem::temp_directory_path() /
                         ("gs360-sim-" + HashHex(absolute.data(), absolute.size()) + ".lock");
  try {
    return InstanceLock::Acquire(
        lock_file, what + " " + absolute,
        std::string("gs360 ") + command + " pid " + std::to_string(::getpid()));
  } catch (const LockHeldError& e) {
    throw ClientError(std::string(e.what()) + ": stop that one, or give another " + option,
                      kExitError);
  }
}

struct SimOptions {
  std::string firmware = "grbl";  // sim-cnc's; sim-rig takes SimArgs'
  double time_scale = 1.0;
  int rx_buffer = 128;
  std::string symlink;
  std::string shape = "cylinder";
  std::string socket;
  std::uint64_t seed = 1;
  SimArgs sim;
};

}  // namespace

void RegisterSimCommands(CLI::App& app, CommandContext& ctx) {
  static SimOptions o;
  auto* cnc = app.add_subcommand(
      "sim-cnc",
      "Serve a virtual GRBL 1.1 CNC (or grblHAL, or a Marlin printer) on a pseudo-terminal "
      "(prints its path)");
  AddFirmwareOption(cnc, &o.firmware,
                    "a Marlin 2.1 printer of the Ender-3 class: 235 x 235 x 250 mm, Z at 5 mm/s");
  cnc->add_option("--time-scale", o.time_scale, "Machine seconds per wall second (0 = instant)")
      ->capture_default_str();
  cnc->add_option("--rx-buffer", o.rx_buffer, "Receive buffer bytes reported by $I")
      ->capture_default_str();
  cnc->add_option("--symlink", o.symlink, "Keep a symlink to the pty here");
  cnc->callback([&ctx] {
    InstanceLock symlink_lock;
    if (!o.symlink.empty()) {
      symlink_lock = LockSimPath(o.symlink, "the CNC's symlink", "--symlink", "sim-cnc");
    }
    VirtualCncOptions options;
    options.firmware = ParseCncFirmware(o.firmware);
    if (options.firmware == CncFirmware::kMarlin)
      options.settings = GrblSettings::PrinterDefaults();
    options.time_scale = o.time_scale;
    options.rx_buffer_bytes = o.rx_buffer;
    options.symlink_path = o.symlink;
    ctx.exit_code = RunVirtualCncForeground(options);
  });

  auto* rig = app.add_subcommand(
      "sim-rig",
      "Serve the whole virtual rig: the CNC on a pty and the tactile camera on a socket");
  rig->add_option("--time-scale", o.time_scale, "Machine seconds per wall second (0 = instant)")
      ->capture_default_str();
  auto* shape =
      rig->add_option("--shape", o.shape, "cylinder, cone or spline")->capture_default_str();
  rig->add_option("--socket", o.socket, "Frame socket path (default: in the temp directory)");
  rig->add_option("--symlink", o.symlink,
                  "Keep a symlink to the CNC's pty here (printed instead of the pty): a replugged "
                  "CNC (--faults unplug) gets a new pty");
  rig->add_option("--seed", o.seed, "Seed of the hidden true camera and the noise")
      ->capture_default_str();
  AddSimArgs(rig, &o.sim);
  shape->excludes("--config");
  rig->callback([rig] {
    InstanceLock symlink_lock, socket_lock;
    if (!o.symlink.empty()) {
      symlink_lock = LockSimPath(o.symlink, "the CNC's symlink", "--symlink", "sim-rig");
    }
    if (!o.socket.empty()) {
      socket_lock = LockSimPath(o.socket, "the frame socket", "--socket", "sim-rig");
    }
    RunConfig run = LoadSimConfig(*rig, &o.sim, &o.seed);
    RigConfig& config = run.rig;
    if (o.sim.config.empty()) config.shape.shape = ParseSensorShape(o.shape);
    VirtualRigOptions options;
    options.rig = SimRigOptionsFor(config, o.seed);
    options.camera.sensor.seed = o.seed;
    options.cnc.time_scale = o.time_scale;
    options.frame_socket = o.socket;
    options.cnc.symlink_path = o.symlink;
    MachineForConfig(run, &options);
    ApplySimArgs(o.sim, &options);
    PrinterForConfig(run, &options);
    VirtualRig virtual_rig(options);
    const auto faults = StartFaults(o.sim, virtual_rig, o.seed);
    if (faults && o.symlink.empty()) {
      std::fprintf(stderr,
                   "sim-rig: without --symlink a sender cannot find the CNC again after an "
                   "unplug fault (it comes back under a new pty)\n");
    }
    std::printf("%s\n%s\n", o.symlink.empty() ? virtual_rig.PtyPath().c_str() : o.symlink.c_str(),
                virtual_rig.FrameUri().c_str());
    std::fflush(stdout);
    std::signal(SIGINT, OnSignal);
    std::signal(SIGTERM, OnSignal);
    while (!g_stop) std::this_thread::sleep_for(std::chrono::milliseconds(100));
    if (faults) std::fprintf(stderr, "sim-rig: %s\n", DescribeFaults(faults->Injected()).c_str());
  });
}

}  // namespace gs360::cli
