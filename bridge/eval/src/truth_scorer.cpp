#include "mrskin/eval/truth_scorer.hpp"

#include <algorithm>
#include <cmath>

#include "mrskin/sim/fingertip.hpp"

namespace mrskin::eval {

TruthScorer::TruthScorer(const ForceTruth& truth, std::size_t fluid_cells,
                         const bridge::BridgeOptions& options)
    : truth_(truth),
      options_(options),
      truth_N_(fluid_cells, 0.0),
      finger_m_(fluid_cells, 0.0),
      finger_prev_m_(fluid_cells, 0.0),
      finger_still_ticks_(fluid_cells, 0),
      finger_retreated_(fluid_cells, 0) {}

void TruthScorer::on_tick(const bridge::TickView& tick, bridge::BridgeStats& stats) noexcept {
  const double dt = tick.period_s();
  const std::span<const double> force_N = tick.observed_force_N();
  const std::span<const double> target_N = tick.target_N();
  const std::span<const double> tissue_N = tick.tissue_N();
  const std::span<const model::CellSolution> solve = tick.solve();
  truth_.true_forces(truth_N_);
  const bool finger_known = truth_.finger_indentation(finger_m_);
  // The finger holds when it moves out slower than this (scenes hold exactly still).
  constexpr double kHoldRate_m_per_s = 1e-6;
  const int still_ticks = std::max(1, static_cast<int>(std::lround(kStill_s / dt)));
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
      // once it has been still for kStill_s, not before (docs/bridge.md, "Scoring").
      if (finger_rate < -kHoldRate_m_per_s) {
        finger_still_ticks_[i] = 0;
        finger_retreated_[i] = 1;
      } else if (finger_rate > kHoldRate_m_per_s) {
        finger_still_ticks_[i] = 0;
        finger_retreated_[i] = 0;
      } else if (finger_still_ticks_[i] < still_ticks) {
        ++finger_still_ticks_[i];
      }
      const bool holding_still = finger_still_ticks_[i] >= still_ticks || finger_retreated_[i] == 0;
      pressing = touching && finger_rate >= -kHoldRate_m_per_s && holding_still;
      retreating = touching && !pressing;
    }
    // A pressed cell the controller does not load is scored against the bare tissue law, except
    // that a released cell (in contact, valves open) cannot render less than what the fluid and
    // the membrane push: the envelope's floor, the observer's force, as for a loaded cell with
    // its valves open (docs/bridge.md, "Scoring").
    double target = role_loaded ? target_N[i] : std::clamp(tissue_N[i], 0.0, options_.max_force_N);
    if (c.role == model::CellRole::unloading && tick.valves_open(i)) {
      target = std::max(target, std::min(force_N[i], options_.max_force_N));
    }
    const double e = truth_N_[i] - target;
    if (pressing) {
      stats.force_sq_error_sum_N2 += e * e;
      stats.force_max_abs_error_N = std::max(stats.force_max_abs_error_N, std::abs(e));
      ++stats.force_samples;
      if (target >= options_.relative_error_floor_N) {
        stats.relative_error.add(e / target);
      }
      // The same law and envelope at the finger's true state (without it: the estimated one).
      double true_state_N = target;
      if (finger_known) {
        true_state_N = std::min(tick.law_force_N(i, finger_m_[i], finger_rate), options_.max_force_N);
        if (role_loaded) {
          const double floor_N = tick.valves_open(i) ? force_N[i] : c.force_min_N;
          true_state_N = std::clamp(true_state_N, floor_N, std::max(floor_N, c.force_max_N));
        } else if (c.role == model::CellRole::unloading && tick.valves_open(i)) {
          true_state_N = std::max(true_state_N, std::min(force_N[i], options_.max_force_N));
        }
      }
      const double e_true = truth_N_[i] - true_state_N;
      stats.true_state_sq_error_sum_N2 += e_true * e_true;
      if (true_state_N >= options_.relative_error_floor_N) {
        stats.true_state_relative_error.add(e_true / true_state_N);
      }
      // Against the law itself, neither clamped into the envelope nor floored by open valves.
      const double law_N = tissue_N[i];
      const double law_true_N =
          finger_known ? std::clamp(tick.law_force_N(i, finger_m_[i], finger_rate), 0.0, options_.max_force_N)
                       : law_N;
      bridge::BridgeStats::Unclamped& u = stats.unclamped;
      const double e_law = truth_N_[i] - law_N;
      const double e_law_true = truth_N_[i] - law_true_N;
      u.sq_error_sum_N2 += e_law * e_law;
      u.true_state_sq_error_sum_N2 += e_law_true * e_law_true;
      if (law_N >= options_.relative_error_floor_N) {
        u.relative_error.add(e_law / law_N);
      }
      if (law_true_N >= options_.relative_error_floor_N) {
        u.true_state_relative_error.add(e_law_true / law_true_N);
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

void press_scene_finger(const bridge::Scene& scene, double t_s, const GridLayout& layout,
                        std::span<double> indentation_m, double depth_scale) noexcept {
  const bridge::Scene::SkinContact contact = scene.skin_contact(t_s, layout.rows(), layout.cols());
  sim::press_fingertip(layout, contact.at.row, contact.at.col, contact.depth_m * depth_scale, indentation_m);
}

}  // namespace mrskin::eval
