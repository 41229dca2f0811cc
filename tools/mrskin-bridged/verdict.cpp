#include "verdict.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cstdint>
#include <string_view>

namespace mrskin::bridged {
namespace {

// The relative-error histogram's last bin holds everything from 100 % up.
std::string percent_or_above(double fraction) {
  return fraction > 1.0 ? std::string("above 100 %") : fmt::format("{:.1f} %", 100.0 * fraction);
}

std::string clamp_note(const bridge::BridgeStats& s) {
  const bridge::BridgeStats::ClampCauses& c = s.clamp_causes;
  const auto pct = [&](std::uint64_t n) {
    return 100.0 * static_cast<double>(n) /
           static_cast<double>(std::max<std::uint64_t>(1, s.target_cell_ticks));
  };
  return fmt::format(
      "clamped {:.1f} % of the loaded cell-ticks (floor: p0 {:.1f} %, viscous {:.1f} %, membrane {:.1f} %; "
      "ceiling {:.1f} %): there the tissue asked for a force outside the skin's envelope (the valves only "
      "resist), and the surgeon felt on average {:.3f} N away from the tissue; the product's figure is "
      "scored against the target clamped into the envelope, the unclamped figure beside it is what only "
      "the device's design can improve (docs/statistics.md, `clamped`)",
      100.0 * s.clamped_fraction(), pct(c.floor_p0), pct(c.floor_viscous), pct(c.floor_membrane),
      pct(c.ceiling), s.clamped_missed_force_mean_N());
}

}  // namespace

std::vector<std::string> verdict_lines(const bridge::BridgeStats& s, bool truth_scored, double period_s,
                                       const VerdictLimits& limits) {
  std::vector<std::string> why;    // each figure beyond its limit, in plain words
  std::vector<std::string> notes;  // what a figure within its limit does not show
  std::vector<std::string> parts;
  bool all_met = true;

  // Rendering: against the target clamped into the envelope, with the true state beside it.
  if (!truth_scored || s.force_samples == 0) {
    parts.emplace_back(truth_scored ? "rendering not scored (no loaded cell was scored)"
                                    : "rendering not scored (no true force on this device)");
  } else {
    const double rms = s.force_rms_error_N();
    const bool has_p95 = s.relative_error.count() > 0;
    const double p95 = has_p95 ? s.relative_error.percentile(0.95) : 0.0;
    const bool met = rms <= limits.rms_error_N && (!has_p95 || p95 <= limits.relative_p95);
    all_met = all_met && met;
    std::string part = fmt::format("rendering {}: {:.4f} N RMS (limit {:.2g} N)", met ? "met" : "NOT MET",
                                   rms, limits.rms_error_N);
    if (has_p95) {
      part += fmt::format(", p95 {:.1f} % (limit {:.0f} %)", 100.0 * p95, 100.0 * limits.relative_p95);
    }
    part += fmt::format(", against the true state {:.4f} N; against the unclamped tissue law {:.4f} N RMS",
                        s.true_state_rms_error_N(), s.unclamped_rms_error_N());
    const bool has_unclamped_p95 = s.unclamped.relative_error.count() > 0;
    const double unclamped_p95 = has_unclamped_p95 ? s.unclamped.relative_error.percentile(0.95) : 0.0;
    if (has_unclamped_p95) {
      part += fmt::format(", p95 {}", percent_or_above(unclamped_p95));
    }
    const bool unclamped_within =
        s.unclamped_rms_error_N() <= limits.rms_error_N && unclamped_p95 <= limits.relative_p95;
    part += unclamped_within
                ? " (within the limits too)"
                : " (beyond the limits; the product's figure leaves out what lies outside the envelope)";
    parts.push_back(std::move(part));
    if (!met) {
      why.push_back(fmt::format(
          "rendering: the force the skin rendered differs from the tissue's by {:.4f} N RMS (p95 {:.1f} %), "
          "beyond the product's {:.2g} N and {:.0f} %",
          rms, 100.0 * p95, limits.rms_error_N, 100.0 * limits.relative_p95));
    }
    if (s.clamped_cell_ticks > 0) {
      notes.push_back(clamp_note(s));
    }
  }

  // Real time: a tick longer than its period is the software's; late wakes are the machine's.
  if (s.overruns > 0 || s.skipped_periods > 0) {
    all_met = false;
    const double tick_p99_s = static_cast<double>(s.tick_time.percentile_ns(0.99)) * 1e-9;
    parts.push_back(
        fmt::format("real time NOT MET: {} overruns, {} skipped periods", s.overruns, s.skipped_periods));
    why.push_back(
        tick_p99_s > period_s
            ? fmt::format("real time: the tick itself took longer than its period (p99 {:.0f} us against "
                          "{:.0f} us): a rendering load this machine cannot carry at this rate",
                          tick_p99_s * 1e6, period_s * 1e6)
            : fmt::format("real time: the machine was too busy to wake the loop on time ({} overruns, {} "
                          "skipped periods, tick p99 {:.0f} us within its {:.0f} us period): not a "
                          "rendering failure; run on an idle or real-time machine (docs/loop.md)",
                          s.overruns, s.skipped_periods, tick_p99_s * 1e6, period_s * 1e6));
  } else {
    parts.emplace_back("real time met: 0 overruns");
  }

  // The bus: measured on the mock's model (bytes or time against limits.bus_load; on CAN, one bus
  // both directions share, their sum), or counted as reports per 1 ms frame (full-speed USB-HID
  // carries one each way).
  const std::string_view kind = s.bus.kind;
  const bool modelled = kind != "none";
  const bool shared = kind == "can" || kind == "canfd";
  const double load = shared ? s.bus.host_to_device.load + s.bus.device_to_host.load : s.bus_load;
  const double bus_limit = kind == "can" ? limits.classic_can_load : limits.bus_load;
  const std::string what =
      shared ? fmt::format(" of the shared {} bus, both directions", kind) : std::string();
  // Counted over a finite run, a report more or less at either end is not a rate: half a percent.
  const double limit = modelled ? bus_limit : limits.reports_per_frame * 1.005;
  if (load > limit) {
    all_met = false;
    parts.push_back(modelled ? fmt::format("bus NOT MET: {:.1f} %{} (limit {:.0f} %)", 100.0 * load, what,
                                           100.0 * bus_limit)
                             : fmt::format("bus NOT MET: {:.2f} reports a frame (limit {:.0f})", load,
                                           limits.reports_per_frame));
    why.push_back(
        modelled
            ? fmt::format("bus: the traffic needs {:.1f} % of the {} bus (dropped {} host to device, {} "
                          "device to host): a real unit on that bus would see the same delay and loss{}",
                          100.0 * load, kind, s.bus.host_to_device.dropped, s.bus.device_to_host.dropped,
                          kind == "can"
                              ? "; a unit's declared sensor deadband (protocol 1.2, docs/protocol.md "
                                "\"Sensor deadband (1.2)\") halves a typical scene's"
                              : "")
            : fmt::format("bus: the link carried {:.2f} reports a 1 ms frame, more than the one a "
                          "full-speed USB-HID unit carries (protocol 1.1 sends status and heartbeat echoes "
                          "in reports of their own; 1.2 packs them); the mock carries them anyway, a real "
                          "full-speed unit would queue and drop them (mock://?bus=hid-fs models it; "
                          "docs/protocol.md, \"Bus budget\")",
                          load));
  } else {
    parts.push_back(modelled ? fmt::format("bus met: {:.1f} %{}", 100.0 * load, what)
                             : fmt::format("bus met: {:.2f} reports a frame", load));
  }
  if (s.device_faults > 0) {
    why.push_back(fmt::format(
        "device: {} FAULT entries (e-stops included): see `fault` on the control socket", s.device_faults));
  }

  std::vector<std::string> out;
  out.reserve(notes.size() + why.size() + 1);
  for (std::string& n : notes) {
    out.push_back("  note: " + std::move(n));
  }
  for (std::string& w : why) {
    out.push_back("  why: " + std::move(w));
  }
  std::string verdict = all_met ? "verdict: OK: " : "verdict: NOT MET: ";
  for (std::size_t i = 0; i < parts.size(); ++i) {
    verdict += (i == 0 ? "" : "; ") + parts[i];
  }
  out.push_back(std::move(verdict));
  return out;
}

}  // namespace mrskin::bridged
