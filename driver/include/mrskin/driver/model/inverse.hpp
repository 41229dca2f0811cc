// The inverse: per-fluid-cell impedance targets to per-valve coil currents, as one bounded
// allocation over the valves (each valve serves 2-4 cells, each cell has 2-4 valves).
//
// Model (the quasi-static cell law of cell.hpp, each loaded cell with its sinks at p0):
//   F_i = F_m(d_i) + A_eff (p0 + min(p_lock(d_i), P_i)),  P_i the valves' pressure at Q_i = A_eff v_i.
// Cell i's branches are parallel; branch b through valve v is an inlet passage and the chamber's
// m other passages in parallel (all magnetised by v), so with t_v = 2 tau_v L / h (one passage's
// yield threshold) its law is exactly P = t_v Phi_m(N q / t_v), Phi_m(r) = x(r) + x(r / m),
// x the dimensionless Bingham pressure (valve.hpp), N = 12 mu L / (w h^3). Its inverse
// q_b(P, t_v) is tabulated once per m (cubic Hermite, exact slopes), so a branch flow and its
// derivatives cost one lookup. "direct" passages are m = 0 (Phi = x), unmagnetised ones linear.
//
// Solve (per connected component of loaded cells joined by shared valves):
//   1. each loaded cell's target force -> impedance law at (d, v), capped at its ceiling, clamped
//      into the envelope [F_min, F_max] (valves at zero / maximum current; flagged);
//   2. each cell's uniform demand u_i: the valve level that alone renders its target, from a
//      second table (one lookup); every valve takes the largest demand of its loaded cells
//      (exact for isolated cells and for holding cells whose targets do not conflict);
//   3. where a shared valve is raised by a neighbour, projected Gauss-Newton on
//      sum_i (P_i(t) - P_i*)^2 + lambda |t|^2, 0 <= t <= t_max: cell rows linearised at the
//      target pressure (flow residual over the cell's conductance; holding cells: the weakest
//      branch), each step a bounded least squares solved in the row space (one small LDL^T per
//      active-set pass), warm-started from the last solve;
//   4. t_v -> tau_v -> current through an inverse of DeviceModel's yield table.
// Semi-active: valves only resist. Unloading cells (rate below -hold tolerance) and cells without
// contact or with an expired target want nothing: their valves go to zero current unless a loaded
// cell shares them.
//
// Incremental: a cell is dirty when its target changed (any field) or its state moved beyond the
// tolerances; with nothing dirty solve() returns the cached currents at once; otherwise only the
// components that hold a dirty cell, or a valve of one, are re-solved. InverseReport counts the
// work (cell and valve updates), independent of timing.
//
// Construction may throw mrskin::InvalidArgument. solve() and every accessor are noexcept, never
// allocate and never throw; a bad input returns its Status and leaves every cached output as it
// was.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>
#include <vector>

#include "mrskin/driver/export.hpp"
#include "mrskin/driver/model/common.hpp"
#include "mrskin/driver/model/device_model.hpp"

