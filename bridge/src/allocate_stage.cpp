#include "allocate_stage.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

#include "mrskin/driver/model/coil.hpp"

namespace mrskin::bridge::detail {
namespace {
constexpr double kNotLoaded = std::numeric_limits<double>::quiet_NaN();  // no envelope to show
constexpr double kSealReleaseLoading_s = 0.01;  // a sealed cell loading this long is pressed on
constexpr double kFallSmoothing_s = 3e-3;       // the fall rate's smoothing (observer force noise)
// A sealed cell under a pressing finger gains about 4 times its force a second (2.1-2.6 N/s from
// 0.6 N at 5 mm/s, docs/bridge.md): a lock for being short of the law waits until the cell is
// short by more than one period of that, or it overshoots (at 200 Hz: 2 % of the law a tick).
constexpr double kSealedRise_per_s = 4.0;
constexpr double kHighestSealFraction = 0.95;  // of the highest current: the seal's delay stays finite

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
                             double max_current_A)
    : options_(options),
      layout_(layout),
      model_(model),
      inverse_(inverse),
      observer_(observer),
      valve_gain_(valve_gain),
      max_current_A_(max_current_A),
      coil_tau_s_(model::coil_time_constant_s(model.profile().coil)),
      open_drain_s_(model.cell_open_drain_time_s()),
      drain_phase_(layout.fluid_cell_count(), DrainPhase::none),
      last_force_N_(layout.fluid_cell_count(), 0.0),
      fall_N_(layout.fluid_cell_count(), 0.0),
      loading_ticks_(layout.fluid_cell_count(), 0),
      loaded_flag_(layout.fluid_cell_count(), 0) {
  was_loaded_.reserve(layout.fluid_cell_count());
  retune_rate();
}

void AllocateStage::retune_rate() noexcept {
  fall_smoothing_ = 1.0 - std::exp(-1.0 / (options_.rate_hz * kFallSmoothing_s));
  seal_release_ticks_ = std::max(1, static_cast<int>(std::lround(kSealReleaseLoading_s * options_.rate_hz)));
  short_of_law_fraction_ = std::max(0.0, 1.0 - kSealedRise_per_s / options_.rate_hz);
  // A drain the observer cannot watch cannot be sealed at its target: a cell that empties within
  // a tick ends at its open floor, and rises again only under a pressing finger (docs/bridge.md,
  // "Where the 16x16's hold goes").
  drain_seen_ = open_drain_s_ * options_.rate_hz >= 1.0;
}

void AllocateStage::run(const Rendering& rendered, std::span<const double> force_N, double since_start_s,
                        BridgeStats& stats, Allocation& out) noexcept {
  // Every cell at rest as last tick (render's word; allocate always follows render): the inverse
  // need not check each cell's inputs again.
  const bool renewed = rendered.unchanged_at_rest && !rendered.target.empty() &&
                       inverse_.renew_at_rest(rendered.target.front().valid_until_s, since_start_s);
  out.solved = renewed || inverse_.solve(rendered.target, rendered.state, since_start_s) == model::Status::ok;
  if (!out.solved) {
    ++stats.inverse_errors;  // the last good currents stand
    return;
  }
  const std::span<const double> currents = inverse_.currents_A();
  std::copy(currents.begin(), currents.end(), out.current_A.begin());
  unload_released_cells(out);
  lock_short_cells(rendered, force_N, out.current_A);
  if (options_.drain_then_seal && drain_seen_) {
    drain_then_seal(rendered, force_N, out);
  }
  if (options_.compensate_hysteresis) {
    compensate_hysteresis(out.current_A);
  }
  clamp_targets_into_envelope(rendered, force_N, out);
  stats.inverse_residual_sum_N += inverse_.report().residual_norm_N;
  if (inverse_.report().from_cache) {
    ++stats.inverse_cached;
  }
}

void AllocateStage::unload_released_cells(Allocation& out) noexcept {
  // Every stage below walks only the loaded cells. A cell not loaded has no drain memory, a zero
  // target and no envelope, so only the cells that left the loaded set this tick are written.
  const std::span<const std::uint32_t> loaded = inverse_.loaded_cells();
  for (const std::uint32_t i : was_loaded_) {
    loaded_flag_[i] = 0;
  }
  for (const std::uint32_t i : loaded) {
    loaded_flag_[i] = 1;
  }
  for (const std::uint32_t i : was_loaded_) {
    if (loaded_flag_[i] != 0) {
      continue;
    }
    drain_phase_[i] = DrainPhase::none;
    loading_ticks_[i] = 0;
    fall_N_[i] = 0.0;
    out.drain_held[i] = 0;
    out.below_floor[i] = 0;
    out.target_N[i] = 0.0;
    out.floor_N[i] = kNotLoaded;
    out.ceiling_N[i] = kNotLoaded;
  }
  was_loaded_.assign(loaded.begin(), loaded.end());  // within its reserve: no allocation
}

void AllocateStage::lock_short_cells(const Rendering& rendered, std::span<const double> force_N,
                                     std::span<double> current_A) const noexcept {
  // Semi-active: a loaded cell that wants more than the quasi-static envelope allows (or more
  // than it has yet, below) gains nothing from open valves and loses fluid through them. Its
  // valves hold at least the threshold of the force it asked for (p = (F - F_membrane) / A_eff
  // across the two passages of a chamber), so no volume leaves before the finger has pushed the
  // pressure there.
  const std::span<const model::CellSolution> cells = inverse_.cells();
  for (const std::uint32_t i : inverse_.loaded_cells()) {
    const model::CellSolution& c = cells[i];
    const bool holding = c.role == model::CellRole::holding;
    const double margin = holding ? options_.hold_margin : 0.0;
    // A loading cell whose observed force is still below its request: the inverse's feed-forward
    // expects the viscous force of a steady flow through open valves, but the network's
    // compliance is still filling, and open valves would let the finger's volume out before it
    // builds the pressure. Held at the request's threshold until the force gets there. Short of
    // its law (as far as the envelope reaches) counts too: a request the feedback wound below
    // the law would let the cell sag under it as the finger slows (BridgeOptions).
    const double short_of_N =
        options_.lock_short_of_law
            ? std::max(c.requested_force_N,
                       std::min(short_of_law_fraction_ * rendered.tissue_N[i], c.force_max_N))
            : c.requested_force_N;
    const bool short_loading =
        options_.lock_while_short && c.role == model::CellRole::loading && force_N[i] < short_of_N;
    if (!(c.clamped_high || margin > 0.0 || short_loading)) {
      continue;
    }
    for (const std::size_t v : layout_.valves_of_cell(i)) {
      const double lock_current_A =
          threshold_current_A(v, (1.0 + margin) * c.requested_force_N, rendered.state[i].indentation_m);
      current_A[v] = std::max(current_A[v], lock_current_A);
    }
  }
}

double AllocateStage::threshold_current_A(std::size_t valve, double force_N, double depth_m) const noexcept {
  // The cell's pressure at that force (p = (F - F_membrane) / A_eff) held across the two passages
  // of a chamber; the highest allowed current where the law has no answer.
  const model::ContactPatch& patch = model_.contact();
  const model::Result<double> membrane_N = model::pad_membrane_force_N(patch, depth_m);
  if (!membrane_N.ok() || patch.effective_area_m2 <= 0.0) {
    return 0.0;
  }
  const double pressure_Pa = (force_N - membrane_N.value) / patch.effective_area_m2;
  const double yield_Pa = std::max(0.0, pressure_Pa) / (2.0 * model_.valve_law().yield_pressure_Pa(1.0));
  const model::Result<double> lock_A = inverse_.current_for_yield_stress_A(yield_Pa / valve_gain_[valve]);
  return std::min(lock_A.ok() ? lock_A.value : max_current_A_, max_current_A_);
}

void AllocateStage::drain_then_seal(const Rendering& rendered, std::span<const double> force_N,
                                    Allocation& out) noexcept {
  // A held cell well above its target (a fast press left it above the law: the open-valve drag
  // while the finger moved) drains fastest with every valve open, and is sealed as it reaches
  // the target: a semi-active cell cannot win back force it let go at rest. The inverse's
  // threshold currents instead approach the target slowly from above, and the feedback winds
  // the request down meanwhile, so the cell ended below its target (docs/bridge.md, Settling).
  // Drain and seal last until the finger leaves or presses on (loading for seal_release_ticks_:
  // the role flickers to loading on single ticks of rate noise while the finger holds).
  // (A cell no finger holds has nothing to drain or seal: unload_released_cells reset it.)
  const std::span<const model::CellSolution> cells = inverse_.cells();
  for (const std::uint32_t i : inverse_.loaded_cells()) {
    const model::CellRole role = cells[i].role;
    out.drain_held[i] = 0;
    // The fall per tick, smoothed over a few ticks: the observer's force noise would seal early.
    fall_N_[i] += fall_smoothing_ * ((last_force_N_[i] - force_N[i]) - fall_N_[i]);
    if (role == model::CellRole::loading) {
      // Pushing well above its law while loading (the finger slowed or stopped before the rate
      // estimate saw it, or the feed-forward overshot): open valves shed force fastest.
      if (force_N[i] > (1.0 + options_.loading_open_fraction) * rendered.tissue_N[i] &&
          rendered.tissue_N[i] > 0.0) {
        hold_valves(i, 0.0, out.current_A);
        out.drain_held[i] = 1;
        continue;
      }
      if (drain_phase_[i] != DrainPhase::none && ++loading_ticks_[i] < seal_release_ticks_) {
        hold_valves(i, drain_phase_[i] == DrainPhase::draining ? 0.0 : max_current_A_, out.current_A);
        out.drain_held[i] = 1;
      } else {
        drain_phase_[i] = DrainPhase::none;
        loading_ticks_[i] = 0;
      }
      continue;
    }
    loading_ticks_[i] = 0;
    const double target_N = rendered.tissue_N[i];
    if (!(target_N > 0.0)) {
      drain_phase_[i] = DrainPhase::none;
      continue;
    }
    if (force_N[i] > (1.0 + options_.drain_open_fraction) * target_N) {
      drain_phase_[i] = DrainPhase::draining;
    } else if (drain_phase_[i] == DrainPhase::draining) {
      const double lead_N =
          std::max(0.0, fall_N_[i]) * options_.rate_hz * seal_delay_s(i, target_N, rendered);
      if (force_N[i] - lead_N <= target_N) {
        drain_phase_[i] = DrainPhase::sealed;
      }
    }
    if (drain_phase_[i] != DrainPhase::none) {
      hold_valves(i, drain_phase_[i] == DrainPhase::draining ? 0.0 : max_current_A_, out.current_A);
      out.drain_held[i] = 1;
    }
  }
  std::copy(force_N.begin(), force_N.end(), last_force_N_.begin());  // every cell: a press's first fall
}

double AllocateStage::seal_delay_s(std::size_t cell, double target_N,
                                   const Rendering& rendered) const noexcept {
  // Sent now, the seal holds the target once the coils have risen (first order, time constant
  // tau) from 0 A to its threshold current: tau ln(1 / (1 - I / I_max)) with I_max sent, one
  // tick later. The steel's play makes the current rising from 0 A hold less than the
  // anhysteretic curve says: the compensated current is the one that counts.
  double highest_A = 0.0;
  for (const std::size_t v : layout_.valves_of_cell(cell)) {
    const double threshold_A = threshold_current_A(v, target_N, rendered.state[cell].indentation_m);
    highest_A = std::max(highest_A, options_.compensate_hysteresis && threshold_A > 0.0
                                        ? observer_.hysteresis_compensated_current_A(v, threshold_A)
                                        : threshold_A);
  }
  const double fraction = std::min(highest_A / max_current_A_, kHighestSealFraction);
  return coil_tau_s_ * std::log(1.0 / (1.0 - fraction)) + 1.0 / options_.rate_hz;
}

void AllocateStage::hold_valves(std::size_t cell, double current_A,
                                std::span<double> currents_A) const noexcept {
  for (const std::size_t v : layout_.valves_of_cell(cell)) {
    currents_A[v] = current_A;
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
  for (const std::uint32_t i : inverse_.loaded_cells()) {  // the others: unload_released_cells
    const model::CellSolution& c = cells[i];
    double floor_N = c.force_min_N;
    if (valves_open(layout_, out.current_A, i, max_current_A_)) {
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
    out.target_N[i] = std::clamp(rendered.tissue_N[i], floor_N, ceiling_N);
    out.floor_N[i] = floor_N;
    out.ceiling_N[i] = ceiling_N;
  }
}

}  // namespace mrskin::bridge::detail
