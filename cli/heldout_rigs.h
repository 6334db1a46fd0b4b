#pragma once
// Held-out rigs for `gs360 bench heldout`: a sensor, its LEDs, its camera and its noise drawn
// from a documented distribution (docs/benchmarks.md, "Held-out rigs") by a seed, written as a
// lab would hand it over: a gs360d.toml with [rig], [plan] and a [sim] table (and an STL file
// when the finger is a mesh), so that `gs360 demo --config FILE` builds the same virtual rig.
//
// What is drawn (uniform unless said), sensor frame, mm:
// - the family: spline, cone, cylinder, dome (a hemisphere-capped cylinder up to 1.25 radii tall)
//   or a mesh that is not round (an elliptical or flattened section, or a bent tip), 1 in 5 each;
//   heights 20-60 mm (domes 10-18 mm radius), base radii 6.5-14 mm;
// - a mesh is an STL, an open surface or a closed solid with its flat base (1 in 2), in mm or
//   in metres (1 in 3, with [rig] mesh_scale = 1000);
// - fins (3 in 4; domes 1 in 4) 0.3-0.9 mm thick; camera_z from -4 to -1 mm;
// - the hidden camera 0.5-3 deg and 0.1-0.6 mm off the nominal one, the lens off by 0.5-2 times
//   the default perturbation; read noise 0.5-3 DN, shot gain 0.02-0.12, LED drift 0-0.04;
// - fin LEDs at 1-3 heights in 0.08-0.7 of the height, 0.3-0.8 across the fin, red and green
//   0.5-1.6, blue 4-14, a blue ring of 6-24 LEDs at 0.2-0.6 of the base radius.
// The machine is sized to the finger as a lab would pick it: Z travel max(45, height + 20) mm
// with the base that far down, and a stylus at least as long as the finger is tall.

#include <cstdint>
#include <filesystem>
#include <string>

#include "cli/sim_args.h"
#include "run/run_config.h"

namespace gs360::cli {

struct HeldoutRig {
  std::uint64_t seed = 0;
  std::string family;            // "spline", "cone", "cylinder", "dome", "ellipse", "flat", "bent"
  std::string description;       // "spline 41 mm x r 9.2, fins 0.5 mm, camera -2.1 mm, ..."
  std::filesystem::path config;  // the gs360d.toml
  std::filesystem::path mesh;    // the STL, or empty for a built-in shape
};

// Draws the rig of `seed` and writes rig-<seed>.toml (and rig-<seed>.stl) into `dir` (created).
// The same seed gives the same files. Throws std::runtime_error naming a file it cannot write.
HeldoutRig DrawHeldoutRig(std::uint64_t seed, const std::filesystem::path& dir);

// The project's own sensor (`shape`: "cylinder", "cone" or "spline") at its defaults, as a
// gs360d.toml in `dir` with the seed's default [sim] (perturbation 1), for comparison rows.
HeldoutRig OwnRig(const std::string& shape, std::uint64_t seed, const std::filesystem::path& dir);

// The rig's file read as `gs360 demo --config FILE` reads it: its run configuration (gs360d's
// defaults under it), the simulator's knobs and seed. Throws ConfigError naming the file.
RunConfig LoadHeldoutRig(const HeldoutRig& rig, SimArgs* sim, std::uint64_t* seed);

}  // namespace gs360::cli
