// The skin as a hydraulic network: fluid cells (pad + free membrane), valve chambers and the
// reservoir, joined by the profile's Bingham passages (HydraulicLink), stepped in time.
//
// Nodes and their stored energy (all pressures gauge, Pa; volumes m^3):
//   fluid cell i   bulge volume s_i = s_rest + A_eff d_i + e_i (d_i: pad depth, e_i: the cell's
//                  net fluid gain through its passages, s_rest = bulge_volume_m3(p0));
//                  p_i = p_b(s_i) (cell.hpp), stored energy U_pad(d_i) + U_bulge(s_i); force on
//                  the finger F_i = F_m(d_i) + A_eff p_i.
//   chamber v      rigid housing, fluid compressibility only: p = p0 + e_v / C_ch (C_ch small).
//   reservoir      p = p0 + e_r / C_r (profile [reservoir]).
// At rest every node is at p0. The finger only pushes: the pad sits at the contact depth while
// F_i >= 0; when the fluid pulls the membrane down faster than the finger retreats the pad
// follows F_i = 0 below the finger (contact force 0). A cell no finger touches keeps d_i = 0.
// Link l from a to b carries q_l = Q_l(p_a - p_b): the exact Bingham law of valve.hpp at the
// yield stress of its coil (zero flow inside the yield band: the passage locks), or a
// regularised law for the fast steppers. Node balance: de_n/dt = sum of inflows.
//
// Invariants (tests): sum_n e_n is constant (volume, every stepper), and for the
// discrete-gradient steppers work_J == stored_J - stored_J(initial) + dissipated_J to round-off
// (dissipated: each passage's flow times the pressure difference its law was evaluated at).
// docs/model.md (Part II) has the schemes, their accuracy and cost.
//
// Setup (constructor) may throw mrskin::InvalidArgument. After construction nothing allocates:
// set_*, step() and the accessors are noexcept and allocation-free.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>

#include "mrskin/driver/export.hpp"
#include "mrskin/driver/model/common.hpp"
#include "mrskin/driver/model/device_model.hpp"

