// Shared by the network tests (unit, stress, soak): profiles, scripted presses and the two
// invariants (fluid volume, energy balance) measured on a NetworkSimulation.
#pragma once

#include <algorithm>
#include <cmath>
#include <fstream>
#include <map>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include "mrskin/driver/model/network.hpp"

namespace mrskin::model::nettest {

inline const std::string kProfileDir = MRSKIN_TEST_PROFILE_DIR;

// One DeviceModel per profile name for the whole test binary (built on first use), with the
// reservoir at ambient (p0 = 0): the closed-form bounds of these tests (locked volume, bulge
// pressure) are for that case. The shipped precharge has its own test (PrechargeRefills...).
inline const DeviceModel& model_of(const std::string& name) {
  static std::map<std::string, std::unique_ptr<DeviceModel>> models;
  auto& m = models[name];
  if (!m) {
    DeviceProfile p = load_profile(kProfileDir + "/" + name + ".toml");
    p.reservoir.initial_pressure_Pa = 0.0;
    m = std::make_unique<DeviceModel>(p);
  }
  return *m;
}

// The palm profile's small, stiff cells on a 5 x 5 grid: nodes far stiffer than a 1 ms step
// (a cell's free annulus holds ~6e-17 m^3/Pa, its passages conduct ~7e-12 m^3/(s Pa)).
inline DeviceModel palm_cells_5x5() {
  std::ifstream f(kProfileDir + "/palm-64x64.toml");
  std::stringstream text;
  text << f.rdbuf();
  std::string t = text.str();
  auto replace = [&t](const std::string& from, const std::string& to) {
    const std::size_t at = t.find(from);
    if (at != std::string::npos) {
      t.replace(at, from.size(), to);
    }
  };
  replace("rows = 64", "rows = 5");
  replace("cols = 64", "cols = 5");
  replace("cell = \"32,32\"", "cell = \"2,2\"");
  return DeviceModel(parse_profile(t, "palm-cells-5x5"));
}

inline double max_yield_Pa(const DeviceModel& m) {
  return m.yield_stress_at_current_Pa(m.profile().coil.max_current_A).value;
}

inline std::size_t design_cell(const DeviceModel& m) {
  return m.fluid_cell_index(m.profile().design.row, m.profile().design.col).value;
}

// A fingertip over the design cell, indentation set later.
inline Contact design_contact(const DeviceModel& m, double radius_m) {
  Contact c;
  c.x_m = m.profile().design.col * m.profile().cell_pitch_m;
  c.y_m = m.profile().design.row * m.profile().cell_pitch_m;
  c.radius_m = radius_m;
  return c;
}

// Press (linear ramp), hold, release (linear ramp) to 0, then rest: indentation at time t.
struct PressCycle {
  double depth_m = 5e-3;
  double press_s = 0.2;
  double hold_s = 0.3;
  double release_s = 0.2;
  double rest_s = 0.1;
  [[nodiscard]] double period_s() const { return press_s + hold_s + release_s + rest_s; }
  [[nodiscard]] double at(double t) const {
    t = std::fmod(t, period_s());
    if (t < press_s) {
      return depth_m * t / press_s;
    }
    t -= press_s;
    if (t < hold_s) {
      return depth_m;
    }
    t -= hold_s;
    if (t < release_s) {
      return depth_m * (1.0 - t / release_s);
    }
    return 0.0;
  }
};

// Worst relative errors of the two invariants seen so far.
struct Invariants {
  double volume_scale_m3 = 1.0;  // A_eff * cell depth * cells: the most the pads can displace
  double worst_volume_rel = 0.0;
  double worst_energy_rel = 0.0;
  double worst_energy_abs_J = 0.0;
  double min_dissipation_increment_J = 0.0;
  double last_dissipated_J = 0.0;

  explicit Invariants(const NetworkSimulation& s)
      : volume_scale_m3(s.model().contact().effective_area_m2 * s.model().profile().cell_depth_m *
                        static_cast<double>(s.fluid_cell_count())) {}

