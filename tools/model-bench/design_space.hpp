// Design suite, part 2: the design parameters a profile exposes, their manufacturing bounds, the
// quantities derived from them (pole area, coil resistance and inductance, current resolution),
// the constraints a design must meet, and the profile file written for the optimum.
// docs/model.md, "The design study".
#pragma once

#include <array>
#include <string>

#include "mrskin/driver/model/device_model.hpp"
#include "mrskin/driver/model/profile.hpp"

namespace mrskin::bench {

// A candidate: a profile, and the share of its current range that the design force needs (the
// coil's sizing rule: max_current_A follows from it).
struct Design {
  model::DeviceProfile profile;
  double range_use = 0.8;
};

struct DesignParam {
  const char* key;      // the profile's key, with its unit (range_use: Design's)
  const char* section;  // the profile's [section]
  double lo;            // manufacturing bounds (docs/model.md gives the reasons)
  double hi;
  bool log_scale;  // searched on a geometric grid
  bool integer;
  double (*get)(const Design&);
  void (*set)(Design&, double);
};

inline constexpr std::size_t kDesignParamCount = 9;
const std::array<DesignParam, kDesignParamCount>& design_params();

// Sets what follows from the searched parameters: the fluid gap of the magnetic circuit, the
// pole face (valve length x width), the coil's resistance (the default's 0.25 mm copper at its
// 0.1 m mean turn: 35 mohm a turn) and inductance (N^2 / reluctance), and one current count
// (max current / 4000 counts, the wire protocol's 12 bits, a whole number of nA as its identity
// carries it); and the current range, so that the
// design force (2 N at 5 mm, held) needs range_use of it. False when no current renders it.
bool apply_derived(Design& d);

// The limits a design must meet.
struct DesignLimits {
  double coil_time_constant_s = 5.16e-3;     // the default profile's (set from it at run time)
  double thermal_resistance_K_per_W = 15.0;  // skin housing to air, stated (docs/model.md)
  double temperature_rise_K = 5.0;           // all coils at full current, continuously
  double count_fraction_of_range = 0.01;     // one current count, of the design force range
  double min_range_use = 0.5;                // the design force needs at least this share of I_max
  double max_range_use = 0.95;               // and leaves the feedback this much headroom
  double refill_depth_m = 0.05e-3;           // pad depth 0.5 s after a release (the network test's)
  // A valve shorter than this many gaps is not a slot: fringing widens the field and the flow
  // enters over part of the length, so neither the reluctance formula nor the slot law holds.
  double min_length_per_gap = 5.0;
};

struct ConstraintReport {
  bool ok = false;
  std::string failed;  // the first constraint that failed, with its value
  double coil_time_constant_s = 0.0;
  double rail_voltage_V = 0.0;  // full-scale step at the driver's bandwidth: R I + L w_bw I
  double coil_power_W = 0.0;    // every coil at max current
  double temperature_rise_K = 0.0;
  double force_per_count_fraction = 0.0;  // largest one-count force step over the range
  double range_use = 0.0;                 // current for the design force / max current
  double refill_depth_m = -1.0;           // -1: not checked
};

// The cheap constraints (coil, power, design point, current resolution); refill adds the
// network simulation of a press, hold and release (about 0.1 s).
ConstraintReport check_constraints(const model::DeviceModel& m, const DesignLimits& limits, bool refill);

// The base profile's TOML text with the searched and derived keys replaced, named "designed".
// Throws InvalidArgument when the result does not parse back to the same values.
std::string designed_toml(const std::string& base_text, const Design& design, const std::string& command);

}  // namespace mrskin::bench
