#include "allocate_stage.hpp"

#include <algorithm>
#include <limits>

namespace mrskin::bridge::detail {
namespace {
constexpr double kNotLoaded = std::numeric_limits<double>::quiet_NaN();  // no envelope to show
}  // namespace

bool valves_open(const GridLayout& layout, std::span<const double> current_A, std::size_t cell,
                 double max_current_A) noexcept {
  const double open_A = kOpenValveFraction * max_current_A;
  return std::ranges::all_of(layout.valves_of_cell(cell),
                             [&](std::size_t v) { return current_A[v] <= open_A; });
}

AllocateStage::AllocateStage(const BridgeOptions& options, const GridLayout& layout,
                             const model::DeviceModel& model, model::CellInverse& inverse,
                             const model::CellObserver& observer, std::span<const double> valve_gain,
                             double max_current_A) noexcept
    : options_(options),
      layout_(layout),
      model_(model),
      inverse_(inverse),
      observer_(observer),
      valve_gain_(valve_gain),
      max_current_A_(max_current_A) {}

void AllocateStage::run(const Rendering& rendered, std::span<const double> force_N, double since_start_s,
                        BridgeStats& stats, Allocation& out) noexcept {
  out.solved = inverse_.solve(rendered.target, rendered.state, since_start_s) == model::Status::ok;
  if (!out.solved) {
    ++stats.inverse_errors;  // the last good currents stand
    return;
  }
  const std::span<const double> currents = inverse_.currents_A();
  std::copy(currents.begin(), currents.end(), out.current_A.begin());
  lock_short_cells(rendered, force_N, out.current_A);
  if (options_.compensate_hysteresis) {
    compensate_hysteresis(out.current_A);
  }
  clamp_targets_into_envelope(rendered, force_N, out);
  stats.inverse_residual_sum_N += inverse_.report().residual_norm_N;
  if (inverse_.report().from_cache) {
    ++stats.inverse_cached;
  }
}

void AllocateStage::lock_short_cells(const Rendering& rendered, std::span<const double> force_N,
                                     std::span<double> current_A) const noexcept {
  // Semi-active: a loaded cell that wants more than the quasi-static envelope allows (or more
  // than it has yet, below) gains nothing from open valves and loses fluid through them. Its
  // valves hold at least the threshold of the force it asked for (p = (F - F_membrane) / A_eff
  // across the two passages of a chamber), so no volume leaves before the finger has pushed the
  // pressure there.
  const std::span<const model::CellSolution> cells = inverse_.cells();
  const model::ContactPatch& patch = model_.contact();
  const double per_passage_Pa_per_Pa = model_.valve_law().yield_pressure_Pa(1.0);
  for (std::size_t i = 0; i < cells.size(); ++i) {
    const model::CellSolution& c = cells[i];
    const bool holding = c.role == model::CellRole::holding;
    const bool loaded = holding || c.role == model::CellRole::loading;
    const double margin = holding ? options_.hold_margin : 0.0;
    // A loading cell whose observed force is still below its request: the inverse's feed-forward
    // expects the viscous force of a steady flow through open valves, but the network's
    // compliance is still filling, and open valves would let the finger's volume out before it
    // builds the pressure. Held at the request's threshold until the force gets there.
    const bool short_of_request =
        options_.lock_while_short && c.role == model::CellRole::loading && force_N[i] < c.requested_force_N;
    if (!loaded || !(c.clamped_high || margin > 0.0 || short_of_request)) {
      continue;
    }
    const model::Result<double> membrane_N =
        model::pad_membrane_force_N(patch, rendered.state[i].indentation_m);
    if (!membrane_N.ok() || patch.effective_area_m2 <= 0.0) {
      continue;
    }
    const double pressure_Pa =
        ((1.0 + margin) * c.requested_force_N - membrane_N.value) / patch.effective_area_m2;
    const double yield_Pa = std::max(0.0, pressure_Pa) / (2.0 * per_passage_Pa_per_Pa);
    for (const std::size_t v : layout_.valves_of_cell(i)) {
      const model::Result<double> lock_A = inverse_.current_for_yield_stress_A(yield_Pa / valve_gain_[v]);
      const double lock_current_A = lock_A.ok() ? lock_A.value : max_current_A_;
      current_A[v] = std::max(current_A[v], std::min(lock_current_A, max_current_A_));
    }
  }
}

void AllocateStage::compensate_hysteresis(std::span<double> current_A) const noexcept {
  // The inverse maps yield to current on the anhysteretic curve; the steel's play keeps more
  // yield coming down and gives less going up (docs/bridge.md).
  for (std::size_t v = 0; v < current_A.size(); ++v) {
    if (current_A[v] > 0.0) {
      current_A[v] = std::min(observer_.hysteresis_compensated_current_A(v, current_A[v]), max_current_A_);
    }
  }
}

void AllocateStage::clamp_targets_into_envelope(const Rendering& rendered, std::span<const double> force_N,
                                                Allocation& out) const noexcept {
  // Against the role and envelope of this tick's solve: a cell that just turned to holding is
  // scored on its hold target, never on last tick's release.
  const std::span<const model::CellSolution> cells = inverse_.cells();
  for (std::size_t i = 0; i < out.target_N.size(); ++i) {
    const model::CellSolution& c = cells[i];
    const bool loaded = c.role == model::CellRole::loading || c.role == model::CellRole::holding;
    double floor_N = c.force_min_N;
    if (loaded && valves_open(layout_, out.current_A, i, max_current_A_)) {
      // With every valve of the cell open the device cannot render less than what the fluid
      // already pushes: the observer's network force, which knows the fluid's history (pressure
      // left by earlier flow, compliance still filling). The quasi-static floor does not: as a
      // press starts it is too high, later too low (docs/bridge.md, "The envelope's floor").
      floor_N = force_N[i];
      out.below_floor[i] = rendered.tissue_N[i] < floor_N ? 1 : 0;
    } else {
      out.below_floor[i] = 0;
    }
    const double ceiling_N = std::max(floor_N, c.force_max_N);
    out.target_N[i] = loaded ? std::clamp(rendered.tissue_N[i], floor_N, ceiling_N) : 0.0;
    out.floor_N[i] = loaded ? floor_N : kNotLoaded;
    out.ceiling_N[i] = loaded ? ceiling_N : kNotLoaded;
  }
}

}  // namespace mrskin::bridge::detail
