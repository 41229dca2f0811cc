#include "mrskin/driver/model/calibration.hpp"

#include <toml++/toml.h>

#include <cmath>
#include <limits>
#include <optional>
#include <random>
#include <sstream>

#include "mrskin/driver/errors.hpp"

namespace mrskin::model {
namespace {

constexpr double kScaleMin = 0.5;
constexpr double kScaleMax = 2.0;

struct ScaleKey {
  const char* key;
  double Calibration::*field;
};
constexpr ScaleKey kScales[] = {
    {"viscosity_scale", &Calibration::viscosity_scale},
    {"yield_scale", &Calibration::yield_scale},
    {"membrane_modulus_scale", &Calibration::membrane_modulus_scale},
    {"membrane_pretension_scale", &Calibration::membrane_pretension_scale},
    {"reservoir_compliance_scale", &Calibration::reservoir_compliance_scale},
    {"turns_scale", &Calibration::turns_scale},
    {"gap_scale", &Calibration::gap_scale},
};

double checked_scale(const toml::node& n, const std::string& origin, std::string_view key) {
  const std::optional<double> v = n.value<double>();
  if (!v || !std::isfinite(*v) || *v < kScaleMin || *v > kScaleMax) {
    std::ostringstream s;
    s << origin << ": " << key << " must be a number in [" << kScaleMin << ", " << kScaleMax
      << "] (measured / nominal); recalibrate the unit (mrskinctl calibrate)";
    throw InvalidArgument(s.str());
  }
  return *v;
}

}  // namespace

Calibration parse_calibration(std::string_view text, const std::string& origin, std::size_t valves,
                              std::size_t sensors) {
  toml::table root;
  try {
    root = toml::parse(text, origin);
  } catch (const toml::parse_error& e) {
    std::ostringstream s;
    s << origin << ": not a calibration (TOML error: " << e.description() << " at line "
      << e.source().begin.line << ")";
    throw InvalidArgument(s.str());
  }
  Calibration c;
  // Integers only: toml++ converts a float to an integer without a range check (undefined for
  // 1e75, found by the calibration fuzzer), and a serial out of 32 bits would wrap.
  const auto integer = [&](const char* key, std::int64_t lo, std::int64_t hi, std::int64_t missing) {
    const toml::node* n = root.get(key);
    if (n == nullptr) {
      return missing;
    }
    const std::optional<std::int64_t> v = n->is_integer() ? n->value<std::int64_t>() : std::nullopt;
    if (!v || *v < lo || *v > hi) {
      throw InvalidArgument(origin + ": " + key + " must be an integer from " + std::to_string(lo) + " to " +
                            std::to_string(hi));
    }
    return *v;
  };
  c.version = integer("version", 1, std::numeric_limits<std::int32_t>::max(), 0);
  if (c.version <= 0) {
    throw InvalidArgument(origin + ": a calibration needs a \"version = N\" line with N >= 1");
  }
  c.serial = static_cast<std::uint32_t>(integer("serial", 0, std::numeric_limits<std::uint32_t>::max(), 0));
  c.profile = root["profile"].value_or<std::string>("");
  for (const ScaleKey& k : kScales) {
    if (const toml::node* n = root.get(k.key)) {
      c.*k.field = checked_scale(*n, origin, k.key);
    }
  }
  if (const toml::node* n = root.get("valve_yield_gain")) {
    if (const toml::array* list = n->as_array()) {
      for (const toml::node& g : *list) {
        c.valve_yield_gain.push_back(checked_scale(g, origin, "valve_yield_gain[]"));
      }
      if (valves != 0 && c.valve_yield_gain.size() != valves) {
        throw InvalidArgument(origin + ": valve_yield_gain lists " +
                              std::to_string(c.valve_yield_gain.size()) + " valves; the unit has " +
                              std::to_string(valves) + ": recalibrate the unit");
      }
    } else {
      c.valve_yield_gain.push_back(checked_scale(*n, origin, "valve_yield_gain"));
    }
  }
  int offset_keys = 0;
  for (const char* unit : {"m", "n", "pa"}) {
    const std::string key = std::string("sensor_offset_") + unit;
    const toml::node* n = root.get(key);
    if (n == nullptr) {
      continue;
    }
    ++offset_keys;
    std::string where = origin;
    where += ": ";
    where += key;
    const toml::array* list = n->as_array();
    if (list == nullptr) {
      throw InvalidArgument(where + " must be a list, one number per sensor");
    }
    c.sensor_offset_unit = unit;
    for (const toml::node& v : *list) {
      const std::optional<double> x = v.value<double>();
      if (!x || !std::isfinite(*x)) {
        throw InvalidArgument(where +
                              " must hold finite numbers; recalibrate the unit (mrskinctl calibrate)");
      }
      c.sensor_offset.push_back(*x);
    }
    if (sensors != 0 && c.sensor_offset.size() != sensors) {
      std::ostringstream m;
      m << where << " lists " << c.sensor_offset.size() << " sensors; the unit has " << sensors
        << ": recalibrate the unit";
      throw InvalidArgument(m.str());
    }
  }
  if (offset_keys > 1) {
    throw InvalidArgument(origin + ": give one of sensor_offset_m, sensor_offset_n, sensor_offset_pa");
  }
  return c;
}

std::string format_calibration(const Calibration& c) {
  std::ostringstream s;
  s.precision(6);
  s << "# mrskin calibration (measured / nominal)\nversion = " << c.version << "\nserial = " << c.serial
    << "\nprofile = \"" << c.profile << "\"\n";
  for (const ScaleKey& k : kScales) {
    s << k.key << " = " << c.*k.field << "\n";
  }
  if (c.valve_yield_gain.empty()) {
    s << "valve_yield_gain = 1.0\n";
  } else {
    s << "valve_yield_gain = [";
    for (std::size_t v = 0; v < c.valve_yield_gain.size(); ++v) {
      s << (v == 0 ? "" : ", ") << c.valve_yield_gain[v];
    }
    s << "]\n";
  }
  if (!c.sensor_offset.empty()) {
    s << "sensor_offset_" << c.sensor_offset_unit << " = [";
    s.precision(9);
    for (std::size_t i = 0; i < c.sensor_offset.size(); ++i) {
      s << (i == 0 ? "" : ", ") << c.sensor_offset[i];
    }
    s << "]\n";
  }
  return s.str();
}

DeviceProfile apply_calibration(const DeviceProfile& nominal, const Calibration& c) {
  DeviceProfile p = nominal;
  p.fluid.viscosity_Pa_s *= c.viscosity_scale;
  p.fluid.carrier_factor *= c.yield_scale;
  p.membrane.youngs_modulus_Pa *= c.membrane_modulus_scale;
  p.membrane.pretension_N_per_m *= c.membrane_pretension_scale;
  p.reservoir.compliance_m3_per_Pa *= c.reservoir_compliance_scale;
  p.magnetic.turns = std::max(1, static_cast<int>(std::lround(p.magnetic.turns * c.turns_scale)));
  p.valve.gap_m *= c.gap_scale;
  p.magnetic.fluid_gap_m = p.valve.gap_m;
  return p;
}

Calibration measure_calibration(const DeviceProfile& nominal, const DeviceProfile& truth,
                                std::span<const double> valve_gain, double measurement_error,
                                std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> error(0.0, measurement_error);
  const auto ratio = [&](double measured, double design) { return measured / design * (1.0 + error(rng)); };
  Calibration c;
  c.version = 1;
  c.profile = nominal.name;
  c.viscosity_scale = ratio(truth.fluid.viscosity_Pa_s, nominal.fluid.viscosity_Pa_s);
  c.yield_scale = ratio(truth.fluid.carrier_factor, nominal.fluid.carrier_factor);
  c.membrane_modulus_scale = ratio(truth.membrane.youngs_modulus_Pa, nominal.membrane.youngs_modulus_Pa);
  c.membrane_pretension_scale = ratio(truth.membrane.pretension_N_per_m, nominal.membrane.pretension_N_per_m);
  c.reservoir_compliance_scale =
      ratio(truth.reservoir.compliance_m3_per_Pa, nominal.reservoir.compliance_m3_per_Pa);
  // Turns are counted, not measured.
  c.turns_scale = static_cast<double>(truth.magnetic.turns) / static_cast<double>(nominal.magnetic.turns);
  c.gap_scale = ratio(truth.valve.gap_m, nominal.valve.gap_m);
  for (const double g : valve_gain) {
    c.valve_yield_gain.push_back(g * (1.0 + error(rng)));
  }
  return c;
}

}  // namespace mrskin::model
