#include "design_space.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <sstream>
#include <vector>

#include "bench_common.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/model/coil.hpp"
#include "mrskin/driver/model/magnetic.hpp"
#include "mrskin/driver/model/network.hpp"

namespace mrskin::bench {

namespace {

using model::DeviceProfile;

constexpr double kCoilOhmPerTurn = 0.035;  // 0.25 mm copper, 0.1 m mean turn (the default's)
constexpr double kCurrentCounts = 4000.0;  // the default's; the wire carries at most 4095
constexpr double kWidestCurrent_A = 5.0;   // the range searched for the design force's current

std::string format_value(double v) {
  std::ostringstream s;
  s.precision(6);
  s << v;
  std::string t = s.str();
  // TOML needs a float to look like one.
  if (t.find_first_of(".eE") == std::string::npos && t.find("inf") == std::string::npos) {
    t += ".0";
  }
  return t;
}

// Pad depth 0.5 s after a release (the network test PrechargeRefillsAReleasedCell): 1 s press
// to 4 mm on the design cell, 1 s hold at 40 % of the highest yield stress, 1 s release.
double refill_depth_m(const model::DeviceModel& m) {
  model::NetworkSimulation sim(m, model::NetworkOptions{});
  const std::size_t cell = m.fluid_cell_index(m.profile().design.row, m.profile().design.col).value;
  const double hold_Pa = m.yield_stress_at_current_Pa(0.4 * m.profile().coil.max_current_A).value;
  std::vector<double> yield(sim.valve_count(), hold_Pa);
  std::vector<double> depth(sim.fluid_cell_count(), 0.0);
  for (int k = 0; k < 3500; ++k) {
    const double t = (k + 1) * 1e-3;
    depth[cell] = t < 1.0 ? 4e-3 * t : t < 2.0 ? 4e-3 : std::max(0.0, 4e-3 * (3.0 - t));
    std::fill(yield.begin(), yield.end(), t < 2.0 ? hold_Pa : 0.0);
    if (sim.set_valve_yield_stress_Pa(yield) != model::Status::ok ||
        sim.set_cell_indentation_m(depth) != model::Status::ok || !sim.step(1e-3).ok()) {
      return 1.0;  // the simulation failed: reported as never refilling
    }
  }
  return sim.cell_indentation_m()[cell];
}

// Largest force change of one current count over the whole range at the design point (hold).
double largest_count_step_N(const model::DeviceModel& m, std::size_t cell) {
  const DeviceProfile& p = m.profile();
  const double res = p.coil.current_resolution_A;
  const double d = p.design.indentation_m;
  constexpr int kSamples = 33;
  double worst = 0.0;
  for (int k = 0; k < kSamples; ++k) {
    const double i0 = (p.coil.max_current_A - res) * k / (kSamples - 1);
    const model::Result<model::CellLoad> a = m.cell_force_uniform(cell, d, 0.0, i0);
    const model::Result<model::CellLoad> b = m.cell_force_uniform(cell, d, 0.0, i0 + res);
    if (!a.ok() || !b.ok()) {
      return INFINITY;
    }
    worst = std::max(worst, std::fabs(b.value.force_N - a.value.force_N));
  }
  return worst;
}

}  // namespace

const std::array<DesignParam, kDesignParamCount>& design_params() {
  static const std::array<DesignParam, kDesignParamCount> params = {{
      {"turns", "magnetic", 5, 400, true, true,
       [](const Design& d) { return 1.0 * d.profile.magnetic.turns; },
       [](Design& d, double v) { d.profile.magnetic.turns = static_cast<int>(std::lround(v)); }},
      {"gap_m", "valve", 0.3e-3, 2.0e-3, true, false, [](const Design& d) { return d.profile.valve.gap_m; },
       [](Design& d, double v) { d.profile.valve.gap_m = v; }},
      {"length_m", "valve", 5e-3, 30e-3, true, false,
       [](const Design& d) { return d.profile.valve.length_m; },
       [](Design& d, double v) { d.profile.valve.length_m = v; }},
      {"width_m", "valve", 10e-3, 30e-3, true, false, [](const Design& d) { return d.profile.valve.width_m; },
       [](Design& d, double v) { d.profile.valve.width_m = v; }},
      {"spacer_gap_m", "magnetic", 0.0, 3e-3, false, false,
       [](const Design& d) { return d.profile.magnetic.spacer_gap_m; },
       [](Design& d, double v) { d.profile.magnetic.spacer_gap_m = v; }},
      {"thickness_m", "membrane", 0.05e-3, 0.5e-3, true, false,
       [](const Design& d) { return d.profile.membrane.thickness_m; },
       [](Design& d, double v) { d.profile.membrane.thickness_m = v; }},
      {"pretension_N_per_m", "membrane", 1.0, 20.0, true, false,
       [](const Design& d) { return d.profile.membrane.pretension_N_per_m; },
       [](Design& d, double v) { d.profile.membrane.pretension_N_per_m = v; }},
      {"initial_pressure_Pa", "reservoir", 0.0, 2000.0, false, false,
       [](const Design& d) { return d.profile.reservoir.initial_pressure_Pa; },
       [](Design& d, double v) { d.profile.reservoir.initial_pressure_Pa = v; }},
      {"range_use", "coil", 0.5, 0.95, false, false, [](const Design& d) { return d.range_use; },
       [](Design& d, double v) { d.range_use = v; }},
  }};
  return params;
}

bool apply_derived(Design& d) {
  DeviceProfile& p = d.profile;
  p.magnetic.fluid_gap_m = p.valve.gap_m;
  p.magnetic.pole_area_m2 = p.valve.length_m * p.valve.width_m;
  p.coil.resistance_ohm = kCoilOhmPerTurn * p.magnetic.turns;
  p.coil.inductance_H = model::zero_field_inductance_H(p.magnetic, p.fluid);
  // The current for the design force, first on a wide range, then on the range it gives (the
  // yield table is finer there).
  p.coil.max_current_A = kWidestCurrent_A;
  for (int pass = 0; pass < 2; ++pass) {
    p.coil.current_resolution_A = p.coil.max_current_A / kCurrentCounts;
    const model::DeviceModel m(p);
    const std::size_t cell = m.fluid_cell_index(p.design.row, p.design.col).value;
    const model::Result<double> i =
        m.current_for_force_A(cell, p.design.indentation_m, 0.0, p.design.force_range_N);
    if (!i.ok()) {
      return false;
    }
    p.coil.max_current_A = i.value / d.range_use;
  }
  // The wire's identity carries one count in whole nanoamperes, and the range as counts of it.
  const double lsb_nA = std::max(1.0, std::round(p.coil.max_current_A / kCurrentCounts * 1e9));
  p.coil.current_resolution_A = lsb_nA * 1e-9;
  p.coil.max_current_A = kCurrentCounts * p.coil.current_resolution_A;
  return true;
}

ConstraintReport check_constraints(const model::DeviceModel& m, const DesignLimits& limits, bool refill) {
  const DeviceProfile& p = m.profile();
  ConstraintReport r;
  const double i_max = p.coil.max_current_A;
  r.coil_time_constant_s = model::coil_time_constant_s(p.coil);
  r.rail_voltage_V = i_max * (p.coil.resistance_ohm +
                              2.0 * std::numbers::pi * p.coil.driver_bandwidth_Hz * p.coil.inductance_H);
  r.coil_power_W = static_cast<double>(m.layout().valve_count()) * i_max * i_max * p.coil.resistance_ohm;
  r.temperature_rise_K = r.coil_power_W * limits.thermal_resistance_K_per_W;
  // Every failure is listed (the report compares designs), cheapest first.
  auto fail = [&r](const std::string& what) { r.failed += (r.failed.empty() ? "" : "; ") + what; };
  if (p.valve.length_m < limits.min_length_per_gap * p.valve.gap_m) {
    fail("valve length " + fixed(p.valve.length_m / p.valve.gap_m, 2) + " gaps");
  }
  if (r.coil_time_constant_s > limits.coil_time_constant_s * (1.0 + 1e-9)) {
    fail("coil time constant " + fixed(r.coil_time_constant_s * 1e3, 2) + " ms");
  }
  if (r.rail_voltage_V > p.coil.supply_voltage_V) {
    fail("a full-scale step needs " + fixed(r.rail_voltage_V, 1) + " V (rail-limited)");
  }
  if (r.temperature_rise_K > limits.temperature_rise_K) {
    fail("temperature rise " + fixed(r.temperature_rise_K, 2) + " K");
  }
  const std::size_t cell = m.fluid_cell_index(p.design.row, p.design.col).value;
  const model::Result<double> i_design =
      m.current_for_force_A(cell, p.design.indentation_m, 0.0, p.design.force_range_N);
  r.range_use = i_design.ok() ? i_design.value / i_max : -1.0;
  if (!i_design.ok()) {
    fail("the design force is outside the envelope");
  } else if (r.range_use < limits.min_range_use - 1e-3 || r.range_use > limits.max_range_use + 1e-3) {
    // (1e-3: the sizing rule sets range_use exactly; the check recomputes it on another table)
    fail("the design force needs " + fixed(100.0 * r.range_use, 2) + " % of the current range");
  }
  r.force_per_count_fraction = largest_count_step_N(m, cell) / p.design.force_range_N;
  if (!(r.force_per_count_fraction < limits.count_fraction_of_range)) {
    fail("one count moves " + fixed(100.0 * r.force_per_count_fraction, 1) + " % of the range");
  }
  if (refill && r.failed.empty()) {
    r.refill_depth_m = refill_depth_m(m);
    if (!(r.refill_depth_m < limits.refill_depth_m)) {
      fail("pad still " + fixed(r.refill_depth_m * 1e3, 3) + " mm in 0.5 s after a release");
    }
  }
  r.ok = r.failed.empty();
  return r;
}

std::string designed_toml(const std::string& base_text, const Design& design, const std::string& command) {
  const DeviceProfile& designed = design.profile;
  struct Key {
    std::string section;
    std::string key;
    std::string value;
  };
  std::vector<Key> keys = {
      {"profile", "name", "\"designed\""},
      {"profile", "description",
       "\"Design study optimum (mrskin-model-bench --suite design): the organs' coverage, docs/model.md\""},
      {"coil", "resistance_ohm", format_value(designed.coil.resistance_ohm)},
      {"coil", "inductance_H", format_value(designed.coil.inductance_H)},
      {"coil", "current_resolution_A", format_value(designed.coil.current_resolution_A)},
      {"coil", "max_current_A", format_value(designed.coil.max_current_A)},
      {"magnetic", "pole_area_m2", format_value(designed.magnetic.pole_area_m2)},
  };
  for (const DesignParam& d : design_params()) {
    if (std::string(d.key) == "range_use") {
      continue;  // not a key: max_current_A carries it
    }
    const double v = d.get(design);
    keys.push_back({d.section, d.key, d.integer ? std::to_string(std::lround(v)) : format_value(v)});
  }
  std::istringstream in(base_text);
  std::ostringstream out;
  out << "# Written by `" << command << "`: the design study's optimum (docs/model.md, \"The design\n"
      << "# study\"). Keys marked `designed` were searched or follow from those that were; the rest\n"
      << "# are the base profile's, whose comments below describe the base design.\n";
  std::string section;
  std::string line;
  while (std::getline(in, line)) {
    const std::size_t first = line.find_first_not_of(" \t");
    if (first != std::string::npos && line[first] == '[') {
      section = line.substr(first + 1, line.find(']', first) - first - 1);
    }
    for (const Key& k : keys) {
      const std::size_t eq = line.find('=');
      if (k.section == section && first != std::string::npos && eq != std::string::npos &&
          line.compare(first, k.key.size(), k.key) == 0 &&
          line.find_first_not_of(" \t", first + k.key.size()) == eq) {
        line = k.key + " = " + k.value + "  # designed";
      }
    }
    out << line << "\n";
  }
  std::string text = out.str();
  const Design back{model::parse_profile(text, "designed.toml"), design.range_use};
  for (const DesignParam& d : design_params()) {
    if (std::fabs(d.get(back) - d.get(design)) > 1e-5 * std::fabs(d.get(design))) {
      throw InvalidArgument(std::string("designed.toml: ") + d.key + " did not survive the round trip");
    }
  }
  if (std::fabs(back.profile.coil.max_current_A / designed.coil.max_current_A - 1.0) > 1e-5) {
    throw InvalidArgument("designed.toml: max_current_A did not survive the round trip");
  }
  return text;
}

}  // namespace mrskin::bench
