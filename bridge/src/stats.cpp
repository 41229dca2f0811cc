#include "mrskin/bridge/stats.hpp"

#include <cmath>
#include <fmt/format.h>

namespace mrskin::bridge {

void DurationHistogram::add(std::int64_t ns) noexcept {
  ++count_;
  max_ns_ = std::max(max_ns_, ns);
  std::size_t index = 0;
  if (ns >= 10) {
    const double pos = (std::log10(static_cast<double>(ns)) - 1.0) * kPerDecade;
    index = static_cast<std::size_t>(std::min(pos + 1.0, static_cast<double>(buckets_.size() - 1)));
  }
  ++buckets_[index];
}

double DurationHistogram::percentile_ns(double q) const noexcept {
  if (count_ == 0) {
    return 0.0;
  }
  const auto rank = static_cast<std::uint64_t>(std::ceil(q * static_cast<double>(count_)));
  std::uint64_t seen = 0;
  for (std::size_t i = 0; i < buckets_.size(); ++i) {
    seen += buckets_[i];
    if (seen >= rank && buckets_[i] > 0) {
      if (i == 0) {
        return 10.0;
      }
      // Upper edge of the bucket, never above the largest value seen.
      const double upper = std::pow(10.0, 1.0 + static_cast<double>(i) / kPerDecade);
      return std::min(upper, static_cast<double>(max_ns_));
    }
  }
  return static_cast<double>(max_ns_);
}

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
      "  \"tick_time_us\": {{\"p50\": {:.4g}, \"p90\": {:.4g}, \"p99\": {:.4g}, \"p999\": {:.4g}, \"max\": {:.4g}}},\n"
      "  \"force_error\": {{\"samples\": {}, \"rms_N\": {:.6g}, \"max_abs_N\": {:.6g}}},\n"
      "  \"clamped_fraction\": {:.6g}\n"
      "}}\n",
      tick_period_s, s.ticks, s.overruns, s.skipped_periods, s.send_failures, s.slave_samples, s.stale_ticks,
      s.tick_time.percentile_ns(0.5) / 1e3, s.tick_time.percentile_ns(0.9) / 1e3,
      s.tick_time.percentile_ns(0.99) / 1e3, s.tick_time.percentile_ns(0.999) / 1e3,
      static_cast<double>(s.tick_time.max_ns()) / 1e3, s.force_samples, s.force_rms_error_N(),
      s.force_max_abs_error_N, s.clamped_fraction());
}

}  // namespace mrskin::bridge
