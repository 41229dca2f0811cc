// Plant suite: the mock device's plant (sim::NetworkPlant: the perturbed network, coils, steel
// hysteresis, noisy sensors), the time one substep takes on each built-in grid, against the
// substep itself. A unit whose substep takes longer than the time it simulates cannot keep real
// time in mrskin-bridged (docs/bridge.md, "Every grid in real time"). Writes
//   <out>/plant_substep.csv   per grid, substep (0.1 and 1 ms), case (idle: no finger; pressed: 5 %
//                             of the fluid cells nearest the design cell pressed to the design
//                             depth in 50 ms and held) and the settled-field reuse (on, the
//                             default, and off, every valve's magnetic circuit solved every
//                             substep): time per substep (median, p90, p99), the real-time
//                             factor (substep / median time) and gap-field solves per substep
// Every valve holds 30 % of its highest current, settled for 0.1 s (untimed) before the timed
// substeps. Both settings of a case run back to back in one process, so their ratio is the
// figure to quote on a shared machine. Wall clock: nothing here is a pass/fail gate.
#include <algorithm>
#include <array>
#include <chrono>
#include <cstdint>
#include <fstream>
#include <iostream>
#include <string>
#include <vector>

#include "bench_common.hpp"
#include "mrskin/driver/model/device_model.hpp"
#include "mrskin/driver/model/profile.hpp"
#include "mrskin/sim/network_plant.hpp"
#include "suites.hpp"

namespace mrskin::bench {

namespace {

using Clock = std::chrono::steady_clock;

constexpr double kSettle_s = 0.1;         // untimed: the coils reach their fixed point
constexpr double kPress_s = 0.05;         // the pressed cells reach the design depth in this
constexpr double kCurrentFraction = 0.3;  // of the coil's highest current, on every valve
constexpr double kPressedFraction = 0.05;

struct Timing {
  std::vector<double> us;
  double solves_per_substep = 0.0;
  std::uint64_t failed = 0;
};

Timing time_plant(const model::DeviceProfile& profile, const model::DeviceModel& nominal, double dt_s,
                  int substeps, bool pressed, bool reuse) {
  sim::NetworkPlantOptions options;
  options.seed = 7;
  options.reuse_settled_fields = reuse;
  sim::NetworkPlant plant(profile, options);
  const std::size_t cells = nominal.layout().fluid_cells().size();
  std::vector<double> depth_m(cells, 0.0);
  const std::vector<double> current_A(nominal.layout().valve_count(),
                                      kCurrentFraction * profile.coil.max_current_A);
  plant.set_valve_currents(current_A);
  plant.set_finger_indentation(depth_m);
  for (double t = 0.0; t < kSettle_s; t += dt_s) {
    plant.step(dt_s);
  }
  const std::vector<std::size_t> touched =
      pressed ? pressed_cells(nominal, kPressedFraction) : std::vector<std::size_t>{};
  const double design_depth_m = nominal.profile().design.indentation_m;
  Timing t;
  t.us.reserve(static_cast<std::size_t>(substeps));
  const std::uint64_t solves_before = plant.gap_field_solves();
  for (int k = 0; k < substeps; ++k) {
    const double d = design_depth_m * std::min(1.0, (k + 1) * dt_s / kPress_s);
    for (const std::size_t c : touched) {
      depth_m[c] = d;
    }
    plant.set_finger_indentation(depth_m);
    const auto t0 = Clock::now();
    plant.step(dt_s);
    t.us.push_back(std::chrono::duration<double, std::micro>(Clock::now() - t0).count());
  }
  t.solves_per_substep = static_cast<double>(plant.gap_field_solves() - solves_before) / substeps;
  t.failed = plant.failed_steps();
  return t;
}

}  // namespace

int run_plant_suite(const BenchOptions& o) {
  struct Grid {
    const char* profile;
    std::array<double, 2> substeps_s;
    int substeps;  // timed, per case
  };
  // The palm at 1 ms only: at 0.1 ms its idle substep alone is several times the time it simulates.
  constexpr std::array<Grid, 3> kGrids = {{{"mr-skin-5x5", {1e-4, 1e-3}, 2000},
                                           {"fingertip-16x16", {1e-4, 1e-3}, 1000},
                                           {"palm-64x64", {1e-3, 0.0}, 200}}};
  std::ofstream csv(o.out + "/plant_substep.csv");
  if (!csv) {
    std::cerr << "cannot write to " << o.out << "\n";
    return 1;
  }
  csv << "profile,fluid_cells,substep_s,case,reuse_settled_fields,substeps,us_median,us_p90,us_p99,"
         "realtime_factor,gap_field_solves_per_substep,failed_steps\n";
  std::cout << "plant: every valve at 30 % of its highest current, settled 0.1 s; pressed: 5 % of the fluid "
               "cells to the design depth in 50 ms, held; realtime = substep / median\n";
  std::cout << pad("profile", 17, true) << pad("substep", 9) << pad("case", 9) << pad("reuse", 7)
            << pad("median_us", 11) << pad("p90_us", 10) << pad("realtime", 10) << pad("solves", 9) << "\n";
  constexpr std::size_t kRuns = 20;  // 5 (grid, substep) pairs x 2 cases x 2 reuse settings
  Progress bar("plant", kRuns);
  int rc = 0;
  for (const Grid& g : kGrids) {
    const model::DeviceProfile profile = model::load_profile(g.profile);
    const model::DeviceModel nominal(profile);
    for (const double dt_s : g.substeps_s) {
      if (dt_s <= 0.0) {
        continue;
      }
      for (const bool pressed : {false, true}) {
        for (const bool reuse : {true, false}) {
          const Timing t = time_plant(profile, nominal, dt_s, g.substeps, pressed, reuse);
          bar.tick(std::string(g.profile) + (pressed ? " pressed" : " idle"));
          const double med = percentile(t.us, 0.5);
          const double realtime = dt_s * 1e6 / med;
          const char* which = pressed ? "pressed" : "idle";
          csv << g.profile << ',' << nominal.layout().fluid_cells().size() << ',' << sci(dt_s, 0) << ','
              << which << ',' << (reuse ? "on" : "off") << ',' << g.substeps << ',' << fixed(med, 2) << ','
              << fixed(percentile(t.us, 0.9), 2) << ',' << fixed(percentile(t.us, 0.99), 2) << ','
              << fixed(realtime, 3) << ',' << fixed(t.solves_per_substep, 2) << ',' << t.failed << '\n';
          std::cout << pad(g.profile, 17, true) << pad(sci(dt_s, 0), 9) << pad(which, 9)
                    << pad(reuse ? "on" : "off", 7) << pad(fixed(med, 1), 11)
                    << pad(fixed(percentile(t.us, 0.9), 1), 10) << pad(fixed(realtime, 2) + "x", 10)
                    << pad(fixed(t.solves_per_substep, 1), 9)
                    << (t.failed > 0 ? "  FAILED STEPS: " + std::to_string(t.failed) : "") << "\n";
          rc = t.failed > 0 ? 1 : rc;
        }
      }
    }
  }
  std::cout << "wrote " << o.out << "/plant_substep.csv\n";
  return rc;
}

}  // namespace mrskin::bench
