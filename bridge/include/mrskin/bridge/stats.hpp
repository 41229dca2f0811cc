// Loop statistics: plain data, filled without allocation on the tick thread.
#pragma once

#include <array>
#include <cstdint>
#include <string>

#include "mrskin/driver/histogram.hpp"

namespace mrskin::bridge {

using mrskin::DurationHistogram;

struct BridgeStats {
  std::uint64_t ticks = 0;
  std::uint64_t overruns = 0;         // ticks whose work exceeded the period
  std::uint64_t skipped_periods = 0;  // periods skipped to catch up (never burst)
  std::uint64_t send_failures = 0;
  std::uint64_t slave_samples = 0;
  std::uint64_t stale_ticks = 0;  // ticks rendering without fresh slave data
  DurationHistogram tick_time;
  // Rendered-force error: plant's true force minus the target clamped into the envelope,
  // scored on contacted cells while loading and holding.
  std::uint64_t force_samples = 0;
  double force_sq_error_sum_N2 = 0.0;
  double force_max_abs_error_N = 0.0;
  std::uint64_t target_cell_ticks = 0;
  std::uint64_t clamped_cell_ticks = 0;
  std::uint64_t observer_errors = 0;    // ticks whose observer update failed (estimate held)
  std::uint64_t inverse_errors = 0;     // ticks whose allocation failed (currents held)
  std::uint64_t inverse_cached = 0;     // ticks on which nothing was dirty: no allocation work
  double max_current_A = 0.0;           // largest valve current commanded
  double inverse_residual_sum_N = 0.0;  // per tick: the allocation's residual norm (fast model)

  [[nodiscard]] double force_rms_error_N() const noexcept;
  [[nodiscard]] double clamped_fraction() const noexcept;
};

// JSON text of the statistics (allocates: call off the tick thread).
std::string to_json(const BridgeStats& stats, double tick_period_s);

}  // namespace mrskin::bridge