  void check(const NetworkSimulation& s) {
    worst_volume_rel =
        std::max(worst_volume_rel, std::fabs(s.total_fluid_volume_change_m3()) / volume_scale_m3);
    const NetworkEnergy e = s.energy();
    const double stored = e.stored_J - e.stored_initial_J;
    const double gap = std::fabs(e.work_J - stored - e.dissipated_J);
    const double scale = std::max({std::fabs(e.work_J), std::fabs(stored), std::fabs(e.dissipated_J)});
    worst_energy_abs_J = std::max(worst_energy_abs_J, gap);
    if (scale > 0.0) {
      worst_energy_rel = std::max(worst_energy_rel, gap / scale);
    } else if (gap > 0.0) {
      worst_energy_rel = std::max(worst_energy_rel, 1.0);
    }
    min_dissipation_increment_J = std::min(min_dissipation_increment_J, e.dissipated_J - last_dissipated_J);
    last_dissipated_J = e.dissipated_J;
  }
};

// Periodic press/hold/release on the design cell (period 1 s, yield 60 % of max while loading
// and holding, 0 while releasing), for `steps` steps of dt. The state must settle onto a
// periodic orbit and stay there: drift shows as a change in each cycle's peak force.
struct SoakResult {
  long steps_done = 0;
  Status failure = Status::ok;
  Invariants invariants;
  double late_peak_change_N = 0.0;  // largest |peak(k) - peak(k-1)| over the second half
  double last_peak_N = 0.0;
  double max_abs_pressure_Pa = 0.0;
  explicit SoakResult(const NetworkSimulation& s) : invariants(s) {}
};

inline SoakResult run_soak(NetworkSimulation& sim, long steps, double dt) {
  const DeviceModel& m = sim.model();
  SoakResult out(sim);
  const PressCycle cyc{m.profile().design.indentation_m, 0.3, 0.3, 0.2, 0.2};
  const auto per_cycle = static_cast<long>(std::lround(cyc.period_s() / dt));
  Contact c = design_contact(m, 0.02);
  std::vector<double> yield(sim.valve_count(), 0.0);
  const double tau = 0.6 * max_yield_Pa(m);
  const std::size_t cell = design_cell(m);
  double peak = 0.0;
  for (long k = 0; k < steps; ++k) {
    const long in_cycle = k % per_cycle;
    const double t = static_cast<double>(in_cycle + 1) * dt;
    if (in_cycle == 0 || in_cycle == static_cast<long>(std::lround((cyc.press_s + cyc.hold_s) / dt))) {
      std::fill(yield.begin(), yield.end(), in_cycle == 0 ? tau : 0.0);
      if (sim.set_valve_yield_stress_Pa(yield) != Status::ok) {
        out.failure = Status::out_of_range;
        return out;
      }
    }
    c.indentation_m = cyc.at(t);
    if (const Status s = sim.set_contacts(std::span<const Contact>(&c, 1)); s != Status::ok) {
      out.failure = s;
      return out;
    }
    const Result<StepReport> r = sim.step(dt);
    if (!r.ok()) {
      out.failure = r.status;
      return out;
    }
    out.steps_done = k + 1;
    out.invariants.check(sim);
    for (const double p : sim.cell_pressure_Pa()) {
      out.max_abs_pressure_Pa = std::isfinite(p) ? std::max(out.max_abs_pressure_Pa, std::fabs(p)) : HUGE_VAL;
    }
    peak = std::max(peak, sim.cell_force_N()[cell]);
    if (in_cycle == per_cycle - 1) {
      if (k > steps / 2) {
        out.late_peak_change_N = std::max(out.late_peak_change_N, std::fabs(peak - out.last_peak_N));
      }
      out.last_peak_N = peak;
      peak = 0.0;
    }
  }
  return out;
}

}  // namespace mrskin::model::nettest
