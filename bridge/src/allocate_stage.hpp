// The tick's third stage: the inverse's one allocation over the shared valves, then every
// correction of its currents, in this order and only here: a loaded cell short of its request
// locked at the request's threshold, a held cell above its target drained then sealed, the
// steel's hysteresis compensated, and the targets clamped into the envelope this tick can render
// (the open-valve floor included).
// Private to the bridge library (bridge.cpp runs it).
#pragma once

#include <cstdint>
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
                std::span<const double> valve_gain, double max_current_A);

  // Solves for this tick's rendering and corrects the currents. On a failed solve the last good
  // allocation stands (out.solved false). Counts the inverse's residual, cache hits and errors.
  void run(const Rendering& rendered, std::span<const double> force_N, double since_start_s,
           BridgeStats& stats, Allocation& out) noexcept;
  void retune_rate() noexcept;  // options' rate changed: the drain's per-tick constants follow it

 private:
  void unload_released_cells(Allocation& out) noexcept;
  void lock_short_cells(const Rendering& rendered, std::span<const double> force_N,
                        std::span<double> current_A) const noexcept;
  void drain_then_seal(const Rendering& rendered, std::span<const double> force_N, Allocation& out) noexcept;
  [[nodiscard]] double threshold_current_A(std::size_t valve, double force_N, double depth_m) const noexcept;
  [[nodiscard]] double seal_delay_s(std::size_t cell, double target_N,
                                    const Rendering& rendered) const noexcept;
  void hold_valves(std::size_t cell, double current_A, std::span<double> currents_A) const noexcept;
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
  double coil_tau_s_;                   // the profile's coil time constant
  double open_drain_s_;                 // how long a cell's bulge takes to empty (DeviceModel)
  bool drain_seen_ = true;              // open_drain_s_ spans a tick: drain_then_seal applies (retune_rate)
  double fall_smoothing_ = 1.0;         // per tick (retune_rate)
  double short_of_law_fraction_ = 1.0;  // of the law, below which a loading cell locks (retune_rate)
  enum class DrainPhase : unsigned char { none, draining, sealed };
  std::vector<DrainPhase> drain_phase_;     // per fluid cell (drain_then_seal)...
  int seal_release_ticks_ = 1;              // loading this many ticks ends a seal (retune_rate)
  std::vector<double> last_force_N_;        // ...its observed force last tick...
  std::vector<double> fall_N_;              // ...how fast it falls (N per tick, smoothed)...
  std::vector<int> loading_ticks_;          // ...and how long a sealed cell has been loading
  std::vector<std::uint32_t> was_loaded_;   // the inverse's loaded cells last tick
  std::vector<unsigned char> loaded_flag_;  // per cell: in this tick's loaded set (scratch)
};

}  // namespace mrskin::bridge::detail
