#include "mrskin/bridge/stats.hpp"

#include <fmt/format.h>

#include <cmath>

namespace mrskin::bridge {

double BridgeStats::force_rms_error_N() const noexcept {
  return force_samples == 0 ? 0.0 : std::sqrt(force_sq_error_sum_N2 / static_cast<double>(force_samples));
}

double BridgeStats::clamped_fraction() const noexcept {
  return target_cell_ticks == 0
             ? 0.0
             : static_cast<double>(clamped_cell_ticks) / static_cast<double>(target_cell_ticks);
}

std::string to_json(const BridgeStats& s, double tick_period_s) {
  return fmt::format(
      "{{\n"
      "  \"tick_period_s\": {:.9g},\n"
      "  \"ticks\": {},\n"
      "  \"overruns\": {},\n"
      "  \"skipped_periods\": {},\n"
      "  \"send_failures\": {},\n"
      "  \"slave_samples\": {},\n"
      "  \"stale_ticks\": {},\n"
      "  \"tick_time_us\": {{\"p50\": {:.4g}, \"p90\": {:.4g}, \"p99\": {:.4g}, \"p999\": {:.4g}, \"max\": "
      "{:.4g}}},\n"
      "  \"force_error\": {{\"samples\": {}, \"rms_N\": {:.6g}, \"max_abs_N\": {:.6g}}},\n"
      "  \"clamped_fraction\": {:.6g},\n"
      "  \"max_current_a\": {:.6g},\n"
      "  \"observer_errors\": {},\n"
      "  \"inverse\": {{\"errors\": {}, \"cached_ticks\": {}, \"mean_residual_N\": {:.6g}}}\n"
      "}}\n",
      tick_period_s, s.ticks, s.overruns, s.skipped_periods, s.send_failures, s.slave_samples, s.stale_ticks,
      s.tick_time.percentile_ns(0.5) / 1e3, s.tick_time.percentile_ns(0.9) / 1e3,
      s.tick_time.percentile_ns(0.99) / 1e3, s.tick_time.percentile_ns(0.999) / 1e3,
      static_cast<double>(s.tick_time.max_ns()) / 1e3, s.force_samples, s.force_rms_error_N(),
      s.force_max_abs_error_N, s.clamped_fraction(), s.max_current_A, s.observer_errors, s.inverse_errors,
      s.inverse_cached, s.ticks == 0 ? 0.0 : s.inverse_residual_sum_N / static_cast<double>(s.ticks));
}

}  // namespace mrskin::bridge
