// The tick's third stage: the inverse's one allocation over the shared valves, then every
// correction of its currents, in this order and only here: a loaded cell short of its request
// locked at the request's threshold, the steel's hysteresis compensated, and the targets clamped
// into the envelope this tick can render (the open-valve floor included).
// Private to the bridge library (bridge.cpp runs it).
#pragma once

#include <span>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/driver/model/device_model.hpp"
#include "tick_record.hpp"

namespace mrskin::bridge::detail {

// A valve below this fraction of full current yields next to nothing: it counts as open.
inline constexpr double kOpenValveFraction = 0.02;

// Every valve of the cell at about 0 A (at most kOpenValveFraction of max_current_A).
[[nodiscard]] bool valves_open(const GridLayout& layout, std::span<const double> current_A, std::size_t cell,
                               double max_current_A) noexcept;

class AllocateStage {
 public:
  // Setup: every reference outlives this (the bridge owns them). max_current_A: the unit's limit.
  AllocateStage(const BridgeOptions& options, const GridLayout& layout, const model::DeviceModel& model,
                model::CellInverse& inverse, const model::CellObserver& observer,
                std::span<const double> valve_gain, double max_current_A) noexcept;

  // Solves for this tick's rendering and corrects the currents. On a failed solve the last good
  // allocation stands (out.solved false). Counts the inverse's residual, cache hits and errors.
  void run(const Rendering& rendered, std::span<const double> force_N, double since_start_s,
           BridgeStats& stats, Allocation& out) noexcept;

 private:
  void lock_short_cells(const Rendering& rendered, std::span<const double> force_N,
                        std::span<double> current_A) const noexcept;
  void compensate_hysteresis(std::span<double> current_A) const noexcept;
  void clamp_targets_into_envelope(const Rendering& rendered, std::span<const double> force_N,
                                   Allocation& out) const noexcept;

  const BridgeOptions& options_;
  const GridLayout& layout_;
  const model::DeviceModel& model_;
  model::CellInverse& inverse_;
  const model::CellObserver& observer_;
  std::span<const double> valve_gain_;  // calibrated per-valve yield gain
  double max_current_A_;
};

}  // namespace mrskin::bridge::detail
