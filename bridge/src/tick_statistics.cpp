#include "tick_statistics.hpp"

#include <algorithm>

namespace mrskin::bridge::detail {

TickStatistics::TickStatistics(const BridgeOptions& options, std::size_t fluid_cells)
    : options_(options),
      port_(fluid_cells, PassivityObserver{options.passivity_tolerance_J}),
      port_open_(fluid_cells, 0) {}

void TickStatistics::count(const TickRecord& record, std::span<const model::CellSolution> solve,
                           BridgeStats& stats) noexcept {
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
}

}  // namespace mrskin::bridge::detail
