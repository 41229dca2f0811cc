// The mock device's plant: the hydraulic network simulation (model/network.hpp) run with the
// reference laws on a profile perturbed from the nominal one, so that the controller, which knows
// only the nominal profile and the stored calibration, never grades itself.
//
// What differs from the nominal profile (seeded, uniform within +-perturbation unless noted):
//   fluid viscosity and yield scale (carrier factor), membrane modulus and pre-tension, reservoir
//   compliance, coil turns (+-perturbation / 3), valve gap (+-perturbation / 5: flow goes as h^3),
//   and a yield gain per valve (manufacturing spread).
// What the controller's model leaves out:
//   coil current loop and eddy lag (model/coil.hpp), steel hysteresis (play operator, the
//   profile's coercivity times hysteresis_scale), a bus delay on commands, sensor noise and
//   quantisation to the profile's resolution.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>

#include "mrskin/driver/model/network.hpp"
#include "mrskin/driver/model/profile.hpp"
#include "mrskin/sim/export.hpp"
#include "mrskin/sim/plant.hpp"

namespace mrskin::sim {

struct NetworkPlantOptions {
  // A unit whose cells' open drain time is under this many substeps: automatic steps it by
  // backward Euler. The discrete gradient's factor a substep, (1 - x/2) / (1 + x/2) at x =
  // substep / time constant, turns negative past x = 2, and a cell of four passages drains 4
  // times faster than through one: 10 keeps a margin of 5 over that.
  static constexpr double kStiffStepRatio = 10.0;

  double perturbation = 0.15;  // relative half-width of the parameter spread
  std::uint64_t seed = 1;
  double command_delay_s = 1.5e-3;  // bus delay from command to coil driver (1-2 ms: docs/requirements.md)
  double hysteresis_scale = 1.0;    // multiplies the profile's steel coercivity (0: none)
  double sensor_noise_scale = 1.0;  // multiplies every sensor's noise_std (0: noise-free)
  bool quantise_sensors = true;     // round readings to the sensor's resolution
  model::Stepper stepper = model::Stepper::implicit_exact;
  // How the implicit steppers take a substep. The discrete gradient keeps the energy balance
  // exact but is not L-stable: a cell that empties through an open passage in far less than a
  // substep (fingertip-16x16: 3.5 us against 100 us) rings at the substep's Nyquist rate and
  // settles in a spurious locked state, under half the force a finer step gives while a finger
  // presses. Backward Euler is L-stable and first order. automatic takes backward Euler for the
  // whole unit when DeviceModel::cell_open_drain_time_s() is under kStiffStepRatio substeps.
  // Step the plant at substep_s: the choice is made for it at construction.
  enum class Integration : unsigned char { automatic, discrete_gradient, backward_euler };
  Integration integration = Integration::automatic;
  double substep_s = 1e-4;  // the step automatic judges against (MockOptions::physics_dt_s)
  // Keep a valve's yield stress while its eddy-lagged current and steel play have the bits of its
  // last gap-field solve (the solve is a pure function of them: the same results, bit for bit).
  // false solves every valve every substep (tests compare the two).
  bool reuse_settled_fields = true;
};

// The perturbed profile the plant runs on (exposed so tests can show the spread).
MRSKIN_SIM_API model::DeviceProfile perturbed_profile(const model::DeviceProfile& nominal,
                                                      double perturbation, std::uint64_t seed);

class MRSKIN_SIM_API NetworkPlant final : public Plant {
 public:
  // Throws InvalidArgument for a profile the network cannot simulate, or a substep_s that is not
  // positive and finite.
  NetworkPlant(const model::DeviceProfile& nominal, const NetworkPlantOptions& options);
  ~NetworkPlant() override;
  NetworkPlant(const NetworkPlant&) = delete;
  NetworkPlant& operator=(const NetworkPlant&) = delete;
  NetworkPlant(NetworkPlant&&) = delete;
  NetworkPlant& operator=(NetworkPlant&&) = delete;

  [[nodiscard]] std::size_t sensor_count() const noexcept override;
  void set_valve_currents(std::span<const double> current_A) noexcept override;
  void set_finger_indentation(std::span<const double> indentation_m) noexcept override;
  void step(double dt_s) noexcept override;
  void read_sensors(std::span<double> out) const noexcept override;
  void contact_forces(std::span<double> out_N) const noexcept override;

  // Ground truth for tests and statistics (never sent to the controller).
  [[nodiscard]] const model::NetworkSimulation& network() const noexcept;
  [[nodiscard]] std::span<const double> valve_yield_stress_Pa() const noexcept;
  [[nodiscard]] std::span<const double> coil_current_A() const noexcept;
  // The perturbed parameters and per-valve yield gains (what a factory calibration measures).
  [[nodiscard]] const model::DeviceProfile& true_profile() const noexcept;
  [[nodiscard]] std::span<const double> valve_yield_gain() const noexcept;
  // Steps whose network solve failed (state kept, counted; never expected).
  [[nodiscard]] std::uint64_t failed_steps() const noexcept;
  // Gap-field solves since construction, over every valve (reuse_settled_fields skips them).
  [[nodiscard]] std::uint64_t gap_field_solves() const noexcept;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace mrskin::sim
