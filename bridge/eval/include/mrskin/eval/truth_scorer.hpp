// Evaluation of the bridge against a simulated unit: scoring every rendered tick against the
// truth of the mock (its plant's contact forces and the finger it was given), and the simulated
// finger following a scene. Off the production libraries: a console links mrskin::eval only to
// measure (the daemon on mock://, the tests, the benchmarks).
#pragma once

#include <span>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/bridge/scene.hpp"
#include "mrskin/driver/force_truth.hpp"
#include "mrskin/driver/layout.hpp"
#include "mrskin/eval/export.hpp"

namespace mrskin::eval {

// Scores each rendered tick (Bridge::set_tick_watcher) into the bridge's statistics: the true
// force against the target where the true finger presses or holds (force_* and relative_error),
// against the law at the finger's true state (true_state_*), and where it retreats (release_*);
// docs/bridge.md, "Scoring", and docs/statistics.md. Allocation-free after construction.
class MRSKIN_EVAL_API TruthScorer final : public bridge::TickWatcher {
 public:
  // truth and options outlive the scorer; options are the bridge's (contact threshold, range).
  TruthScorer(const ForceTruth& truth, std::size_t fluid_cells, const bridge::BridgeOptions& options);
  void on_tick(const bridge::TickView& tick, bridge::BridgeStats& stats) noexcept override;

 private:
  const ForceTruth& truth_;
  bridge::BridgeOptions options_;
  std::vector<double> truth_N_;
  std::vector<double> finger_m_;                 // the truth's finger this tick...
  std::vector<double> finger_prev_m_;            // ...and last tick
  std::vector<int> finger_still_ticks_;          // per cell: ticks the true finger has not moved
  std::vector<unsigned char> finger_retreated_;  // per cell: its last move was out
  // Still this long after a retreat: holding. A time, not a tick count: the daemon moves the
  // finger every ~1.1 ms whatever the loop's rate (5 ticks at 1 kHz, 50 at 10 kHz).
  static constexpr double kStill_s = 5e-3;
};

// The simulated finger following the scene at scene time t_s: a fingertip (sim::press_fingertip)
// where the scene's mapping puts the slave's contact, as deep as the slave's indentation times
// depth_scale (the unit's design point: Bridge::scale().length; 1 on the default unit).
MRSKIN_EVAL_API void press_scene_finger(const bridge::Scene& scene, double t_s, const GridLayout& layout,
                                        std::span<double> indentation_m, double depth_scale = 1.0) noexcept;

}  // namespace mrskin::eval
