// Watches each rendered tick after it, from its record: the clamp counts, the energy at each
// cell's rendered port (passivity), and with a truth (the mock's) the rendered force's error.
// Evaluation, not rendering: nothing here feeds back into the tick. Private to the bridge library.
#pragma once

#include <span>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "tick_record.hpp"

namespace mrskin::bridge::detail {

class TickScorer {
 public:
  // Setup: sizes every per-cell array. options and layout are the bridge's and outlive this.
  TickScorer(const BridgeOptions& options, const GridLayout& layout, double max_current_A);

  void set_truth(const ForceTruth* truth) noexcept { truth_ = truth; }
  // After the tick: record as the stages left it, solve the inverse's cells (roles, envelopes),
  // memory the render stage's cells (the laws rendered).
  void score(const TickRecord& record, std::span<const model::CellSolution> solve,
             std::span<const CellMemory> memory, BridgeStats& stats) noexcept;

 private:
  void score_against_truth(const TickRecord& record, std::span<const model::CellSolution> solve,
                           std::span<const CellMemory> memory, BridgeStats& stats) noexcept;
  [[nodiscard]] bool open(const TickRecord& record, std::size_t cell) const noexcept;

  const BridgeOptions& options_;
  const GridLayout& layout_;
  double max_current_A_;
  const ForceTruth* truth_ = nullptr;
  std::vector<PassivityObserver> port_;   // per cell: energy at the rendered port...
  std::vector<unsigned char> port_open_;  // ...while the finger is in the cell
  std::vector<double> truth_N_;
  std::vector<double> finger_m_;                 // the truth's finger this tick...
  std::vector<double> finger_prev_m_;            // ...and last tick
  std::vector<int> finger_still_ticks_;          // per cell: ticks the true finger has not moved
  std::vector<unsigned char> finger_retreated_;  // per cell: its last move was out
  static constexpr int kStillTicks = 5;          // still this long after a retreat: holding
};

}  // namespace mrskin::bridge::detail
