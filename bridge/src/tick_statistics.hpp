// Statistics of each rendered tick, read from its record after it: the clamp counts and the
// energy at each cell's rendered port (passivity). Nothing here feeds back into the tick; scoring
// against a truth is a TickWatcher's (mrskin::eval::TruthScorer). Private to the bridge library.
#pragma once

#include <cstddef>
#include <span>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "tick_record.hpp"

namespace mrskin::bridge::detail {

class TickStatistics {
 public:
  // Setup: sizes every per-cell array. options and inverse are the bridge's and outlive this.
  TickStatistics(const BridgeOptions& options, const model::CellInverse& inverse, std::size_t fluid_cells);

  // After the tick: record as the stages left it, solve the inverse's cells (roles, clamps).
  void count(const TickRecord& record, std::span<const model::CellSolution> solve,
             BridgeStats& stats) noexcept;

 private:
  void count_active_tick(BridgeStats& stats) const noexcept;
  void count_clamp(const TickRecord& record, std::size_t cell, const model::CellSolution& solve,
                   BridgeStats& stats) const noexcept;

  const BridgeOptions& options_;
  const model::CellInverse& inverse_;
  std::vector<PassivityObserver> port_;   // per cell: energy at the rendered port...
  std::vector<unsigned char> port_open_;  // ...while the finger is in the cell
  std::size_t open_ports_ = 0;            // how many port_open_ are set
};

}  // namespace mrskin::bridge::detail
