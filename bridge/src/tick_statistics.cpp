#include "tick_statistics.hpp"

#include <algorithm>
#include <cstdint>

namespace mrskin::bridge::detail {

TickStatistics::TickStatistics(const BridgeOptions& options, const model::CellInverse& inverse,
                               std::size_t fluid_cells)
    : options_(options),
      inverse_(inverse),
      port_(fluid_cells, PassivityObserver{options.passivity_tolerance_J}),
      port_open_(fluid_cells, 0) {}

void TickStatistics::count(const TickRecord& record, std::span<const model::CellSolution> solve,
                           BridgeStats& stats) noexcept {
  const Rendering& rendered = record.rendered;
  // The loaded cells are the inverse's list (ascending, as the walk over every cell was).
  for (const std::uint32_t i : inverse_.loaded_cells()) {
    ++stats.target_cell_ticks;
    if (solve[i].clamped_low || solve[i].clamped_high || record.allocated.below_floor[i] != 0) {
      ++stats.clamped_cell_ticks;
      count_clamp(record, i, solve[i], stats);
    }
  }
  // No port open and no finger on any cell: no port to observe (an untouched skin's tick).
  if (open_ports_ == 0 && rendered.contact_cells == 0) {
    count_active_tick(stats);
    return;
  }
  for (std::size_t i = 0; i < solve.size(); ++i) {
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
      open_ports_ = open_ports_ - port_open_[i] + (contact ? 1 : 0);
      port_open_[i] = contact ? 1 : 0;
      stats.passivity_energy_J += port.stats().energy_J - before_J;
      stats.passivity_min_energy_J = std::min(stats.passivity_min_energy_J, port.stats().min_energy_J);
    }
  }
  count_active_tick(stats);
}

void TickStatistics::count_active_tick(BridgeStats& stats) const noexcept {
  // The ports' total: below zero the rendering gave energy.
  if (stats.passivity_energy_J < -options_.passivity_tolerance_J) {
    ++stats.active_ticks;
  }
}

void TickStatistics::count_clamp(const TickRecord& record, std::size_t cell, const model::CellSolution& solve,
                                 BridgeStats& stats) const noexcept {
  BridgeStats::ClampCauses& causes = stats.clamp_causes;
  const double law_N = record.rendered.tissue_N[cell];
  const double target_N = record.allocated.target_N[cell];
  const bool below_floor = record.allocated.below_floor[cell] != 0;
  if (solve.clamped_high && !below_floor) {
    ++causes.ceiling;
    causes.ceiling_missed_sum_N += std::max(0.0, law_N - target_N);
    return;
  }
  // The floor the target was held at: with every valve open the observer's force (the fluid's
  // push, history included), else the solve's quasi-static floor. Its largest part is the cause.
  const double floor_N = below_floor ? record.observed.force_N[cell] : solve.force_min_N;
  const model::CellInverse::FloorParts parts =
      inverse_.floor_parts(record.rendered.state[cell].indentation_m);
  const double viscous_N = floor_N - parts.membrane_N - parts.preload_N;
  if (viscous_N >= parts.membrane_N && viscous_N >= parts.preload_N) {
    ++causes.floor_viscous;
  } else if (parts.membrane_N >= parts.preload_N) {
    ++causes.floor_membrane;
  } else {
    ++causes.floor_p0;
  }
  causes.floor_excess_sum_N += std::max(0.0, target_N - law_N);
}

}  // namespace mrskin::bridge::detail
