// mrskin-bridged: runs the bridge in real time on a device, with a scripted scene.
#include <CLI/CLI.hpp>

#include <atomic>
#include <csignal>
#include <cstdio>
#include <fstream>
#include <optional>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/bridge/scene.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/driver/version.hpp"

namespace {

std::atomic<int> g_signal{0};
extern "C" void on_signal(int sig) { g_signal.store(sig); }

class MockTruth final : public mrskin::bridge::ForceTruth {
 public:
  explicit MockTruth(const mrskin::MockDevice& mock) : mock_(mock) {}
  void true_forces(std::span<double> out_N) const noexcept override { mock_.true_contact_forces(out_N); }

 private:
  const mrskin::MockDevice& mock_;
};

// Exit codes: 0 ok, 1 runtime failure, 2 usage, 3 device not found/denied, 4 protocol mismatch.
int run(const std::string& device_uri, const std::string& scene_name, double duration_s, double rate_hz,
        const std::string& stats_path, bool quiet) {
  using namespace mrskin;
  MonotonicClock clock;
  auto scene = bridge::make_scene(scene_name);
  OpenedDevice dev = open_device(device_uri, clock);
  const DeviceInfo& info = dev.session->info();
  std::printf("mrskin-bridged %s: %s serial %08X firmware %s protocol v%d.%d, %d x %d grid, %zu valves, %zu sensors\n",
              std::string(library_version()).c_str(), device_uri.c_str(), info.serial, info.firmware.c_str(),
              info.protocol_major, info.protocol_minor, info.rows, info.cols, info.valves, info.sensors);
  bridge::BridgeOptions options;
  options.rate_hz = rate_hz;
  bridge::Bridge loop(*dev.session, *scene, options);
  std::optional<MockTruth> truth;
  if (dev.mock) {
    truth.emplace(*dev.mock);
    loop.set_force_truth(&*truth);
  }
  const TimePoint t0 = clock.now();
  scene->set_start(t0);
  (void)loop.enable();
  loop.start(clock);

  std::vector<double> finger(dev.mock ? dev.mock->layout().fluid_cell_count() : 0, 0.0);
  const TimePoint end = t0 + from_seconds(duration_s);
  TimePoint next_print = t0 + std::chrono::milliseconds(500);
  TimePoint next = t0;
  while (clock.now() < end && g_signal.load() == 0) {
    const TimePoint now = clock.now();
    if (dev.mock) {  // the simulated finger follows the scene script
      scene->finger(to_seconds(now - t0), dev.mock->layout(), finger);
      dev.mock->set_finger_indentation(finger);
    }
    if (!quiet && now >= next_print) {
      next_print += std::chrono::milliseconds(500);
      const auto targets = loop.targets_N();
      double peak = 0.0;
      for (const double f : targets) {
        peak = std::max(peak, f);
      }
      std::printf("t=%5.2f s  ticks=%-7llu state=%-8s stiffness=%6.1f N/m  peak target=%5.3f N  rms error=%6.4f N\n",
                  to_seconds(now - t0), static_cast<unsigned long long>(loop.live_ticks()),
                  to_string(dev.session->state()), loop.live_stiffness_N_per_m(), peak, loop.live_rms_error_N());
      std::fflush(stdout);
    }
    next += std::chrono::milliseconds(1);
    clock.sleep_until(next);
  }
  loop.stop();
  if (dev.mock) {
    dev.mock->stop();
  }
  const bridge::BridgeStats& s = loop.stats();
  if (g_signal.load() != 0) {
    std::printf("stopped by signal %d\n", g_signal.load());
  }
  std::printf(
      "summary: %llu ticks at %.0f Hz, %llu overruns, %llu skipped periods, tick p50 %.2f us p99 %.2f us "
      "p99.9 %.2f us max %.2f us; rendered-force error rms %.4f N max %.4f N over %llu samples; "
      "clamped %.1f %%\n",
      static_cast<unsigned long long>(s.ticks), rate_hz, static_cast<unsigned long long>(s.overruns),
      static_cast<unsigned long long>(s.skipped_periods), s.tick_time.percentile_ns(0.5) / 1e3,
      s.tick_time.percentile_ns(0.99) / 1e3, s.tick_time.percentile_ns(0.999) / 1e3,
      static_cast<double>(s.tick_time.max_ns()) / 1e3, s.force_rms_error_N(), s.force_max_abs_error_N,
      static_cast<unsigned long long>(s.force_samples), 100.0 * s.clamped_fraction());
  if (!stats_path.empty()) {
    std::ofstream out(stats_path);
    if (!out) {
      std::fprintf(stderr, "error: cannot write statistics to %s: check the directory exists and is writable\n",
                   stats_path.c_str());
      return 1;
    }
    out << bridge::to_json(s, loop.tick_period_s());
    std::printf("statistics written to %s\n", stats_path.c_str());
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"mrskin-bridged: renders a slave robot's palpation forces on the MR skin in real time"};
  app.set_version_flag("--version", std::string(mrskin::library_version()));
  std::string device = "mock://";
  std::string scene = "demo";
  double duration_s = 0.0;
  double rate_hz = 1000.0;
  std::string stats_path;
  bool quiet = false;
  app.add_option("--device", device, "device URI (mock://[?seed=N])")->capture_default_str();
  app.add_option("--scene", scene, "built-in scene driving the slave stream and the simulated finger")
      ->capture_default_str();
  app.add_option("--duration", duration_s, "seconds to run; 0 runs until SIGINT/SIGTERM")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--rate", rate_hz, "loop rate, Hz")->check(CLI::Range(1.0, 20000.0))->capture_default_str();
  app.add_option("--stats-json", stats_path, "write loop statistics as JSON to this file at exit");
  app.add_flag("--quiet", quiet, "no live status lines");
  CLI11_PARSE(app, argc, argv);
  if (duration_s == 0.0) {
    duration_s = 1e9;
  }
  std::signal(SIGINT, on_signal);
  std::signal(SIGTERM, on_signal);
  try {
    return run(device, scene, duration_s, rate_hz, stats_path, quiet);
  } catch (const mrskin::InvalidArgument& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 2;
  } catch (const mrskin::DeviceNotFound& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 3;
  } catch (const mrskin::PermissionDenied& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 3;
  } catch (const mrskin::ProtocolMismatch& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 4;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 1;
  }
}
