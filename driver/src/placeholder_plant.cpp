#include <algorithm>
#include <cmath>

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

}  // namespace

double placeholder_yield_force(const PlaceholderParams& p, double current_A) noexcept {
  return p.yield_saturation_N * std::tanh(std::max(current_A, 0.0) / p.yield_current_scale_A);
}

double placeholder_current_for_yield(const PlaceholderParams& p, double force_N, double max_A) noexcept {
  const double ratio = std::clamp(force_N / p.yield_saturation_N, 0.0, 0.999999);
  return std::min(p.yield_current_scale_A * std::atanh(ratio), max_A);
}

PlaceholderPlant::PlaceholderPlant(const GridLayout& layout, const PlaceholderParams& nominal,
                                   double perturbation, std::uint64_t seed)
    : layout_(layout),
      cells_(layout.fluid_cell_count()),
      valve_yield_N_(layout.valve_count(), 0.0),
      valve_gain_(layout.valve_count(), 1.0) {
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
  for (std::size_t v = 0; v < valve_gain_.size(); ++v) {
    valve_yield_N_[v] = 0.0;
  }
  nominal_ = nominal;
}

void PlaceholderPlant::set_valve_currents(std::span<const double> current_A) noexcept {
  const std::size_t n = std::min(current_A.size(), valve_yield_N_.size());
  for (std::size_t v = 0; v < n; ++v) {
    valve_yield_N_[v] = valve_gain_[v] * placeholder_yield_force(nominal_, current_A[v]);
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
    const double contact = std::max(0.0, c.finger_m - c.fluid_m) * c.p.contact_stiffness_N_per_m;
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
  const std::size_t n = std::min(out.size(), cells_.size());
  for (std::size_t c = 0; c < n; ++c) {
    out[c] = std::max(cells_[c].finger_m, cells_[c].fluid_m);
  }
}

void PlaceholderPlant::contact_forces(std::span<double> out_N) const noexcept {
  const std::size_t n = std::min(out_N.size(), cells_.size());
  for (std::size_t c = 0; c < n; ++c) {
    const Cell& cell = cells_[c];
    out_N[c] = std::max(0.0, cell.finger_m - cell.fluid_m) * cell.p.contact_stiffness_N_per_m;
  }
}

}  // namespace mrskin