namespace mrskin::model {

enum class Stepper : unsigned char {
  // Discrete-gradient implicit step with the exact Bingham law (stick and slip), solved by damped
  // Newton on the step's convex potential; exact energy balance; stable when valves lock.
  implicit_exact,
  // Same scheme, regularised yield: Q_exact(x) + (G_N / regularisation_viscosity_factor) x, a
  // Newtonian creep inside the yield band, smooth and strictly monotone everywhere.
  implicit_regularised,
  // One linearised (Rosenbrock-Euler) solve per step with the regularised law: the fast stepper.
  linearly_implicit_regularised,
  // Forward Euler with the regularised law: a benchmark baseline only (the chambers make it
  // unstable above dt ~ 2 C_ch / sum G, ~5e-6 s on the 5x5).
  explicit_euler,
};
MRSKIN_DRIVER_API const char* to_string(Stepper s) noexcept;

struct NetworkOptions {
  Stepper stepper = Stepper::implicit_exact;
  // Regularised law: a Newtonian conductance whose viscosity is this factor times the fluid's
  // is added to the exact law (inside the yield band: the creep of a nearly locked passage).
  double regularisation_viscosity_factor = 1.0e4;
  // Compliance of a valve chamber (fluid bulk modulus ~1.5 GPa on the chamber's volume).
  double chamber_compliance_m3_per_Pa = 1.0e-14;
  int max_newton_iterations = 50;
  // Newton stops when every node's volume residual is below this, m^3, and the last pressure
  // correction was below pressure_tolerance_Pa (the step after that is at round-off: what the
  // energy balance needs, since a chamber turns 1e-15 m^3 into 0.05 Pa). A step that reaches
  // the iteration cap with the volume residual met is accepted (reported in StepReport).
  double volume_tolerance_m3 = 1.0e-15;
  double pressure_tolerance_Pa = 1.0e-6;
  // Force-mode contacts: |contact force - force_N| at which the indentation solve stops, N.
  double force_tolerance_N = 1.0e-9;
  // Implicit steppers: evaluate the passages at the end-of-step pressures (backward Euler)
  // instead of the discrete gradient. L-stable: no ringing of nodes much stiffer than dt (the
  // small cells of 16x16 and 64x64 profiles), first order, and it dissipates numerically: the
  // energy gap work - stored change - dissipated is then that numerical dissipation (>= 0).
  bool backward_euler = false;
  // linearly_implicit_regularised: the step fails with out_of_regime when the pressures its one
  // solve predicted differ from the laws' at the new volumes by more than this fraction of the
  // pressure scale (largest predicted or new pressure, or yield threshold): dt too long for the
  // linearisation (stiff cells, a jump in the inputs). StepReport::linearisation_error reports
  // the fraction.
  double linearisation_tolerance = 0.25;
};

// A fingertip on the skin: a sphere of radius radius_m whose lowest point is at (x_m, y_m) in the
// skin's frame (origin at the centre of cell (0,0), x along columns, y along rows, pitch
// apart). Each fluid cell's pad depth is indentation_m - r^2 / (2 radius_m), r the distance from
// the contact point to the cell centre, floored at 0; several contacts take the deepest.
// In force mode the indentation is solved each step (bracketed Illinois search, every evaluation
// a trial step) so that the contact's total force equals force_N; indentation_m is its first
// guess. A negative indentation (finger above the skin) is valid.
struct Contact {
  enum class Mode : unsigned char { indentation, force };
  double x_m = 0.0;
  double y_m = 0.0;
  double radius_m = 8.0e-3;
  Mode mode = Mode::indentation;
  double indentation_m = 0.0;
  double force_N = 0.0;
};

struct StepReport {
  int iterations = 0;                // Newton iterations (1 for the one-solve steppers)
  double volume_residual_m3 = 0.0;   // implicit steppers: Newton's final residual (others 0)
  std::size_t locked_links = 0;      // passages inside their yield band
  double linearisation_error = 0.0;  // linearly_implicit_regularised only (see NetworkOptions)
};

struct NetworkEnergy {
  double work_J = 0.0;        // done by the finger on the skin since construction (or reset)
  double stored_J = 0.0;      // membranes, chambers and reservoir, now
  double dissipated_J = 0.0;  // in the passages since construction (or reset)
  double stored_initial_J = 0.0;
};

class MRSKIN_DRIVER_API NetworkSimulation {
 public:
  // Builds the network of the model's profile. Starts at rest: every pressure p0, no contact.
  NetworkSimulation(const DeviceModel& model, const NetworkOptions& options);
  ~NetworkSimulation();
  NetworkSimulation(const NetworkSimulation&) = delete;
  NetworkSimulation& operator=(const NetworkSimulation&) = delete;
  NetworkSimulation(NetworkSimulation&& other) noexcept;
  NetworkSimulation& operator=(NetworkSimulation&& other) noexcept;

  [[nodiscard]] const DeviceModel& model() const noexcept;
  [[nodiscard]] std::size_t fluid_cell_count() const noexcept;
  [[nodiscard]] std::size_t valve_count() const noexcept;
  [[nodiscard]] std::size_t link_count() const noexcept;
  [[nodiscard]] std::size_t sensor_count() const noexcept;  // the profile's sensors
  [[nodiscard]] const NetworkOptions& options() const noexcept;
  // Unknowns of the step (fluid cells + chambers + reservoir) and non-zeros of the sparse
  // factor (fixed at construction), for reports.
  [[nodiscard]] std::size_t node_count() const noexcept;
  [[nodiscard]] std::size_t factor_nonzeros() const noexcept;
  // Since construction or reset(): the depth searches of pads the fluid holds off the finger's
  // depth (one per such cell an evaluation of the step's balance; safeguarded Newton) and their
  // iterations in all, for reports and tests (a few iterations each: docs/bridge.md, "The pad's
  // depth search").
  [[nodiscard]] std::uint64_t pad_searches() const noexcept;
  [[nodiscard]] std::uint64_t pad_search_iterations() const noexcept;
  // Since construction or reset(): evaluations of the step's balance (every cell's law and every
  // link's: the dearest part of a step, a few a step), for reports and tests.
  [[nodiscard]] std::uint64_t balance_evaluations() const noexcept;

  // Inputs, taking effect at the next step. out_of_range on a size mismatch (or more than 16
  // contacts, a zero radius, a depth at or below the cell's floor), not_finite or negative on
  // bad values (the previous inputs stay).
  Status set_valve_yield_stress_Pa(std::span<const double> yield_Pa) noexcept;  // one per valve
  Status set_contacts(std::span<const Contact> contacts) noexcept;              // at most 16
  Status set_cell_indentation_m(std::span<const double> depth_m) noexcept;      // one per fluid cell
  // Back to rest, counters and energy zeroed, contacts lifted; the valves' yield stresses stay.
  void reset() noexcept;

