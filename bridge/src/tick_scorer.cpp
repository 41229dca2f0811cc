#include "tick_scorer.hpp"

#include <algorithm>
#include <cmath>

#include "allocate_stage.hpp"

namespace mrskin::bridge::detail {

TickScorer::TickScorer(const BridgeOptions& options, const GridLayout& layout, double max_current_A)
    : options_(options), layout_(layout), max_current_A_(max_current_A) {
  const std::size_t cells = layout.fluid_cell_count();
  port_.assign(cells, PassivityObserver{options.passivity_tolerance_J});
  port_open_.assign(cells, 0);
  truth_N_.assign(cells, 0.0);
  finger_m_.assign(cells, 0.0);
  finger_prev_m_.assign(cells, 0.0);
  finger_still_ticks_.assign(cells, 0);
  finger_retreated_.assign(cells, 0);
}

bool TickScorer::open(const TickRecord& record, std::size_t cell) const noexcept {
  return valves_open(layout_, record.allocated.current_A, cell, max_current_A_);
}

void TickScorer::score(const TickRecord& record, std::span<const model::CellSolution> solve,
                       std::span<const CellMemory> memory, BridgeStats& stats) noexcept {
  const Rendering& rendered = record.rendered;
  for (std::size_t i = 0; i < solve.size(); ++i) {
    const bool loaded =
        solve[i].role == model::CellRole::loading || solve[i].role == model::CellRole::holding;
    if (loaded) {
      ++stats.target_cell_ticks;
      if (solve[i].clamped_low || solve[i].clamped_high || record.allocated.below_floor[i] != 0) {
        ++stats.clamped_cell_ticks;
      }
    }
    // The rendered port opens and closes at zero force and depth, so the energy of the first and
    // last contact threshold's worth of travel is counted both ways.
    const bool contact = rendered.contact[i] != 0;
    if (contact || port_open_[i] != 0) {
      PassivityObserver& port = port_[i];
      const double before_J = port.stats().energy_J;
      if (port_open_[i] == 0) {
        port.observe(0.0, 0.0);
      }
      port.observe(contact ? rendered.tissue_N[i] : 0.0, contact ? rendered.state[i].indentation_m : 0.0);
      port_open_[i] = contact ? 1 : 0;
      stats.passivity_energy_J += port.stats().energy_J - before_J;
      stats.passivity_min_energy_J = std::min(stats.passivity_min_energy_J, port.stats().min_energy_J);
    }
  }
  // The ports' total: below zero the rendering gave energy.
  if (stats.passivity_energy_J < -options_.passivity_tolerance_J) {
    ++stats.active_ticks;
  }
  if (truth_ != nullptr) {
    score_against_truth(record, solve, memory, stats);
  }
}

void TickScorer::score_against_truth(const TickRecord& record, std::span<const model::CellSolution> solve,
                                     std::span<const CellMemory> memory, BridgeStats& stats) noexcept {
  const double dt = 1.0 / options_.rate_hz;
  const std::span<const double> force_N = record.observed.force_N;
  const std::span<const double> target_N = record.allocated.target_N;
  const std::span<const double> tissue_N = record.rendered.tissue_N;
  truth_->true_forces(truth_N_);
  const bool finger_known = truth_->finger_indentation(finger_m_);
  // The finger holds when it moves out slower than this (scenes hold exactly still).
  constexpr double kHoldRate_m_per_s = 1e-6;
  for (std::size_t i = 0; i < truth_N_.size(); ++i) {
    const model::CellSolution& c = solve[i];
    const bool role_loaded = c.role == model::CellRole::loading || c.role == model::CellRole::holding;
    bool pressing = role_loaded;
    bool retreating = false;
    double finger_rate = 0.0;
    if (finger_known) {
      const bool touching = finger_m_[i] > options_.contact_threshold_m;
      finger_rate = (finger_m_[i] - finger_prev_m_[i]) / dt;
      // A finger still for one tick in the middle of a retreat is one whose script was not
      // advanced that tick (the daemon moves it from another thread, every ~1.1 ms): it holds
      // once it has been still for kStillTicks, not before (docs/bridge.md, "Scoring").
      if (finger_rate < -kHoldRate_m_per_s) {
        finger_still_ticks_[i] = 0;
        finger_retreated_[i] = 1;
      } else if (finger_rate > kHoldRate_m_per_s) {
        finger_still_ticks_[i] = 0;
        finger_retreated_[i] = 0;
      } else if (finger_still_ticks_[i] < kStillTicks) {
        ++finger_still_ticks_[i];
      }
      const bool holding_still = finger_still_ticks_[i] >= kStillTicks || finger_retreated_[i] == 0;
      pressing = touching && finger_rate >= -kHoldRate_m_per_s && holding_still;
      retreating = touching && !pressing;
    }
    // A pressed cell the controller does not load is scored against the bare tissue law, except
    // that a released cell (in contact, valves open) cannot render less than what the fluid and
    // the membrane push: the envelope's floor, the observer's force, as for a loaded cell with
    // its valves open (docs/bridge.md, "Scoring").
    double target = role_loaded ? target_N[i] : std::clamp(tissue_N[i], 0.0, options_.max_force_N);
    if (c.role == model::CellRole::unloading && open(record, i)) {
      target = std::max(target, std::min(force_N[i], options_.max_force_N));
    }
    const double e = truth_N_[i] - target;
    if (pressing) {
      stats.force_sq_error_sum_N2 += e * e;
      stats.force_max_abs_error_N = std::max(stats.force_max_abs_error_N, std::abs(e));
      ++stats.force_samples;
      if (target >= 0.3) {
        stats.relative_error.add(e / target);
      }
      // The same law and envelope at the finger's true state (without it: the estimated one).
      double true_state_N = target;
      if (finger_known) {
        true_state_N = std::min(memory[i].law.force_N(finger_m_[i], finger_rate), options_.max_force_N);
        if (role_loaded) {
          const double floor_N = open(record, i) ? force_N[i] : c.force_min_N;
          true_state_N = std::clamp(true_state_N, floor_N, std::max(floor_N, c.force_max_N));
        } else if (c.role == model::CellRole::unloading && open(record, i)) {
          true_state_N = std::max(true_state_N, std::min(force_N[i], options_.max_force_N));
        }
      }
      const double e_true = truth_N_[i] - true_state_N;
      stats.true_state_sq_error_sum_N2 += e_true * e_true;
      if (true_state_N >= 0.3) {
        stats.true_state_relative_error.add(e_true / true_state_N);
      }
    } else if (retreating) {
      stats.release_sq_error_sum_N2 += e * e;
      ++stats.release_samples;
    }
  }
  if (finger_known) {
    std::copy(finger_m_.begin(), finger_m_.end(), finger_prev_m_.begin());
  }
}

}  // namespace mrskin::bridge::detail
