// mrskinctl selftest: link, sensor range and noise, stuck sensors, a valve sweep, leak, and the
// heartbeat round-trip latency; each item PASS, FAIL or SKIP with its measured value and limit.
// What each check means physically, and why some need the press fixture: docs/cli.md.
#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "command.hpp"
#include "ctl_device_rig.hpp"
#include "ctl_device_sampler.hpp"
#include "exit_codes.hpp"
#include "json_text.hpp"

namespace mrskin::ctl {
namespace {

struct SelftestOptions {
  std::string uri = "mock://";
  LeaseOption lease;  // --bridge: the device of a running mrskin-bridged
  bool realtime = false;
  double rest_s = 0.3;
  double press_depth_m = 3e-3;
};

enum class Verdict : unsigned char { pass, fail, skip };
const char* to_string(Verdict v) {
  return v == Verdict::pass ? "PASS" : v == Verdict::fail ? "FAIL" : "SKIP";
}

struct Item {
  std::string name;
  Verdict verdict = Verdict::skip;
  double measured = 0.0;
  double limit = 0.0;
  std::string unit;
  std::string detail;
};

std::string si(double v, std::string_view unit) { return fmt::format("{:.4g} {}", v, unit); }

// The round-trip histogram's non-empty buckets: (upper edge, ns; count).
std::vector<std::pair<double, std::uint64_t>> rtt_buckets(const DurationHistogram& h) {
  std::vector<std::pair<double, std::uint64_t>> out;
  for (std::size_t i = 0; i < DurationHistogram::bucket_count(); ++i) {
    if (h.bucket(i) > 0) {
      out.emplace_back(DurationHistogram::upper_edge_ns(i), h.bucket(i));
    }
  }
  return out;
}

// Range: at rest a displacement/force sensor reads ~0; pinned at a count limit, it is broken or
// out of its range. Limit: 20 resolution steps from zero (noise is ~1 step).
Item range_item(const SensorStats& rest, const DeviceInfo& info, const std::string& unit) {
  const std::size_t n = info.sensors;
  // Range: at rest a displacement/force sensor reads ~0; pinned at a count limit, it is broken or
  // out of its range. Limit: 20 resolution steps from zero (noise is ~1 step).
  Item it{"sensor range at rest", Verdict::pass, 0.0, 20.0 * info.sensor_lsb, unit, ""};
  const double pin_lo = protocol::kSensorCountMin * info.sensor_lsb;
  const double pin_hi = protocol::kSensorCountMax * info.sensor_lsb;
  std::size_t worst = 0;
  for (std::size_t s = 0; s < n; ++s) {
    if (std::abs(rest.mean[s]) > std::abs(rest.mean[worst])) {
      worst = s;
    }
    if (rest.min[s] <= pin_lo || rest.max[s] >= pin_hi) {
      it.verdict = Verdict::fail;
      it.detail += fmt::format("sensor {} pinned at its range limit; ", s);
    }
  }
  it.measured = n > 0 ? std::abs(rest.mean[worst]) : 0.0;
  if (rest.samples == 0) {
    it.verdict = Verdict::fail;
    it.detail = "no telemetry";
  } else if (it.measured > it.limit) {
    it.verdict = Verdict::fail;
  }
  it.detail += fmt::format("worst sensor {}, {} samples", worst, rest.samples);
  return it;
}

// Noise: standard deviation at rest against 3x the profile's noise (at least one resolution step).
Item noise_item(const SensorStats& rest, const DeviceInfo& info, const model::DeviceProfile* profile,
                const std::string& unit) {
  const std::size_t n = info.sensors;
  // Noise: standard deviation at rest against 3x the profile's noise (at least one resolution step).
  Item it{"sensor noise", Verdict::pass, 0.0, 0.0, unit, ""};
  std::size_t worst = 0;
  double worst_ratio = 0.0;
  std::string failed;
  for (std::size_t s = 0; s < n; ++s) {
    const double nominal =
        profile != nullptr && s < profile->sensors.size() ? profile->sensors[s].noise_std : info.sensor_lsb;
    const double limit = std::max(3.0 * nominal, info.sensor_lsb);
    const double ratio = rest.std_dev[s] / limit;
    if (ratio > worst_ratio || s == 0) {
      worst_ratio = ratio;
      worst = s;
      it.measured = rest.std_dev[s];
      it.limit = limit;
    }
    if (ratio > 1.0) {
      failed += fmt::format("{}{} ({})", failed.empty() ? "" : ", ", s, si(rest.std_dev[s], unit));
    }
  }
  it.verdict = failed.empty() ? Verdict::pass : Verdict::fail;
  it.detail = failed.empty() ? fmt::format("worst sensor {}", worst) : "noisy sensors: " + failed;
  return it;
}

// Span: with every cell pressed span_m (valves open), every displacement sensor reads the press.
Item span_item(const SensorStats& pressed, double span_m, const DeviceInfo& info, const std::string& unit) {
  const std::size_t n = info.sensors;
  Item it{"sensor span (press)", Verdict::pass, 0.0, 0.1, "relative", ""};
  std::string failed;
  for (std::size_t s = 0; s < n; ++s) {
    const double err = std::abs(pressed.mean[s] - span_m) / span_m;
    it.measured = std::max(it.measured, err);
    if (err > it.limit) {
      failed += fmt::format("{}{} ({})", failed.empty() ? "" : ", ", s, si(pressed.mean[s], unit));
    }
  }
  it.verdict = failed.empty() ? Verdict::pass : Verdict::fail;
  it.detail = fmt::format("press {} on every cell; ", si(span_m, "m")) +
              (failed.empty() ? "every sensor followed" : "off: " + failed);
  if (unit != "m") {
    it.verdict = Verdict::skip;
    it.detail = "the sensors are not displacement sensors: no reference value for a press";
  }
  return it;
}

// Stuck: a sensor whose reading never changes while the others do (noise at rest, the press).
Item stuck_item(const SensorStats& rest, const SensorStats* pressed, const DeviceInfo& info,
                const std::string& unit) {
  const std::size_t n = info.sensors;
  // Stuck: a sensor whose reading never changes while the others do (noise at rest, the press).
  Item it{"stuck sensor", Verdict::pass, 0.0, 0.0, unit, ""};
  std::vector<double> span(n, 0.0);
  std::vector<std::size_t> moving;
  for (std::size_t s = 0; s < n; ++s) {
    const double lo = std::min(rest.min[s], pressed != nullptr ? pressed->min[s] : rest.min[s]);
    const double hi = std::max(rest.max[s], pressed != nullptr ? pressed->max[s] : rest.max[s]);
    span[s] = hi - lo;
    if (span[s] > 0.5 * info.sensor_lsb) {
      moving.push_back(s);
    }
  }
  std::string stuck;
  it.measured = n > 0 ? *std::min_element(span.begin(), span.end()) : 0.0;
  if (moving.size() * 2 > n) {  // most sensors move: the still ones are stuck
    for (std::size_t s = 0; s < n; ++s) {
      if (span[s] <= 0.5 * info.sensor_lsb) {
        stuck += fmt::format("{}{}", stuck.empty() ? "" : ", ", s);
      }
    }
    it.verdict = stuck.empty() ? Verdict::pass : Verdict::fail;
    it.detail = stuck.empty() ? fmt::format("all {} sensors changed (smallest span shown)", n)
                              : "sensors that never changed while the others did: " + stuck;
  } else {
    it.verdict = Verdict::skip;
    it.detail = "most sensors did not change either: nothing to compare against (noise-free unit, no press)";
  }
  return it;
}

// Each sensor's residual depth must not fall as the current rises, and must rise from 0 A to the
// maximum by at least 10 resolution steps.
Item sweep_item(const std::vector<PressReleaseResult>& residual, const SensorStats& rest,
                const DeviceInfo& info, double press_depth_m, const std::string& unit) {
  const std::size_t n = info.sensors;
  const std::size_t levels = residual.size();
  // Each sensor's residual depth must not fall as the current rises,
  // and must rise from 0 A to the maximum by at least 10 resolution steps (far above the noise:
  // the energised valves held fluid out of the pads).
  Item it{"valve sweep", Verdict::pass, 0.0, 10.0 * info.sensor_lsb, unit, ""};
  std::string failed;
  double smallest_rise = std::numeric_limits<double>::infinity();
  for (std::size_t s = 0; s < n; ++s) {
    // Slack: noise, plus 10 % of the rise (the steel's remanence carries a little between steps).
    const double slack = 3.0 * std::max(rest.std_dev[s], info.sensor_lsb) +
                         0.1 * std::abs(residual.back().residual_m[s] - residual.front().residual_m[s]);
    bool monotonic = true;
    for (std::size_t k = 1; k < levels; ++k) {
      monotonic = monotonic && residual[k].residual_m[s] >= residual[k - 1].residual_m[s] - slack;
    }
    const double rise = residual.back().residual_m[s] - residual.front().residual_m[s];
    smallest_rise = std::min(smallest_rise, rise);
    if (!monotonic || rise < it.limit) {
      failed +=
          fmt::format("{}{} (residual {:.3g}", failed.empty() ? "" : ", ", s, residual.front().residual_m[s]);
      for (std::size_t k = 1; k < levels; ++k) {
        failed += fmt::format(" -> {:.3g}", residual[k].residual_m[s]);
      }
      failed += ")";
    }
  }
  it.measured = smallest_rise;
  it.verdict = failed.empty() ? Verdict::pass : Verdict::fail;
  it.detail = fmt::format(
                  "residual depth after a {} press and retreat, cells in valve-disjoint groups, all coils "
                  "at 0/50/100 % of {} A; ",
                  si(press_depth_m, "m"), info.max_current_A) +
              (failed.empty() ? "every sensor held more as the current rose (smallest rise shown)"
                              : "no monotonic rise at sensors: " + failed);
  return it;
}

// Drift over the held time against the noise of two 50 ms means (3 sigma) or 1 % of the press per
// second, whichever is larger.
Item leak_item(const PressReleaseResult& leak_run, const SensorStats& rest, const DeviceInfo& info,
               double drift_s, double press_depth_m, double leak_level, const std::string& unit) {
  const std::size_t n = info.sensors;
  // Drift over 0.3 s against the noise of two 50 ms means (3 sigma) or 1 % of the press per
  // second, whichever is larger.
  Item leak{"leak (held drift)", Verdict::pass, 0.0, 0.0, unit + "/s", ""};
  std::string leaking;
  for (std::size_t s = 0; s < n; ++s) {
    const double sigma_mean = std::max(rest.std_dev[s], info.sensor_lsb) / std::sqrt(50.0);
    const double limit = std::max(3.0 * std::sqrt(2.0) * sigma_mean / drift_s, 0.01 * press_depth_m);
    const double drift = (leak_run.residual_m[s] - leak_run.later_m[s]) / drift_s;  // > 0: refilling
    if (drift > leak.measured || s == 0) {
      leak.measured = drift;
      leak.limit = limit;
    }
    if (drift > limit) {
      leaking += fmt::format("{}{}", leaking.empty() ? "" : ", ", s);
    }
  }
  leak.verdict = leaking.empty() ? Verdict::pass : Verdict::fail;
  leak.detail =
      fmt::format("all coils at {} A, from 60 ms after the retreat; ", leak_level * info.max_current_A) +
      (leaking.empty() ? "pads held (largest refill rate shown)"
                       : "pads refilling past energised valves at sensors " + leaking);
  return leak;
}

// Link integrity over the whole test.
Item link_item(const SessionCounters& c) {
  const std::uint64_t errors =
      c.decode_errors + c.sequence_gaps + c.duplicates + c.disconnects + c.telemetry_timeouts + c.faults;
  Item it{"link", errors == 0 ? Verdict::pass : Verdict::fail, static_cast<double>(errors), 0.0, "events",
          ""};
  it.detail = fmt::format(
      "{} decode errors, {} sequence gaps, {} duplicates, {} disconnects, {} telemetry timeouts, {} "
      "faults, over "
      "{} packets received",
      c.decode_errors, c.sequence_gaps, c.duplicates, c.disconnects, c.telemetry_timeouts, c.faults,
      c.received);
  return it;
}

// The items and the heartbeat round trips, as JSON or text.
void print_report(const std::string& uri, bool fixture, bool simulated, bool json,
                  const std::vector<Item>& items, const DurationHistogram& round_trip, bool failed) {
  const double p50_s = round_trip.percentile_ns(0.5) * 1e-9;
  const double p99_s = round_trip.percentile_ns(0.99) * 1e-9;
  const double max_s = static_cast<double>(round_trip.max_ns()) * 1e-9;
  const auto buckets = rtt_buckets(round_trip);
  if (json) {
    std::string out = fmt::format(
        R"({{"uri": "{}", "fixture": {}, "simulated_clock": {}, "result": "{}", "items": [)",
        json_escape(uri), fixture ? "true" : "false", simulated ? "true" : "false", failed ? "FAIL" : "PASS");
    for (std::size_t i = 0; i < items.size(); ++i) {
      const Item& it = items[i];
      out += fmt::format(
          R"({}{{"name": "{}", "result": "{}", "measured": {}, "limit": {}, "unit": "{}", "detail": "{}"}})",
          i == 0 ? "" : ", ", it.name, to_string(it.verdict), json_number(it.measured), json_number(it.limit),
          json_escape(it.unit), json_escape(it.detail));
    }
    out += fmt::format(
        R"(], "round_trip": {{"count": {}, "p50_s": {}, "p99_s": {}, "max_s": {}, "histogram": [)",
        round_trip.count(), json_number(p50_s), json_number(p99_s), json_number(max_s));
    bool first = true;
    for (const auto& [edge_ns, count] : buckets) {
      out += fmt::format(R"({}{{"le_s": {}, "count": {}}})", first ? "" : ", ", json_number(edge_ns * 1e-9),
                         count);
      first = false;
    }
    fmt::print("{}]}}}}\n", out);
  } else {
    fmt::print("selftest of {}{}\n", uri, simulated ? " (simulated clock)" : "");
    for (const Item& it : items) {
      fmt::print("  {} {:<24} {:>12} (limit {}) {}\n", to_string(it.verdict), it.name,
                 fmt::format("{:.4g} {}", it.measured, it.unit), fmt::format("{:.4g}", it.limit), it.detail);
    }
    fmt::print("round trip: {} heartbeats, p50 {:.3f} ms, p99 {:.3f} ms, max {:.3f} ms\n", round_trip.count(),
               p50_s * 1e3, p99_s * 1e3, max_s * 1e3);
    std::uint64_t most = 1;
    for (const auto& b : buckets) {
      most = std::max(most, b.second);
    }
    for (const auto& [edge_ns, count] : buckets) {
      fmt::print("  <= {:8.3f} ms {:>6} {}\n", edge_ns * 1e-6, count,
                 std::string(static_cast<std::size_t>(40 * count / most), '#'));
    }
    fmt::print("result: {}\n", failed ? "FAIL" : "PASS");
  }
}

int run_selftest(const SelftestOptions& o, const GlobalOptions& global) {
  Rig rig(o.uri, o.realtime, o.lease.lease_socket());
  const DeviceInfo& info = rig.info();
  const model::DeviceProfile* profile = rig.session().profile();
  const bool fixture = rig.fixture() != nullptr;
  const std::string unit = info.sensor_unit;
  std::vector<Item> items;
  const int steps = fixture ? 6 : 1;
  Progress progress(!global.json, "selftest", steps);
  int step = 0;

  // Enable: every valve check needs the coils driven.
  Item enable{"enable", Verdict::pass, 0.0, 0.0, "", ""};
  try {
    rig.enable();
    enable.detail = "ENABLED";
  } catch (const Error& e) {
    enable.verdict = Verdict::fail;
    enable.detail = e.what();
  }
  items.push_back(enable);

  // At rest: valves open, nothing pressing.
  CurrentHolder hold(rig);
  hold.set(0.0);
  const SensorStats rest = sample_sensors(rig, o.rest_s, hold);
  progress.step(++step);
  items.push_back(range_item(rest, info, unit));
  items.push_back(noise_item(rest, info, profile, unit));

  // With the fixture: press every cell (valves open); every sensor must follow the press.
  SensorStats pressed;
  if (fixture) {
    const double span_m =
        profile != nullptr ? std::min(o.press_depth_m, 0.4 * profile->cell_depth_m) : o.press_depth_m;
    const std::vector<double> press(info.fluid_cells, span_m);
    rig.fixture()->set_finger_indentation(press);
    rig.run_for(0.1, hold);
    pressed = sample_sensors(rig, 0.05, hold);
    rig.lift_finger();
    rig.run_for(0.4, hold);  // refill through the open valves
    progress.step(++step);
    items.push_back(span_item(pressed, span_m, info, unit));
  }
  items.push_back(stuck_item(rest, fixture ? &pressed : nullptr, info, unit));

  // Valve sweep and leak: the press-release experiment (ctl_device_sampler.hpp) at rising currents.
  const bool displacement = unit == "m" && profile != nullptr;
  if (fixture && displacement && enable.verdict == Verdict::pass) {
    const std::vector<double> levels = {0.0, 0.5, 1.0};
    std::vector<PressReleaseResult> residual;
    PressRelease pr;
    pr.depth_m = o.press_depth_m;
    for (const double level : levels) {
      residual.push_back(press_release(rig, level * info.max_current_A, pr));
      progress.step(++step);
    }
    // Leak: held at half the maximum current, sampled soon after the retreat. At full current a
    // valve that lost most of its field still holds (the current is several times what a press
    // needs: the sweep's 50 and 100 % residuals match); at half it passes fluid back.
    constexpr double kLeakLevel = 0.5;
    PressRelease held = pr;
    held.settle_s = 0.06;
    held.drift_s = 0.3;
    const PressReleaseResult leak_run = press_release(rig, kLeakLevel * info.max_current_A, held);
    progress.step(++step);
    items.push_back(sweep_item(residual, rest, info, o.press_depth_m, unit));

    items.push_back(leak_item(leak_run, rest, info, held.drift_s, o.press_depth_m, kLeakLevel, unit));
  } else {
    const char* why = !displacement ? "needs displacement sensors (the residual depth is what is measured)"
                      : fixture
                          ? "the device did not enable"
                          : "needs a press: only mock:// has a fixture the host can drive (docs/cli.md)";
    items.push_back({"valve sweep", Verdict::skip, 0.0, 0.0, unit, why});
    items.push_back({"leak (held drift)", Verdict::skip, 0.0, 0.0, unit + "/s", why});
  }

  // Link integrity over the whole test.
  const SessionCounters& c = rig.session().counters();
  items.push_back(link_item(c));
  // Latency: heartbeat round trips; p99 must leave the watchdog half its timeout as margin.
  const double p50_s = c.round_trip.percentile_ns(0.5) * 1e-9;
  const double p99_s = c.round_trip.percentile_ns(0.99) * 1e-9;
  const double max_s = static_cast<double>(c.round_trip.max_ns()) * 1e-9;
  {
    Item it{"round-trip latency p99", Verdict::pass, p99_s, 0.5 * info.heartbeat_timeout_s, "s", ""};
    // Classic CAN's heartbeat frame has no echo (docs/protocol.md, "Classic CAN"): nothing to time.
    const std::optional<protocol::BusSpec> bus = rig.session().transport().bus();
    const bool no_echo = bus && bus->kind == protocol::BusKind::can_classic;
    it.verdict = c.round_trip.count() == 0 ? (no_echo ? Verdict::skip : Verdict::fail)
                 : p99_s <= it.limit       ? Verdict::pass
                                           : Verdict::fail;
    it.detail =
        c.round_trip.count() == 0 && no_echo
            ? std::string(
                  "classic CAN carries no heartbeat echo: no round trip to time (the link item "
                  "counts what the link lost)")
            : fmt::format("{} heartbeats, p50 {:.3f} ms, max {:.3f} ms{}", c.round_trip.count(), p50_s * 1e3,
                          max_s * 1e3,
                          rig.simulated() ? "; simulated clock: the mock answers within its 1 ms tick" : "");
    items.push_back(it);
  }
  rig.release();

  const bool failed =
      std::any_of(items.begin(), items.end(), [](const Item& i) { return i.verdict == Verdict::fail; });
  print_report(o.uri, fixture, rig.simulated(), global.json, items, c.round_trip, failed);
  return failed ? tools::kFailure : tools::kOk;
}

}  // namespace

void add_selftest_command(CliCommand app, const GlobalOptions& global, int& exit_code) {
  auto options = std::make_shared<SelftestOptions>();
  CliCommand sub = app.subcommand(
      "selftest",
      "check link, sensor range, noise and stuck sensors, sweep the valves, look for leaks and measure the "
      "heartbeat round trip; each item PASS/FAIL/SKIP with its value and limit (docs/cli.md). Exit 0 no "
      "FAIL, "
      "1 a check failed");
  add_device_options(sub, options->uri, options->realtime);
  sub.option("--rest", options->rest_s, "seconds of rest sampled for range and noise")
      .range(0.05, 10.0)
      .show_default();
  sub.option("--press-depth-m", options->press_depth_m, "fixture press depth, m")
      .range(0.5e-3, 6e-3)
      .show_default();
  add_lease_option(sub, options->lease);
  sub.callback([options, &global, &exit_code] {
    if (const std::optional<std::string> socket = options->lease.lease_socket()) {
      options->uri = "bridge:" + *socket;  // what the report names; the Rig leases the socket
    }
    exit_code = run_selftest(*options, global);
  });
}

}  // namespace mrskin::ctl