namespace mrskin::model {

// What one fluid cell should feel like: a tissue law in the indentation below the tissue's
// surface, x = indentation - surface_offset_m (no force while x <= 0):
//   F = k x^n + b x' + lambda x^n x',  then 0 <= F <= force_ceiling_N.
// n = 1, lambda = 0 is Kelvin-Voigt; b = 0 is Hunt-Crossley; b = lambda = 0, n = 1.5 is Hertz.
struct CellImpedanceTarget {
  double stiffness_N_per_m = 0.0;      // k (unit N/m^n when exponent != 1), >= 0
  double exponent = 1.0;               // n, in [0.5, 4]
  double damping_N_s_per_m = 0.0;      // b, >= 0
  double hc_damping_N_s_per_m2 = 0.0;  // lambda (unit N s/m^(n+1)), >= 0
  double surface_offset_m = 0.0;       // indentation at which the tissue's surface sits, any sign
  double force_ceiling_N = 0.0;        // >= 0
  double valid_until_s = 0.0;          // in the caller's clock; a target past it is stale
};

// A fluid cell's state, from the observer: pad indentation (<= 0: no contact) and its rate.
struct CellState {
  double indentation_m = 0.0;
  double rate_m_per_s = 0.0;
};

enum class CellRole : unsigned char {
  no_contact,  // indentation <= 0: wants nothing
  expired,     // in contact but the target is past valid_until_s: wants nothing (released)
  unloading,   // rate < -hold tolerance: released (semi-active: the valves cannot push back)
  holding,     // |rate| within the hold tolerance (or zero): the valves hold at their threshold
  loading,     // rate > 0: flow through the valves
};
MRSKIN_DRIVER_API const char* to_string(CellRole r) noexcept;

struct CellSolution {
  CellRole role = CellRole::no_contact;
  bool clamped_low = false;        // the law's force was below F_min
  bool clamped_high = false;       // the law's force was above F_max
  double requested_force_N = 0.0;  // the impedance law at the state, capped at the ceiling
  double target_force_N = 0.0;     // clamped into [force_min_N, force_max_N]
  double force_min_N = 0.0;        // renderable envelope at the state (loaded cells)
  double force_max_N = 0.0;
  double residual_N = 0.0;  // fast model's rendered force minus target_force_N (loaded cells)
};

struct InverseReport {
  Status status = Status::ok;
  std::size_t error_cell = 0;       // the first offending cell when status != ok
  bool from_cache = false;          // nothing dirty and no search under way: currents unchanged
  bool converged = true;            // every component solved this call met force_tolerance_N
  bool residual_predicted = false;  // some residuals are a tracking step's linear prediction
  std::size_t loaded_cells = 0;
  std::size_t clamped_cells = 0;  // loaded cells whose target was clamped into the envelope
  std::size_t dirty_cells = 0;    // this solve
  std::size_t cell_updates = 0;   // cell evaluations this solve (targets, envelopes, model rows)
  std::size_t valve_updates = 0;  // valve currents recomputed this solve
  std::size_t components_solved = 0;
  int iterations = 0;            // Gauss-Newton steps this solve, over all components
  double residual_norm_N = 0.0;  // sqrt(sum of residual_N^2) over loaded cells
  double max_residual_N = 0.0;
};

struct InverseOptions {
  // Rates down to -hold_rate_tolerance count as holding (observer noise must not release a
  // held press); the valves then hold as at zero rate.
  double hold_rate_tolerance_m_per_s = 1.0e-4;
  // A state that moved less than these since the cell's last update is not dirty.
  double indentation_tolerance_m = 1.0e-7;
  double rate_tolerance_m_per_s = 1.0e-6;
  // Gauss-Newton stops when every loaded cell of the component is within this (fast model).
  double force_tolerance_N = 1.0e-5;
  int max_iterations = 12;
  // A component of more than 32 loaded cells (a hand on a large grid: the sparse path, each
  // step dozens of sweeps over it) takes at most this many Gauss-Newton steps a solve and goes on
  // from its levels on the next; 0: max_iterations, as a small component. The worst tick is then
  // bounded by the steps, not by the conflict (docs/bridge.md, "Large components in steps").
  int large_component_steps = 1;
  // The same for a component of at most 32 loaded cells (the dense path), and twice it for each
  // trial of a search for better levels (a cold restart, a stall escape); 0: max_iterations, so
  // that one solve converges where it can. The bridge sets 1: the 5x5 with every cell pressed then
  // costs one step a tick, not a dozen (docs/bridge.md, "Small components in steps").
  int small_component_steps = 0;
  // Ridge on the valve levels (relative to the cells' unit sensitivity): picks the smallest
  // currents among equally good allocations.
  double regularisation = 1.0e-8;
};

class MRSKIN_DRIVER_API CellInverse {
 public:
  // Throws mrskin::InvalidArgument when the profile's hydraulic graph has a branch whose
  // passages are magnetised by different coils, or the coil cannot raise the yield stress.
  explicit CellInverse(const DeviceModel& model, const InverseOptions& options = {});
  ~CellInverse();
  CellInverse(const CellInverse&) = delete;
  CellInverse& operator=(const CellInverse&) = delete;
  CellInverse(CellInverse&& other) noexcept;
  CellInverse& operator=(CellInverse&& other) noexcept;

  [[nodiscard]] std::size_t fluid_cell_count() const noexcept;
  [[nodiscard]] std::size_t valve_count() const noexcept;

