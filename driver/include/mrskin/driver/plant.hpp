// The physical skin simulated under the mock device's firmware. The device model
// (network simulation) implements this interface; PlaceholderPlant stands in until then.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>
#include <vector>

#include "mrskin/driver/layout.hpp"

namespace mrskin {

class Plant {
 public:
  Plant() = default;
  Plant(const Plant&) = delete;
  Plant& operator=(const Plant&) = delete;
  Plant(Plant&&) = delete;
  Plant& operator=(Plant&&) = delete;
  virtual ~Plant() = default;

  [[nodiscard]] virtual std::size_t sensor_count() const noexcept = 0;
  // Coil currents, A, one per valve.
  virtual void set_valve_currents(std::span<const double> current_A) noexcept = 0;
  // Finger indentation imposed on each fluid cell, m (<= 0: no contact).
  virtual void set_finger_indentation(std::span<const double> indentation_m) noexcept = 0;
  virtual void step(double dt_s) noexcept = 0;
  // Sensor readings in their SI unit, before quantisation.
  virtual void read_sensors(std::span<double> out) const noexcept = 0;
  // True contact force of each fluid cell on the finger, N (the ground truth).
  virtual void contact_forces(std::span<double> out_N) const noexcept = 0;
};

// Nominal parameters of the placeholder: per fluid cell, a mass-spring-damper (the fluid
// column) behind a stiff contact spring, held by a Coulomb yield clamp whose force is the
// mean of its valves' yield forces F_sat * tanh(I / I_0).
struct PlaceholderParams {
  double contact_stiffness_N_per_m = 2000.0;
  double membrane_stiffness_N_per_m = 100.0;
  double damping_N_s_per_m = 0.5;
  double mass_kg = 1e-3;
  double yield_saturation_N = 3.0;
  double yield_current_scale_A = 0.4;
};

// Yield force of one valve at a coil current, N.
double placeholder_yield_force(const PlaceholderParams& p, double current_A) noexcept;
// Current that gives a yield force (inverse of the above, clamped to [0, max_A]).
double placeholder_current_for_yield(const PlaceholderParams& p, double force_N, double max_A) noexcept;

class PlaceholderPlant final : public Plant {
 public:
  // Parameters are perturbed by a seeded uniform factor within +-perturbation.
  PlaceholderPlant(const GridLayout& layout, const PlaceholderParams& nominal, double perturbation,
                   std::uint64_t seed);

  [[nodiscard]] std::size_t sensor_count() const noexcept override { return cells_.size(); }
  void set_valve_currents(std::span<const double> current_A) noexcept override;
  void set_finger_indentation(std::span<const double> indentation_m) noexcept override;
  void step(double dt_s) noexcept override;
  void read_sensors(std::span<double> out) const noexcept override;
  void contact_forces(std::span<double> out_N) const noexcept override;

 private:
  struct Cell {
    PlaceholderParams p;  // this cell's perturbed parameters
    double finger_m = 0.0;
    double fluid_m = 0.0;  // fluid column displacement
    double velocity_m_per_s = 0.0;
    double yield_N = 0.0;
  };
  GridLayout layout_;
  std::vector<Cell> cells_;
  std::vector<double> valve_yield_N_;
  std::vector<double> valve_gain_;  // per-valve perturbation of the yield law
  PlaceholderParams nominal_;
};

}  // namespace mrskin
