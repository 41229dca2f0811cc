// A unit's calibration: how its measured parameters differ from the profile it was built to,
// as ratios (measured / nominal), stored as versioned TOML text in the unit's configuration
// memory. A host applies it to the nominal profile before building its models, so the
// observer and the inverse run the unit's own parameters rather than the design's.
//
//   version = 3                      # increases with every write (the unit refuses older)
//   serial = 48879
//   profile = "mr-skin-5x5"
//   viscosity_scale = 1.031          # every *_scale: measured / nominal, default 1
//   yield_scale = 0.962              # MR fluid yield stress (carrier factor)
//   membrane_modulus_scale = 1.084
//   membrane_pretension_scale = 0.931
//   reservoir_compliance_scale = 1.102
//   turns_scale = 1.0
//   gap_scale = 0.991
//   valve_yield_gain = [1.02, 0.97, ...]   # per valve, or one number for all
//   sensor_offset_m = [1.2e-7, ...]         # per sensor: its reading at rest, subtracted from
//                                           # every reading (_m, _n or _pa: the sensors' unit)
#pragma once

#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "mrskin/driver/export.hpp"
#include "mrskin/driver/model/profile.hpp"

namespace mrskin::model {

struct Calibration {
  long version = 0;
  std::uint32_t serial = 0;
  std::string profile;
  double viscosity_scale = 1.0;
  double yield_scale = 1.0;
  double membrane_modulus_scale = 1.0;
  double membrane_pretension_scale = 1.0;
  double reservoir_compliance_scale = 1.0;
  double turns_scale = 1.0;
  double gap_scale = 1.0;
  std::vector<double> valve_yield_gain;  // empty: 1 for every valve
  // Per sensor, in the sensors' SI unit (sensor_offset_unit: "m", "n" or "pa", the key's
  // suffix): the reading at rest, subtracted from every reading. Empty: no offsets.
  std::vector<double> sensor_offset;
  std::string sensor_offset_unit = "m";

  // The gain of valve v (1 when not calibrated per valve).
  [[nodiscard]] double valve_gain(std::size_t v) const noexcept {
    return valve_yield_gain.empty()       ? 1.0
           : valve_yield_gain.size() == 1 ? valve_yield_gain[0]
                                          : valve_yield_gain[v];
  }
};

// Parses calibration text; origin names it in errors. Throws InvalidArgument naming the bad
// key: scales must be in [0.5, 2], a per-valve list must have one entry per valve of the
// profile (valves = 0 skips that check), sensor offsets finite, one per sensor (sensors = 0
// skips that check).
MRSKIN_DRIVER_API Calibration parse_calibration(std::string_view text, const std::string& origin,
                                                std::size_t valves = 0, std::size_t sensors = 0);
MRSKIN_DRIVER_API std::string format_calibration(const Calibration& c);

// The nominal profile with the calibration's scales applied (per-valve gains are not part of
// a profile: the observer and the inverse take them separately).
MRSKIN_DRIVER_API DeviceProfile apply_calibration(const DeviceProfile& nominal, const Calibration& c);

// What a factory measures on a unit whose true parameters are `truth` (built to `nominal`),
// each ratio off by a seeded relative measurement error of spread `measurement_error`.
MRSKIN_DRIVER_API Calibration measure_calibration(const DeviceProfile& nominal, const DeviceProfile& truth,
                                                  std::span<const double> valve_gain,
                                                  double measurement_error, std::uint64_t seed);

}  // namespace mrskin::model
