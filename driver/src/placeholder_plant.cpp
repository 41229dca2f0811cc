#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <string>

#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/plant.hpp"

namespace mrskin {
namespace {

// splitmix64: small, seeded and the same on every platform.
std::uint64_t next_random(std::uint64_t& state) noexcept {
  std::uint64_t z = (state += 0x9E3779B97F4A7C15ULL);
  z = (z ^ (z >> 30U)) * 0xBF58476D1CE4E5B9ULL;
  z = (z ^ (z >> 27U)) * 0x94D049BB133111EBULL;
  return z ^ (z >> 31U);
}
double uniform(std::uint64_t& state, double lo, double hi) noexcept {
  const double u = static_cast<double>(next_random(state) >> 11U) * 0x1.0p-53;
  return lo + (hi - lo) * u;
}

bool supported(const model::SensorSpec& s) noexcept {
  return s.place == model::PlaceKind::fluid_cell &&
         (s.quantity == model::SensorQuantity::displacement || s.quantity == model::SensorQuantity::force);
}

// A TOML float that reads back as the same double ("2.5e-06", "1.0").
std::string toml_float(double v) {
  std::string text = fmt::format("{}", v);
  if (text.find_first_of(".eEn") == std::string::npos) {
    text += ".0";
  }
  return text;
}

std::string_view trim(std::string_view s) noexcept {
  while (!s.empty() && (s.front() == ' ' || s.front() == '\t')) {
    s.remove_prefix(1);
  }
  while (!s.empty() && (s.back() == ' ' || s.back() == '\t' || s.back() == '\r')) {
    s.remove_suffix(1);
  }
  return s;
}

// The table a header line opens ("sensors.sensor" for "[[sensors.sensor]]  # c"), or "" when
// the line is not a table header.
std::string_view table_of(std::string_view line) noexcept {
  line = trim(line);
  if (line.empty() || line.front() != '[') {
    return {};
  }
  const std::size_t close = line.find(']');
  if (close == std::string_view::npos) {
    return {};
  }
  std::string_view name = line.substr(0, close);
  while (!name.empty() && name.front() == '[') {
    name.remove_prefix(1);
  }
  return trim(name);
}

double contact_force_N(double finger_m, double fluid_m, double contact_stiffness_N_per_m) noexcept {
  return std::max(0.0, finger_m - fluid_m) * contact_stiffness_N_per_m;
}

}  // namespace

double placeholder_yield_force(const PlaceholderParams& p, double current_A, double max_A) noexcept {
  const double scale_A = p.yield_current_scale_fraction * max_A;
  if (!(scale_A > 0.0)) {
    return 0.0;
  }
  return p.yield_saturation_N * std::tanh(std::max(current_A, 0.0) / scale_A);
}

double placeholder_current_for_yield(const PlaceholderParams& p, double force_N, double max_A) noexcept {
  const double ratio = std::clamp(force_N / p.yield_saturation_N, 0.0, 0.999999);
  return std::clamp(p.yield_current_scale_fraction * max_A * std::atanh(ratio), 0.0, std::max(max_A, 0.0));
}

bool placeholder_sensors_supported(const model::DeviceProfile& profile) noexcept {
  return !profile.sensors.empty() && std::all_of(profile.sensors.begin(), profile.sensors.end(), supported);
}

std::string replace_sensors_section(std::string_view profile_text, std::string_view sensors_toml) {
  std::string out;
  out.reserve(profile_text.size() + sensors_toml.size() + 1);
  bool skipping = false;
  while (!profile_text.empty()) {
    const std::size_t eol = profile_text.find('\n');
    const std::string_view line =
        profile_text.substr(0, eol == std::string_view::npos ? profile_text.size() : eol + 1);
    profile_text.remove_prefix(line.size());
    const std::string_view table = table_of(line);
    if (!table.empty()) {
      skipping = table == "sensors" || table.starts_with("sensors.");
    }
    if (!skipping) {
      out += line;
    }
  }
  if (!out.empty() && out.back() != '\n') {
    out += '\n';
  }
  out += sensors_toml;
  return out;
}

std::string placeholder_profile_text(std::string_view profile_text, const model::DeviceProfile& profile) {
  if (placeholder_sensors_supported(profile)) {
    return std::string(profile_text);
  }
  // Keep the resolution and noise of the profile's first displacement sensor.
  double resolution_m = 2.5e-6;
  double noise_m = 2.0e-6;
  for (const model::SensorSpec& s : profile.sensors) {
    if (s.quantity == model::SensorQuantity::displacement) {
      resolution_m = s.resolution;
      noise_m = s.noise_std;
      break;
    }
  }
  return replace_sensors_section(
      profile_text,
      fmt::format(
          "# Rewritten by the mock device: its placeholder plant measures displacement at the fluid\n"
          "# cells only, so the profile's own sensors return with the network plant (Device model II).\n"
          "[sensors]\ngenerate = \"per_fluid_cell\"\nquantity = \"displacement\"\nunit = \"m\"\n"
          "resolution = {}\nnoise_std = {}\n",
          toml_float(resolution_m), toml_float(noise_m)));
}

PlaceholderPlant::PlaceholderPlant(const model::DeviceProfile& profile, const PlaceholderParams& nominal,
                                   double perturbation, std::uint64_t seed)
    : layout_(profile.rows, profile.cols),
      cells_(layout_.fluid_cell_count()),
      valve_yield_N_(layout_.valve_count(), 0.0),
      valve_gain_(layout_.valve_count(), 1.0),
      nominal_(nominal),
      max_current_A_(profile.coil.max_current_A) {
  if (!placeholder_sensors_supported(profile)) {
    throw InvalidArgument(
        "profile " + profile.name +
        ": the placeholder plant measures displacement or force at fluid cells only; rewrite its [sensors] "
        "with placeholder_profile_text() (the mock device does)");
  }
  for (const model::SensorSpec& s : profile.sensors) {
    sensors_.push_back({s.index, s.quantity == model::SensorQuantity::force});
  }
  std::uint64_t rng = seed;
  const double lo = 1.0 - perturbation;
  const double hi = 1.0 + perturbation;
  for (Cell& c : cells_) {
    c.p = nominal;
    c.p.contact_stiffness_N_per_m *= uniform(rng, lo, hi);
    c.p.membrane_stiffness_N_per_m *= uniform(rng, lo, hi);
    c.p.damping_N_s_per_m *= uniform(rng, lo, hi);
    c.p.mass_kg *= uniform(rng, lo, hi);
  }
  for (double& g : valve_gain_) {
    g = uniform(rng, lo, hi);
  }
}

void PlaceholderPlant::set_valve_currents(std::span<const double> current_A) noexcept {
  const std::size_t n = std::min(current_A.size(), valve_yield_N_.size());
  for (std::size_t v = 0; v < n; ++v) {
    valve_yield_N_[v] = valve_gain_[v] * placeholder_yield_force(nominal_, current_A[v], max_current_A_);
  }
  for (std::size_t c = 0; c < cells_.size(); ++c) {
    const auto& valves = layout_.valves_of_cell(c);
    double sum = 0.0;
    for (const std::size_t v : valves) {
      sum += valve_yield_N_[v];
    }
    cells_[c].yield_N = valves.empty() ? 0.0 : sum / static_cast<double>(valves.size());
  }
}

void PlaceholderPlant::set_finger_indentation(std::span<const double> indentation_m) noexcept {
  const std::size_t n = std::min(indentation_m.size(), cells_.size());
  for (std::size_t c = 0; c < n; ++c) {
    cells_[c].finger_m = indentation_m[c];
  }
}

void PlaceholderPlant::step(double dt_s) noexcept {
  for (Cell& c : cells_) {
    const double contact = contact_force_N(c.finger_m, c.fluid_m, c.p.contact_stiffness_N_per_m);
    const double free_force =
        contact - c.p.membrane_stiffness_N_per_m * c.fluid_m - c.p.damping_N_s_per_m * c.velocity_m_per_s;
    // Semi-implicit Coulomb clamp: the yield impulse can stop the column but never
    // reverse it, so locked valves stay locked without chatter.
    const double v_free = c.velocity_m_per_s + dt_s * free_force / c.p.mass_kg;
    const double v_yield = dt_s * c.yield_N / c.p.mass_kg;
    if (std::abs(v_free) <= v_yield) {
      c.velocity_m_per_s = 0.0;
    } else {
      c.velocity_m_per_s = v_free - std::copysign(v_yield, v_free);
    }
    c.fluid_m += dt_s * c.velocity_m_per_s;
  }
}

void PlaceholderPlant::read_sensors(std::span<double> out) const noexcept {
  const std::size_t n = std::min(out.size(), sensors_.size());
  for (std::size_t s = 0; s < n; ++s) {
    const Cell& c = cells_[sensors_[s].cell];
    out[s] = sensors_[s].force ? contact_force_N(c.finger_m, c.fluid_m, c.p.contact_stiffness_N_per_m)
                               : std::max(c.finger_m, c.fluid_m);
  }
}

void PlaceholderPlant::contact_forces(std::span<double> out_N) const noexcept {
  const std::size_t n = std::min(out_N.size(), cells_.size());
  for (std::size_t c = 0; c < n; ++c) {
    out_N[c] = contact_force_N(cells_[c].finger_m, cells_[c].fluid_m, cells_[c].p.contact_stiffness_N_per_m);
  }
}

}  // namespace mrskin
