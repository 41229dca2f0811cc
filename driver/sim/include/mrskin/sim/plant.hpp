// The physical skin simulated under the mock device's firmware. NetworkPlant
// (network_plant.hpp) implements it; tests may plug in their own.
#pragma once

#include <cstddef>
#include <span>

#include "mrskin/sim/export.hpp"

namespace mrskin::sim {

class MRSKIN_SIM_API Plant {
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

}  // namespace mrskin::sim
