// The physical skin simulated under the mock device's firmware. The device model
// (network simulation) implements this interface; PlaceholderPlant stands in until then.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "mrskin/driver/layout.hpp"
#include "mrskin/driver/model/profile.hpp"

namespace mrskin {

class Plant {
 public:
  Plant() = default;
  Plant(const Plant&) = delete;
  Plant& operator=(const Plant&) = delete;
  Plant(Plant&&) = delete;
  Plant& operator=(Plant&&) = delete;
  virtual ~Plant() = default;

  // One per sensor of the profile the mock device was built with, in the profile's order.
  [[nodiscard]] virtual std::size_t sensor_count() const noexcept = 0;
  // Coil currents, A, one per valve.
  virtual void set_valve_currents(std::span<const double> current_A) noexcept = 0;
  // Finger indentation imposed on each fluid cell, m (<= 0: no contact).
  virtual void set_finger_indentation(std::span<const double> indentation_m) noexcept = 0;
  virtual void step(double dt_s) noexcept = 0;
  // Sensor readings in their SI unit, before the firmware's noise and quantisation.
  virtual void read_sensors(std::span<double> out) const noexcept = 0;
  // True contact force of each fluid cell on the finger, N (the ground truth).
  virtual void contact_forces(std::span<double> out_N) const noexcept = 0;
};

// TEMPORARY: the placeholder stands in for the network plant (Device model II) and goes with
// it. Nominal parameters: per fluid cell, a mass-spring-damper (the fluid column) behind a
// stiff contact spring, held by a Coulomb yield clamp whose force is the mean of its valves'
// yield forces F_sat * tanh(I / I_0). I_0 is a fraction of the device's maximum current (the
// profile's [coil] max_current_A), so that the same share of the current range gives the same
// force whatever the profile's range: 0.8 x 0.1 A = 80 mA for the default 5 x 5.
struct PlaceholderParams {
  double contact_stiffness_N_per_m = 2000.0;
  double membrane_stiffness_N_per_m = 100.0;
  double damping_N_s_per_m = 0.5;
  double mass_kg = 1e-3;
  double yield_saturation_N = 3.0;
  double yield_current_scale_fraction = 0.8;  // I_0 / max current
};

// Yield force of one valve at a coil current, N, on a device whose maximum current is max_A.
double placeholder_yield_force(const PlaceholderParams& p, double current_A, double max_A) noexcept;
// Current that gives a yield force (inverse of the above, clamped to [0, max_A]).
double placeholder_current_for_yield(const PlaceholderParams& p, double force_N, double max_A) noexcept;

// What the placeholder can measure: displacement (m) or force (N) at a fluid cell. A profile
// whose sensors sit elsewhere (under valves, in the reservoir) or measure pressure is beyond it:
// placeholder_sensors_supported() says so, and placeholder_profile_text() rewrites such a
// profile's [sensors] into one displacement sensor per fluid cell with the profile's own
// resolution and noise (the mock device stores that text, so host and unit agree).
bool placeholder_sensors_supported(const model::DeviceProfile& profile) noexcept;
std::string placeholder_profile_text(std::string_view profile_text, const model::DeviceProfile& profile);
// profile_text with every [sensors] / [sensors.*] / [[sensors.*]] table removed and
// sensors_toml appended (a complete [sensors] table). Setup only.
std::string replace_sensors_section(std::string_view profile_text, std::string_view sensors_toml);

class PlaceholderPlant final : public Plant {
 public:
  // Parameters are perturbed by a seeded uniform factor within +-perturbation. The sensors are
  // the profile's (placeholder_sensors_supported() must hold: InvalidArgument otherwise).
  PlaceholderPlant(const model::DeviceProfile& profile, const PlaceholderParams& nominal, double perturbation,
                   std::uint64_t seed);

  [[nodiscard]] std::size_t sensor_count() const noexcept override { return sensors_.size(); }
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
  struct Sensor {
    std::size_t cell = 0;
    bool force = false;  // else displacement
  };
  GridLayout layout_;
  std::vector<Cell> cells_;
  std::vector<Sensor> sensors_;
  std::vector<double> valve_yield_N_;
  std::vector<double> valve_gain_;  // per-valve perturbation of the yield law
  PlaceholderParams nominal_;
  double max_current_A_;
};

}  // namespace mrskin