  // One allocation. targets and states: one per fluid cell (GridLayout order); now_s: the
  // caller's clock, compared with valid_until_s. Errors (nothing cached changes):
  //   out_of_range  a span of the wrong size, an indentation at or below the cell's floor,
  //                 an exponent outside [0.5, 4];
  //   not_finite    any NaN or infinite input;
  //   negative      a negative stiffness, damping or ceiling.
  Status solve(std::span<const CellImpedanceTarget> targets, std::span<const CellState> states,
               double now_s) noexcept;
  // solve() for a caller that knows its inputs are bitwise those of the last call but for the
  // targets' validity (now valid_until_s, finite, on every cell) and the clock: when the last
  // solve() succeeded and left every cell untouched (no contact, at rest; renewals since keep
  // that), nothing is examined, the cached currents stand (report().from_cache) and it returns true.
  // Otherwise it changes nothing and returns false: call solve(). The per-cell check it skips is most of an
  // idle tick's inverse on a large grid.
  [[nodiscard]] bool renew_at_rest(double valid_until_s, double now_s) noexcept;

  // After the last successful solve (zero currents before the first).
  [[nodiscard]] std::span<const double> currents_A() const noexcept;
  [[nodiscard]] std::span<const double> valve_yield_stress_Pa() const noexcept;
  [[nodiscard]] std::span<const CellSolution> cells() const noexcept;
  // The cells holding or loading after the last successful solve, ascending: a caller walks
  // these instead of every cell's role, so the untouched cells of a large grid cost nothing.
  [[nodiscard]] std::span<const std::uint32_t> loaded_cells() const noexcept;
  [[nodiscard]] const InverseReport& report() const noexcept;  // of the last call, ok or not

  // Forget every cache: the next solve recomputes every cell.
  void invalidate() noexcept;

  // The parts of a loaded cell's envelope floor (CellSolution::force_min_N) that no valve current
  // changes, at an indentation: the pad membrane's push and the reservoir's pre-pressure p0 on the
  // pad. The rest of the floor is the viscous drag of the flow through the open valves. For the
  // statistics' clamp causes (docs/statistics.md, `clamped`); not used by solve().
  struct FloorParts {
    double membrane_N = 0.0;
    double preload_N = 0.0;
  };
  [[nodiscard]] FloorParts floor_parts(double indentation_m) const noexcept;

  // The fast model itself, for tests and benchmarks (same tables as solve()):
  // valves' pressure of a cell driving flow Q >= 0 at per-valve yield stresses (size valve_count()).
  [[nodiscard]] Result<double> valve_pressure_Pa(std::size_t cell, double flow_m3_per_s,
                                                 std::span<const double> valve_yield_Pa) const noexcept;
  // Same with one yield stress on every valve (the law CellObserver's local force model uses).
  [[nodiscard]] Result<double> uniform_valve_pressure_Pa(std::size_t cell, double flow_m3_per_s,
                                                         double yield_stress_Pa) const noexcept;
  // The current that gives a yield stress (inverse of DeviceModel's table), and the largest
  // error of that inverse measured at construction (yield stress, Pa).
  [[nodiscard]] Result<double> current_for_yield_stress_A(double yield_stress_Pa) const noexcept;
  // A unit's calibrated per-valve yield gains (true / nominal yield stress at a current, one per
  // valve): the currents then give each valve the yield stress the model asked for.
  // out_of_range for a wrong size or a gain that is not finite and positive. Setup only.
  Status set_valve_yield_gain(std::span<const double> gain) noexcept;
  [[nodiscard]] double current_table_max_error_Pa() const noexcept;
  // Largest relative error of the branch-flow table against the exact law, measured at
  // construction between the table's nodes.
  [[nodiscard]] double branch_table_max_relative_error() const noexcept;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// The impedance law alone at a state (no envelope): k x^n + b x' + lambda x^n x', clamped to
// [0, force_ceiling_N]; 0 while x <= 0. No validation (solve() validates).
MRSKIN_DRIVER_API double impedance_force_N(const CellImpedanceTarget& target,
                                           const CellState& state) noexcept;

// The role solve() gives a cell at a state: no contact at indentation <= 0, expired when now is
// past its target's valid_until_s, then by rate against +-hold_rate_tolerance_m_per_s. The offline
// reference (driver/reference/) classifies with it.
MRSKIN_DRIVER_API CellRole classify_cell(const CellState& state, bool expired,
                                         double hold_rate_tolerance_m_per_s) noexcept;

}  // namespace mrskin::model
