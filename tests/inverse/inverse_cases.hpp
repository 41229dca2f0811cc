// Shared by the inverse tests: the default profile, and random inputs inside the operating
// envelope (fixed seeds).
#pragma once

#include <cmath>
#include <cstddef>
#include <random>
#include <string>
#include <vector>

#include "mrskin/driver/model/inverse.hpp"

namespace mrskin::test {

inline model::DeviceModel default_model() {
  return model::DeviceModel(model::load_profile(std::string(MRSKIN_TEST_PROFILE_DIR) + "/mr-skin-5x5.toml"));
}

// Inputs of every fluid cell for one call.
struct InverseCase {
  std::vector<model::CellImpedanceTarget> targets;
  std::vector<model::CellState> states;
  double now_s = 0.0;
};

// A tissue law whose force is `force_N` at the state (x = indentation, Kelvin-Voigt, no damping).
inline model::CellImpedanceTarget law_for_force(double force_N, double indentation_m) {
  model::CellImpedanceTarget t;
  t.stiffness_N_per_m = force_N / indentation_m;
  t.force_ceiling_N = 100.0;
  t.valid_until_s = 1e9;
  return t;
}

// The operating envelope: up to `max_contacts` cells in contact at 0.2-6 mm, rates -20..20 mm/s
// (a tenth exactly zero), laws k x^n + b x' + lambda x^n x' with n 1-2 and forces up to a few
// newtons, surfaces -1..3 mm, ceilings 0-5 N, a tenth of the targets stale.
class CaseGenerator {
 public:
  CaseGenerator(std::size_t cells, unsigned seed) : cells_(cells), rng_(seed) {}

  InverseCase next(std::size_t max_contacts) {
    InverseCase c;
    c.now_s = 100.0 * u(0.0, 1.0);
    c.targets.resize(cells_);
    c.states.resize(cells_);
    const std::size_t contacts = 1 + rng_() % max_contacts;
    for (std::size_t i = 0; i < cells_; ++i) {
      c.states[i] = {-2e-3 * u(0.0, 1.0), u(-0.02, 0.02)};
      c.targets[i] = law();
      c.targets[i].valid_until_s = c.now_s + (u(0.0, 1.0) < 0.1 ? -1.0 : 1.0);
    }
    for (std::size_t k = 0; k < contacts; ++k) {
      model::CellState& s = c.states[rng_() % cells_];
      s.indentation_m = u(0.2e-3, 6e-3);
      s.rate_m_per_s = u(0.0, 1.0) < 0.1 ? 0.0 : u(-0.02, 0.02);
    }
    return c;
  }

  model::CellImpedanceTarget law() {
    model::CellImpedanceTarget t;
    t.exponent = u(1.0, 2.0);
    // Scaled so that the law gives 0-3 N at 4 mm whatever the exponent.
    t.stiffness_N_per_m = u(0.0, 3.0) / std::pow(4e-3, t.exponent);
    t.damping_N_s_per_m = u(0.0, 20.0);
    t.hc_damping_N_s_per_m2 = u(0.0, 20.0) / std::pow(4e-3, t.exponent);
    t.surface_offset_m = u(-1e-3, 3e-3);
    t.force_ceiling_N = u(0.0, 5.0);
    t.valid_until_s = 1e9;
    return t;
  }

  double u(double lo, double hi) { return std::uniform_real_distribution<double>(lo, hi)(rng_); }
  std::mt19937_64& rng() { return rng_; }

 private:
  std::size_t cells_;
  std::mt19937_64 rng_;
};

}  // namespace mrskin::test
