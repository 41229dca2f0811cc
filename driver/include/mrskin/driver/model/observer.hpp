// Per-fluid-cell indentation, rate and force, estimated from the profile's sensors through the
// network model. The default 5 x 5 has 12 displacement sensors (one under each valve cell, reading
// the mean pad depth of the fluid cells that valve joins) for 13 fluid cells, so the readings
// alone do not fix the cells' depths (the averaging map has a null space). Three facts do:
//   - depths are never negative (a finger presses, it does not pull): for presses on one or a
//     few cells the non-negative solution is unique;
//   - fewer pressed cells are likelier than a spread of small depths (an L1 weight);
//   - depths move continuously (a prior at the previous estimate plus rate * dt).
// Each tick solves that bounded least-squares problem by projected coordinate descent (warm
// started, a fixed number of sweeps, no allocation). Sensors at fluid cells enter as rows of
// their own. The rate is the filtered difference of the estimates. The force comes from the
// nominal network model (NetworkSimulation with the fast stepper), driven by the estimated
// depths and the commanded currents through the nominal coil lag and yield curve: the
// observer never sees the plant's parameters.
#pragma once

#include <cstddef>
#include <memory>
#include <span>

#include "mrskin/driver/model/common.hpp"
#include "mrskin/driver/model/device_model.hpp"
#include "mrskin/driver/model/network.hpp"

namespace mrskin::model {

struct ObserverOptions {
  // Expected depth change per tick not explained by the rate (the prior's spread), m.
  double prior_spread_m = 50e-6;
  // L1 weight on depth: a spread of this many metres over the grid costs as much as one
  // sensor standard deviation of misfit.
  double sparsity_scale_m = 2e-3;
  int sweeps = 12;
  double rate_filter_time_constant_s = 4e-3;
  Stepper force_stepper = Stepper::linearly_implicit_regularised;
  // Depths below this are no contact for the force model: with a precharged reservoir (p0 > 0)
  // the contact force jumps from 0 to p0 A_eff at first touch, so sensor noise on an untouched
  // cell must not read as a touch. Above the noise (2-3 um RMS, ~20 um max on the mock).
  double contact_threshold_m = 25e-6;
};

class CellObserver {
 public:
  // The nominal model (not copied: it must outlive the observer). Throws InvalidArgument when the
  // profile has no displacement sensor.
  CellObserver(const DeviceModel& nominal, const ObserverOptions& options);
  ~CellObserver();
  CellObserver(const CellObserver&) = delete;
  CellObserver& operator=(const CellObserver&) = delete;
  CellObserver(CellObserver&&) = delete;
  CellObserver& operator=(CellObserver&&) = delete;

  // One tick: readings in the profile's sensor order (SI units), the currents commanded to
  // each valve (A), and the tick (s). Errors (state kept): out_of_range (sizes, dt),
  // not_finite; the network model's own failure is passed through.
  Status update(std::span<const double> sensor_readings, std::span<const double> valve_current_A,
                double dt_s) noexcept;
  void reset() noexcept;
  // A unit's calibrated per-valve yield gains (true / nominal yield stress at a current), one per
  // valve; out_of_range for a wrong size or a gain that is not finite and positive. Setup only.
  Status set_valve_yield_gain(std::span<const double> gain) noexcept;

  [[nodiscard]] std::span<const double> indentation_m() const noexcept;
  [[nodiscard]] std::span<const double> velocity_m_per_s() const noexcept;
  [[nodiscard]] std::span<const double> force_N() const noexcept;
  // Root-mean-square misfit of the displacement sensors after the last update, m.
  [[nodiscard]] double sensor_misfit_m() const noexcept;
  [[nodiscard]] std::size_t fluid_cell_count() const noexcept;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace mrskin::model
