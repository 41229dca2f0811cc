// mrskin-bridged: runs the bridge in real time on a device, with a scripted scene.
#include <fmt/format.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <atomic>
#include <csignal>
#include <cstdio>
#include <fstream>
#include <optional>
#include <vector>

#include "exit_codes.hpp"
#include "mrskin/bridge/bridge.hpp"
#include "mrskin/bridge/scene.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/driver/version.hpp"

namespace {

// Set by the signal handler, read by the main loop: a handler can only reach a global.
std::atomic<int> g_signal{0};  // NOLINT(cppcoreguidelines-avoid-non-const-global-variables)
extern "C" void on_signal(int sig) { g_signal.store(sig); }

using namespace mrskin::tools;  // exit codes

struct Settings {
  std::string device = "mock://";
  std::string scene = "demo";
  double duration_s = 0.0;
  double rate_hz = 1000.0;
  std::string stats_path;
  bool quiet = false;
};

void print_summary(const mrskin::bridge::BridgeStats& s, double rate_hz) {
  fmt::print(
      "summary: {} ticks at {:.0f} Hz, {} overruns, {} skipped periods, tick p50 {:.2f} us p99 {:.2f} us "
      "p99.9 {:.2f} us max {:.2f} us; rendered-force error rms {:.4f} N max {:.4f} N over {} samples; "
      "clamped {:.1f} %\n",
      s.ticks, rate_hz, s.overruns, s.skipped_periods, s.tick_time.percentile_ns(0.5) / 1e3,
      s.tick_time.percentile_ns(0.99) / 1e3, s.tick_time.percentile_ns(0.999) / 1e3,
      static_cast<double>(s.tick_time.max_ns()) / 1e3, s.force_rms_error_N(), s.force_max_abs_error_N,
      s.force_samples, 100.0 * s.clamped_fraction());
}

int run(const Settings& cfg) {
  using namespace mrskin;
  MonotonicClock clock;
  bridge::BridgeOptions options;
  options.rate_hz = cfg.rate_hz;
  auto scene = bridge::make_scene(cfg.scene, options.mapping);
  OpenedDevice dev = open_device(cfg.device, clock);
  const DeviceInfo& info = dev.session->info();
  fmt::print(
      "mrskin-bridged {}: {} serial {:08X} firmware {} protocol v{}.{}, {} x {} grid, {} valves, {} "
      "sensors\n",
      library_version(), cfg.device, info.serial, info.firmware, info.protocol_major, info.protocol_minor,
      info.rows, info.cols, info.valves, info.sensors);
  bridge::Bridge loop(*dev.session, *scene, options);
  std::optional<mrskin::bridge::MockDeviceTruth> truth;
  if (dev.mock) {
    truth.emplace(*dev.mock);
    loop.set_force_truth(&*truth);
  }
  const TimePoint t0 = clock.now();
  scene->set_start(t0);
  (void)loop.enable();
  if (const std::string warning = loop.start(clock); !warning.empty()) {
    fmt::print(stderr, "warning: {}\n", warning);
  }

  std::vector<double> finger(dev.mock ? dev.mock->layout().fluid_cell_count() : 0, 0.0);
  const TimePoint end = t0 + from_seconds(cfg.duration_s);
  TimePoint next_print = t0 + std::chrono::milliseconds(500);
  TimePoint next = t0;
  while (clock.now() < end && g_signal.load() == 0) {
    const TimePoint now = clock.now();
    if (dev.mock) {  // the simulated finger follows the scene script
      scene->finger(to_seconds(now - t0), dev.mock->layout(), finger);
      dev.mock->set_finger_indentation(finger);
    }
    if (!cfg.quiet && now >= next_print) {
      next_print += std::chrono::milliseconds(500);
      double peak_N = 0.0;
      for (const double f : loop.targets_N()) {
        peak_N = std::max(peak_N, f);
      }
      fmt::print(
          "t={:5.2f} s  ticks={:<7} state={:<8} stiffness={:6.1f} N/m  peak target={:5.3f} N  rms "
          "error={:6.4f} N\n",
          to_seconds(now - t0), loop.live_ticks(), to_string(dev.session->state()),
          loop.live_stiffness_N_per_m(), peak_N, loop.live_rms_error_N());
      std::fflush(stdout);
    }
    next += std::chrono::milliseconds(1);
    clock.sleep_until(next);
  }
  loop.stop();
  if (dev.mock) {
    dev.mock->stop();
  }
  if (g_signal.load() != 0) {
    fmt::print("stopped by signal {}\n", g_signal.load());
  }
  // Bus load, busier direction: one packet per 64-byte report, one report per 1 ms frame on
  // full-speed USB-HID (the mock speaks the HID framing; docs/protocol.md, "Bus load").
  bridge::BridgeStats stats = loop.stats();
  const double run_s = std::max(1e-9, to_seconds(clock.now() - t0));
  const SessionCounters& link = dev.session->counters();
  stats.bus_load = static_cast<double>(std::max(link.sent, link.received)) / run_s / 1000.0;
  print_summary(stats, cfg.rate_hz);
  fmt::print(
      "bus load   {:.1f} % of full-speed USB-HID reports (host to device {:.1f} %, device to host {:.1f} "
      "%)\n",
      100.0 * stats.bus_load, 100.0 * static_cast<double>(link.sent) / run_s / 1000.0,
      100.0 * static_cast<double>(link.received) / run_s / 1000.0);
  if (const bridge::LoopStats* ls = loop.loop_stats(); ls != nullptr) {
    fmt::print(
        "scheduler  {} priority {}, memory {}; wake latency p50 {:.1f} us, p99 {:.1f} us, p99.9 {:.1f} us\n",
        ls->scheduler.policy_name(), ls->scheduler.priority,
        ls->scheduler.memory_locked ? "locked" : "not locked", ls->wake_latency.percentile_ns(0.5) / 1e3,
        ls->wake_latency.percentile_ns(0.99) / 1e3, ls->wake_latency.percentile_ns(0.999) / 1e3);
  }
  if (!cfg.stats_path.empty()) {
    std::ofstream out(cfg.stats_path);
    if (!out) {
      fmt::print(stderr, "error: cannot write statistics to {}: check the directory exists and is writable\n",
                 cfg.stats_path);
      return kFailure;
    }
    out << bridge::to_json(stats, loop.tick_period_s());
    fmt::print("statistics written to {}\n", cfg.stats_path);
  }
  return kOk;
}

int guarded_main(int argc, char** argv) {
  CLI::App app{"mrskin-bridged: renders a slave robot's palpation forces on the MR skin in real time"};
  app.set_version_flag("--version", std::string(mrskin::library_version()));
  Settings cfg;
  app.add_option("--device", cfg.device, "device URI (mock://[?seed=N])")->capture_default_str();
  std::string scenes;
  for (const std::string_view name : mrskin::bridge::scene_names()) {
    scenes += (scenes.empty() ? "" : ", ") + std::string(name);
  }
  app.add_option("--scene", cfg.scene,
                 "built-in scene driving the slave stream and the simulated finger: " + scenes)
      ->capture_default_str();
  app.add_option("--duration", cfg.duration_s, "seconds to run; 0 runs until SIGINT/SIGTERM")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--rate", cfg.rate_hz, "loop rate, Hz")
      ->check(CLI::Range(1.0, 20000.0))
      ->capture_default_str();
  app.add_option("--stats-json", cfg.stats_path, "write loop statistics as JSON to this file at exit");
  app.add_flag("--quiet", cfg.quiet, "no live status lines");
  CLI11_PARSE(app, argc, argv);
  if (cfg.duration_s == 0.0) {
    cfg.duration_s = 1e9;
  }
  (void)std::signal(SIGINT, on_signal);
  (void)std::signal(SIGTERM, on_signal);
  return run(cfg);
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return guarded_main(argc, argv);
  } catch (...) {
    return mrskin::tools::exit_code_for_current_exception();
  }
}
