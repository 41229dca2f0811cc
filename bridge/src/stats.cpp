#include "mrskin/bridge/stats.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>

namespace mrskin::bridge {

void RelativeErrorHistogram::add(double relative) noexcept {
  if (!std::isfinite(relative)) {
    relative = 1e9;  // counted in the overflow bin
  }
  const double pos = std::abs(relative) / kBinWidth;
  const auto bin = static_cast<std::size_t>(std::min(pos, static_cast<double>(kBins - 1)));
  ++bins_[bin];
  ++count_;
}

double RelativeErrorHistogram::percentile(double q) const noexcept {
  if (count_ == 0) {
    return 0.0;
  }
  const auto rank = static_cast<std::uint64_t>(std::ceil(q * static_cast<double>(count_)));
  std::uint64_t seen = 0;
  for (std::size_t i = 0; i < kBins; ++i) {
    seen += bins_[i];
    if (seen >= rank && bins_[i] > 0) {
      return static_cast<double>(i + 1) * kBinWidth;
    }
  }
  return static_cast<double>(kBins) * kBinWidth;
}

void ForceHistogram::add(double force_N) noexcept {
  if (!std::isfinite(force_N)) {
    return;  // sources drop these; nothing to place
  }
  std::size_t bin = 0;
  if (force_N > kLow_N) {
    const double pos = std::log(force_N / kLow_N) / std::log(kRatio);
    bin = 1 + static_cast<std::size_t>(std::min(pos, static_cast<double>(kBins - 2)));
  }
  ++bins_.at(bin);
  ++count_;
  max_N_ = std::max(max_N_, force_N);
}

double ForceHistogram::percentile_N(double q) const noexcept {
  if (count_ == 0) {
    return 0.0;
  }
  const auto rank =
      std::max<std::uint64_t>(1, static_cast<std::uint64_t>(std::ceil(q * static_cast<double>(count_))));
  std::uint64_t seen = 0;
  for (std::size_t i = 0; i < kBins; ++i) {
    seen += bins_.at(i);
    if (seen >= rank) {
      if (i == 0) {
        return std::min(kLow_N, max_N_);
      }
      return std::min(kLow_N * std::pow(kRatio, static_cast<double>(i)), max_N_);
    }
  }
  return max_N_;
}

double BridgeStats::force_rms_error_N() const noexcept {
  return force_samples == 0 ? 0.0 : std::sqrt(force_sq_error_sum_N2 / static_cast<double>(force_samples));
}

double BridgeStats::release_rms_error_N() const noexcept {
  return release_samples == 0 ? 0.0
                              : std::sqrt(release_sq_error_sum_N2 / static_cast<double>(release_samples));
}

double BridgeStats::true_state_rms_error_N() const noexcept {
  return force_samples == 0 ? 0.0
                            : std::sqrt(true_state_sq_error_sum_N2 / static_cast<double>(force_samples));
}

double BridgeStats::clamped_fraction() const noexcept {
  return target_cell_ticks == 0
             ? 0.0
             : static_cast<double>(clamped_cell_ticks) / static_cast<double>(target_cell_ticks);
}

double BridgeStats::unclamped_rms_error_N() const noexcept {
  return force_samples == 0 ? 0.0 : std::sqrt(unclamped.sq_error_sum_N2 / static_cast<double>(force_samples));
}

double BridgeStats::unclamped_true_state_rms_error_N() const noexcept {
  return force_samples == 0
             ? 0.0
             : std::sqrt(unclamped.true_state_sq_error_sum_N2 / static_cast<double>(force_samples));
}

double BridgeStats::clamped_missed_force_mean_N() const noexcept {
  return clamped_cell_ticks == 0 ? 0.0
                                 : (clamp_causes.floor_excess_sum_N + clamp_causes.ceiling_missed_sum_N) /
                                       static_cast<double>(clamped_cell_ticks);
}

namespace {

std::string percentiles_us(const DurationHistogram& h) {
  return fmt::format(
      R"({{"samples": {}, "p50": {:.4g}, "p90": {:.4g}, "p99": {:.4g}, "p999": {:.4g}, "max": {:.4g}}})",
      h.count(), h.percentile_ns(0.5) / 1e3, h.percentile_ns(0.9) / 1e3, h.percentile_ns(0.99) / 1e3,
      h.percentile_ns(0.999) / 1e3, static_cast<double>(h.max_ns()) / 1e3);
}

std::string drops_by_reason(const DropCounts& drops) {
  std::string out = "{";
  for (std::size_t i = 0; i < kDropReasonCount; ++i) {
    out += fmt::format("{}\"{}\": {}", i == 0 ? "" : ", ", drop_reason_name(static_cast<DropReason>(i)),
                       drops.at(i));
  }
  return out + "}";
}

std::string direction_json(const BridgeStats::Direction& d) {
  return fmt::format(
      "{{\"load\": {:.6g}, \"packets\": {}, \"carried\": {}, \"bytes\": {}, \"dropped\": {}, "
      "\"unsent\": {}, \"max_wait_s\": {:.6g}}}",
      d.load, d.packets, d.carried, d.bytes, d.dropped, d.unsent, d.max_wait_s);
}

std::string bus_json(const BridgeStats::Bus& b) {
  return fmt::format(
      "{{\"kind\": \"{}\", \"host_to_device\": {:.6g}, \"device_to_host\": {:.6g}, \"enobufs\": {}, "
      "\"host_to_device_traffic\": {}, \"device_to_host_traffic\": {}}}",
      b.kind, b.host_to_device.load, b.device_to_host.load, b.enobufs, direction_json(b.host_to_device),
      direction_json(b.device_to_host));
}

std::string unclamped_json(const BridgeStats& s) {
  return fmt::format(
      "{{\"force_rms_error_n\": {:.6g}, \"relative_error_p95\": {:.6g}, \"relative_error_samples\": {}, "
      "\"true_state\": {{\"force_rms_error_n\": {:.6g}, \"relative_error_p95\": {:.6g}}}}}",
      s.unclamped_rms_error_N(), s.unclamped.relative_error.percentile(0.95),
      s.unclamped.relative_error.count(), s.unclamped_true_state_rms_error_N(),
      s.unclamped.true_state_relative_error.percentile(0.95));
}

std::string clamped_json(const BridgeStats& s) {
  const BridgeStats::ClampCauses& c = s.clamp_causes;
  const auto of_loaded = [&](std::uint64_t n) {
    return s.target_cell_ticks == 0 ? 0.0 : static_cast<double>(n) / static_cast<double>(s.target_cell_ticks);
  };
  const auto mean = [](double sum, std::uint64_t n) { return n == 0 ? 0.0 : sum / static_cast<double>(n); };
  const std::uint64_t floor = c.floor_viscous + c.floor_membrane + c.floor_p0;
  return fmt::format(
      "{{\"fraction\": {:.6g}, \"floor_viscous\": {:.6g}, \"floor_membrane\": {:.6g}, \"floor_p0\": {:.6g}, "
      "\"ceiling\": {:.6g}, \"missed_force_mean_n\": {:.6g}, \"floor_excess_mean_n\": {:.6g}, "
      "\"ceiling_missed_mean_n\": {:.6g}}}",
      s.clamped_fraction(), of_loaded(c.floor_viscous), of_loaded(c.floor_membrane), of_loaded(c.floor_p0),
      of_loaded(c.ceiling), s.clamped_missed_force_mean_N(), mean(c.floor_excess_sum_N, floor),
      mean(c.ceiling_missed_sum_N, c.ceiling));
}

std::string threads_json(const BridgeStats& s) {
  std::string out = fmt::format(R"({{"wall_s": {:.6g}, "by_name": [)", s.threads_wall_s);
  for (std::size_t k = 0; k < s.threads.size(); ++k) {
    const BridgeStats::ThreadCpu& t = s.threads[k];
    std::string name;  // kernel thread names are short: keep printable ASCII, no quote or backslash
    for (const char c : t.name) {
      name += c >= 0x20 && c < 0x7f && c != '"' && c != '\\' ? c : '_';
    }
    out += fmt::format(R"({}{{"name": "{}", "threads": {}, "cpu_s": {:.6g}, "cpu_fraction": {:.6g}}})",
                       k == 0 ? "" : ", ", name, t.count, t.cpu_s,
                       s.threads_wall_s > 0.0 ? t.cpu_s / s.threads_wall_s : 0.0);
  }
  return out + "]}";
}

}  // namespace

std::string to_json(const BridgeStats& s, double tick_period_s) {
  return fmt::format(
      "{{\n"
      "  \"format_version\": {},\n"
      "  \"tick_period_s\": {:.9g},\n"
      "  \"ticks\": {},\n"
      "  \"overruns\": {},\n"
      "  \"skipped_periods\": {},\n"
      "  \"send_failures\": {},\n"
      "  \"unchanged_sends_skipped\": {},\n"
      "  \"slave_samples\": {},\n"
      "  \"samples_accepted\": {},\n"
      "  \"samples_dropped\": {},\n"
      "  \"samples_dropped_by_reason\": {},\n"
      "  \"slave_force_n\": {{\"samples\": {}, \"p50\": {:.6g}, \"p99\": {:.6g}, \"max\": {:.6g}}},\n"
      "  \"stale_ticks\": {},\n"
      "  \"tick_us\": {},\n"
      "  \"processing_latency_us\": {},\n"
      "  \"end_to_end_latency_us\": {},\n"
      "  \"force_samples\": {},\n"
      "  \"force_rms_error_n\": {:.6g},\n"
      "  \"force_max_abs_error_n\": {:.6g},\n"
      "  \"relative_error_p95\": {:.6g},\n"
      "  \"relative_error_samples\": {},\n"
      "  \"true_state\": {{\"force_rms_error_n\": {:.6g}, \"relative_error_p95\": {:.6g}}},\n"
      "  \"release_rms_error_n\": {:.6g},\n"
      "  \"unclamped\": {},\n"
      "  \"outside_envelope_fraction\": {:.6g},\n"
      "  \"clamped\": {},\n"
      "  \"max_current_a\": {:.6g},\n"
      "  \"bus_load\": {:.6g},\n"
      "  \"bus\": {},\n"
      "  \"passivity\": {{\"energy_j\": {:.6g}, \"min_energy_j\": {:.6g}, \"active_ticks\": {}}},\n"
      "  \"observer_errors\": {},\n"
      "  \"sensor_faults\": {{\"found\": {}, \"halts\": {}}},\n"
      "  \"stream_stalls\": {},\n"
      "  \"stream_connections\": {{\"made\": {}, \"lost\": {}, \"restarts\": {}}},\n"
      "  \"device_faults\": {},\n"
      "  \"link_errors\": {{\"sequence_gaps\": {}, \"duplicates\": {}, \"undecodable\": {}, \"crc\": {}, "
      "\"telemetry_timeouts\": {}, \"disconnects\": {}, \"reconnects\": {}}},\n"
      "  \"inverse\": {{\"errors\": {}, \"cached_ticks\": {}, \"mean_residual_n\": {:.6g}}},\n"
      "  \"threads\": {}\n"
      "}}\n",
      kStatisticsFormatVersion, tick_period_s, s.ticks, s.overruns, s.skipped_periods, s.send_failures,
      s.unchanged_sends_skipped, s.slave_samples, s.samples_accepted, s.samples_dropped,
      drops_by_reason(s.samples_dropped_by_reason), s.slave_force.count(), s.slave_force.percentile_N(0.5),
      s.slave_force.percentile_N(0.99), s.slave_force.max_N(), s.stale_ticks, percentiles_us(s.tick_time),
      percentiles_us(s.processing_latency), percentiles_us(s.end_to_end_latency), s.force_samples,
      s.force_rms_error_N(), s.force_max_abs_error_N, s.relative_error.percentile(0.95),
      s.relative_error.count(), s.true_state_rms_error_N(), s.true_state_relative_error.percentile(0.95),
      s.release_rms_error_N(), unclamped_json(s), s.clamped_fraction(), clamped_json(s), s.max_current_A,
      s.bus_load, bus_json(s.bus), s.passivity_energy_J, s.passivity_min_energy_J, s.active_ticks,
      s.observer_errors, s.sensor_faults, s.sensor_fault_halts, s.stream_stalls, s.stream_connections,
      s.stream_disconnects, s.stream_restarts, s.device_faults, s.link.sequence_gaps, s.link.duplicates,
      s.link.undecodable, s.link.crc, s.link.telemetry_timeouts, s.link.disconnects, s.link.reconnects,
      s.inverse_errors, s.inverse_cached,
      s.ticks == 0 ? 0.0 : s.inverse_residual_sum_N / static_cast<double>(s.ticks), threads_json(s));
}

}  // namespace mrskin::bridge
