// Instruction-count probe for CellInverse::solve on the default 5 x 5 (run under
// valgrind --tool=callgrind --instr-atstart=no; see CMakeLists.txt). Each scenario warms up
// outside the instrumented region, then runs kSolves ticks with every target changing every tick
// between CALLGRIND_START_INSTRUMENTATION and CALLGRIND_STOP_INSTRUMENTATION.
//
//   inverse_callgrind_probe SCENARIO [PROFILE_DIR]
//   SCENARIO: press1 | press2 | press3 | hold3 | idle
// Prints "solves N" (the number of instrumented solves) for the gate to divide by.
#include <valgrind/callgrind.h>

#include <cmath>
#include <cstdio>
#include <cstring>
#include <string>
#include <vector>

#include "mrskin/driver/model/inverse.hpp"

namespace {

using namespace mrskin::model;

constexpr int kWarmup = 200;
constexpr int kSolves = 2000;

struct Scenario {
  std::vector<std::size_t> cells;
  std::vector<double> share;  // of the finger's indentation each cell sees
  bool hold = false;
  bool idle = false;
};

// One tick of a finger: loading at 4.5 mm/s from 0.5 mm (press), or holding near 4 mm with
// observer-like jitter (hold); every cell's state moves beyond the inverse's tolerances.
void state_at(const Scenario& sc, int tick, std::vector<CellState>& st) {
  for (std::size_t k = 0; k < sc.cells.size(); ++k) {
    const double f = sc.share[k];
    if (sc.idle) {
      st[sc.cells[k]] = {4e-3 * f, 0.0};
    } else if (sc.hold) {
      const double jitter = std::sin(0.7 * tick + static_cast<double>(k));
      st[sc.cells[k]] = {f * (4e-3 + 2e-6 * jitter), 5e-5 * jitter};
    } else {
      const double time = 1e-3 * (tick % 1000);
      st[sc.cells[k]] = {f * (0.5e-3 + 4.5e-3 * time), f * 4.5e-3};
    }
  }
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2) {
    std::fprintf(stderr, "usage: %s press1|press2|press3|hold3|idle [PROFILE_DIR]\n", argv[0]);
    return 2;
  }
  const std::string which = argv[1];
  const std::string dir = argc > 2 ? argv[2] : "";
  const DeviceModel model(dir.empty() ? default_profile() : load_profile(dir + "/mr-skin-5x5.toml"));
  CellInverse inverse(model);
  const std::size_t n = inverse.fluid_cell_count();
  auto cell = [&](int r, int c) { return model.fluid_cell_index(r, c).value; };
  Scenario sc;
  if (which == "press1") {
    sc.cells = {cell(2, 2)};
    sc.share = {1.0};
  } else if (which == "press2") {
    sc.cells = {cell(2, 2), cell(1, 1)};
    sc.share = {1.0, 0.7};
  } else if (which == "press3" || which == "hold3" || which == "idle") {
    sc.cells = {cell(1, 1), cell(2, 2), cell(1, 3)};
    sc.share = {1.0, 0.8, 0.6};
    sc.hold = which == "hold3";
    sc.idle = which == "idle";
  } else {
    std::fprintf(stderr, "unknown scenario %s\n", which.c_str());
    return 2;
  }
  std::vector<CellImpedanceTarget> targets(n);
  for (const std::size_t c : sc.cells) {
    // Stomach-like tissue: k x^1.2 through 1.2 N at 4 mm (secant ~300 N/m), some damping; the
    // law changes every tick. Its forces sit inside the envelope, so the valves are shared.
    targets[c] = {900.0, 1.2, 5.0, 0.0, 0.0, 2.5, 1e9};
  }
  // Inputs of every tick precomputed: only solve() runs in the instrumented region.
  const int ticks = kWarmup + kSolves;
  std::vector<std::vector<CellState>> states(static_cast<std::size_t>(ticks), std::vector<CellState>(n));
  std::vector<std::vector<CellImpedanceTarget>> laws(static_cast<std::size_t>(ticks), targets);
  for (int k = 0; k < ticks; ++k) {
    state_at(sc, k, states[static_cast<std::size_t>(k)]);
    for (const std::size_t c : sc.cells) {
      laws[static_cast<std::size_t>(k)][c].stiffness_N_per_m = sc.idle ? 900.0 : 900.0 + 0.01 * (k % 97);
    }
  }
  auto tick = [&](int k) {
    const auto ku = static_cast<std::size_t>(k);
    return inverse.solve(laws[ku], states[ku], 1e-3 * k);
  };
  for (int k = 0; k < kWarmup; ++k) {
    if (tick(k) != Status::ok) {
      std::fprintf(stderr, "solve failed in warm-up\n");
      return 1;
    }
  }
  int failures = 0;
  CALLGRIND_START_INSTRUMENTATION;
  for (int k = kWarmup; k < ticks; ++k) {
    failures += tick(k) != Status::ok ? 1 : 0;
  }
  CALLGRIND_STOP_INSTRUMENTATION;
  const InverseReport& r = inverse.report();
  std::printf("solves %d\nfailures %d\nloaded %zu residual_norm_N %.3g converged %d\n", kSolves, failures,
              r.loaded_cells, r.residual_norm_N, r.converged ? 1 : 0);
  return failures == 0 ? 0 : 1;
}
