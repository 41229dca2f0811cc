// The offline reference for CellInverse: the slow exact solve, for the tests and the model bench
// only. Not part of the installed libraries (libmrskin_model_reference is static and stays in the
// build tree): it allocates, and takes milliseconds to seconds.
#pragma once

#include <span>
#include <vector>

#include "mrskin/driver/model/device_model.hpp"
#include "mrskin/driver/model/inverse.hpp"

namespace mrskin::model {

// ---- offline reference: the slow exact solve ------------------------------------------------
// Minimises the same objective with the exact DeviceModel (cell_force with per-valve currents,
// nested exact network solves) by a bounded pattern search (single valves, then each cell's
// valves together), from `start_currents_A` and from uniform per-cell currents; targets clamped
// into the exact envelope. Allocates and takes milliseconds to seconds: benchmarks and tests only.
struct ExactInverseResult {
  Status status = Status::ok;
  std::vector<double> currents_A;      // per valve
  std::vector<double> force_N;         // exact force at currents_A, per cell (0 unless loaded)
  std::vector<double> target_force_N;  // clamped into the exact envelope (0 unless loaded)
  std::vector<CellRole> roles;
  double residual_norm_N = 0.0;  // sqrt(sum (force - target)^2) over loaded cells
  int sweeps = 0;
  long evaluations = 0;  // exact cell_force calls
};
ExactInverseResult solve_inverse_exact(const DeviceModel& model, std::span<const CellImpedanceTarget> targets,
                                       std::span<const CellState> states, double now_s,
                                       std::span<const double> start_currents_A,
                                       const InverseOptions& options = {}, int max_sweeps = 40);

// Exact forces of every loaded cell at given currents (the "rendered force" of a solution):
// out[i] = DeviceModel::cell_force at (d, max(v, 0)) for holding/loading cells, 0 otherwise.
Status exact_rendered_forces_N(const DeviceModel& model, std::span<const CellImpedanceTarget> targets,
                               std::span<const CellState> states, double now_s,
                               std::span<const double> currents_A, std::span<double> out,
                               const InverseOptions& options = {});
}  // namespace mrskin::model