  // Advances dt_s (> 0). Errors (state kept): not_finite (dt, or the stepper produced NaN),
  // out_of_range (dt <= 0; a force-mode contact that cannot reach its force), no_convergence,
  // out_of_regime (linearly_implicit_regularised: dt too long for its linearisation).
  Result<StepReport> step(double dt_s) noexcept;

  // step(dt_s) spread over several calls, for a caller with a budget per call (the observer's
  // tick): begin_step takes the inputs as they are and does the first of kStepPhases phases,
  // each advance_step the next; the value is true once the step is committed, its state then
  // what step(dt_s) leaves, to the bit. Only the linearly_implicit_regularised stepper on
  // set_cell_indentation_m depths is split: its parts (evaluate the cells, then each link;
  // assemble; factorise row by row; solve; settle each cell; check) are shared out so that each
  // phase does about an eighth of the work, and the last commits; any other setup does the whole
  // step in begin_step. Errors as step's, state kept. A setter, reset() or step() while a step
  // is in phases abandons it (nothing of it is committed); advance_step with none in progress is
  // out_of_range.
  static constexpr int kStepPhases = 8;
  Result<bool> begin_step(double dt_s) noexcept;
  Result<bool> advance_step() noexcept;
  [[nodiscard]] bool step_in_progress() const noexcept;

  // State after the last step. The spans stay valid, showing the latest state, for the object's
  // life (a moved-from object has none).
  [[nodiscard]] std::span<const double> cell_indentation_m() const noexcept;  // pad depth
  [[nodiscard]] std::span<const double> cell_velocity_m_per_s() const noexcept;
  [[nodiscard]] std::span<const double> cell_pressure_Pa() const noexcept;
  [[nodiscard]] std::span<const double> cell_force_N() const noexcept;  // on the finger (truth)
  // Each fluid cell's force on the finger were its pad at depth_m[i] now, its fluid as the last
  // step left it plus gain_m3[i] (empty: none; the caller's estimate of the flow since): the
  // cell's undrained law, 0 at depth 0 or where the fluid holds the pad deeper. At the depths of
  // the last step and no gain it is cell_force_N(), to the bit, for a pad the finger holds.
  // out_of_range (nothing written) unless depth_m and force_N hold a value per fluid cell and
  // gain_m3 one per cell or none.
  Status cell_force_at_depth_N(std::span<const double> depth_m, std::span<const double> gain_m3,
                               std::span<double> force_N) const noexcept;
  // Moves gain_m3 on by dt_s for the cells at depth (depth_m[i] > 0): an explicit step of their
  // passages alone, at the valves' yield_Pa (one per valve), the regularised law, between the
  // cell (at its depth, its fluid as the last step left it plus gain_m3[i]) and the other end
  // (a touched cell likewise; any other node as the last step left it), every flow taken at the
  // pressures before the step. For a caller between steps. out_of_range (nothing moved) on a
  // size mismatch, and dt_s must be finite and > 0.
  Status advance_cell_gain(std::span<const double> depth_m, std::span<const double> yield_Pa, double dt_s,
                           std::span<double> gain_m3) noexcept;
  [[nodiscard]] std::span<const double> chamber_pressure_Pa() const noexcept;  // one per valve (0 if none)
  [[nodiscard]] double reservoir_pressure_Pa() const noexcept;
  [[nodiscard]] std::span<const double> link_flow_m3_per_s() const noexcept;  // a -> b positive
  [[nodiscard]] double total_fluid_volume_change_m3() const noexcept;         // sum of e_n: stays 0
  [[nodiscard]] NetworkEnergy energy() const noexcept;
  // Contact force of each contact (force mode: the solved indentation is in contact_indentation_m).
  [[nodiscard]] std::span<const double> contact_force_N() const noexcept;
  [[nodiscard]] std::span<const double> contact_indentation_m() const noexcept;
  // The profile's sensors, in their SI unit, noise-free and unquantised:
  //   displacement at a fluid cell: its pad depth; at a valve: the mean pad depth of the fluid
  //   cells it joins (the valve cell's plate rests on their rims);
  //   force: the same with contact forces; pressure: the node's pressure (valve: its chamber).
  // Writes min(out.size(), sensor_count()) values.
  void read_sensors(std::span<double> out) const noexcept;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace mrskin::model
