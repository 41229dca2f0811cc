// The 5 x 5 tick's instruction count per tick over the demo on the perturbed mock (seed 7, its
// network plant and sensor noise), the reference issue 19's refactoring must not exceed. Run
// under
//   valgrind --tool=callgrind --instr-atstart=no --collect-atstart=no --dump-instr=no
// (demo_callgrind_max.sh): collection is on around Bridge::step only and the counts are dumped
// after every tick, one file per tick, so the script can take the maximum and percentiles.
//   demo_callgrind_probe [TICKS [URI [FINGER]]]   (default 3000: idle, the first press, its hold
//                                         and release; URI default mock://?seed=7; FINGER
//                                         "scene", the demo's finger, or "all": every fluid
//                                         cell pressed to 2 mm after 1 s untouched, held,
//                                         then released, or "rest": no finger on the skin and
//                                         the slave out of contact, streaming at every tick)
// With MRSKIN_PROBE_PHASES=FILE it writes each tick's phase, from the finger's true depths,
// one line a tick in order (issue 21's gates are a maximum per phase): idle (no cell touched
// for 1 s or since the start), refill (none touched now, one within 1 s), load1 / hold1 /
// release1 (one cell deeper than 50 um, its finger deeper, still or shallower than the last
// tick by more than 0.1 um), load_all / hold_all / release_all (every fluid cell deeper than
// 50 um), other. MRSKIN_PROBE_INVERSE=1 prints the inverse's report every 25 ticks (loaded
// cells, components, Gauss-Newton steps, converged, residuals in N).
// It also prints the observer's rate error (its velocity less the finger's, RMS, mm/s) on the
// cells the finger is off (idle: the rate noise a settled test sees) and on those it presses
// deeper than 0.1 mm; run without valgrind for those alone.
#include <valgrind/callgrind.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/eval/truth_scorer.hpp"
#include "mrskin/sim/open_mock.hpp"

namespace {

// The slave hovering out of contact: a sample at every tick with no force and no depth (what a
// robot streams between palpations), so nothing on either side is touched.
class HoveringSlave final : public mrskin::bridge::SlaveSource {
 public:
  bool latest(mrskin::TimePoint now, mrskin::bridge::SlaveSample& out) noexcept override {
    out = mrskin::bridge::SlaveSample{};
    out.stamp = now;
    out.valid = true;
    return true;
  }
};

}  // namespace

int main(int argc, char** argv) {
  using namespace mrskin;
  const int ticks = argc > 1 ? std::atoi(argv[1]) : 3000;
  if (ticks <= 0) {
    std::fputs("usage: demo_callgrind_probe [TICKS > 0 [URI]]\n", stderr);
    return 2;
  }
  const std::string uri = argc > 2 ? argv[2] : "mock://?seed=7";
  const std::string finger_mode = argc > 3 ? argv[3] : "scene";
  if (finger_mode != "scene" && finger_mode != "all" && finger_mode != "rest") {
    std::fputs("FINGER must be scene, all or rest\n", stderr);
    return 2;
  }
  std::FILE* phases = nullptr;
  if (const char* path = std::getenv("MRSKIN_PROBE_PHASES")) {
    phases = std::fopen(path, "w");
    if (phases == nullptr) {
      std::perror(path);
      return 2;
    }
  }
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  OpenedDevice dev = open_device(uri, clock, open);
  auto scene = bridge::make_scene("demo");
  bridge::BridgeOptions options;
  options.sensor_faults.enabled = std::getenv("MRSKIN_PROBE_NO_SENSOR_FAULTS") == nullptr;
  // MRSKIN_PROBE_SMALL_GRID_SWEEPS: the observer's small_grid_sweeps (a tuning's cost, measured).
  if (const char* sweeps = std::getenv("MRSKIN_PROBE_SMALL_GRID_SWEEPS")) {
    options.observer.small_grid_sweeps = static_cast<int>(std::strtol(sweeps, nullptr, 10));
  }
  // MRSKIN_PROBE_NETWORK_STEP_S: the observer's network_step_s (a tuning's cost, measured).
  if (const char* step = std::getenv("MRSKIN_PROBE_NETWORK_STEP_S")) {
    options.observer.network_step_s = std::strtod(step, nullptr);
  }
  HoveringSlave hovering;
  bridge::SlaveSource& source = finger_mode == "rest" ? static_cast<bridge::SlaveSource&>(hovering) : *scene;
  bridge::Bridge loop(*dev.session, source, options);
  loop.set_perf_clock(&clock);
  scene->set_start(clock.now());
  if (loop.enable() != ResultCode::ok) {
    std::fputs("enable failed\n", stderr);
    return 1;
  }
  const std::shared_ptr<sim::MockDevice> mock = sim::mock_of(dev);
  std::vector<double> finger(mock->layout().fluid_cell_count());
  std::vector<double> last_finger(finger.size(), 0.0);
  double idle_sq = 0.0;
  double contact_sq = 0.0;
  long idle_n = 0;
  long contact_n = 0;
  int ticks_untouched = 0;
  const bool print_inverse = std::getenv("MRSKIN_PROBE_INVERSE") != nullptr;
  CALLGRIND_START_INSTRUMENTATION;
  for (int k = 0; k < ticks; ++k) {
    const double t_s = to_seconds(clock.now() - scene->start());
    if (finger_mode == "rest") {
      std::fill(finger.begin(), finger.end(), 0.0);
    } else if (finger_mode == "all") {
      // 1 s untouched, 0.6 s down to 2 mm, 0.6 s held, 0.6 s up, then untouched.
      const double depth_m = 2e-3 * std::clamp(std::min((t_s - 1.0) / 0.6, (2.8 - t_s) / 0.6), 0.0, 1.0);
      std::fill(finger.begin(), finger.end(), depth_m);
    } else {
      mrskin::eval::press_scene_finger(*scene, t_s, mock->layout(), finger);
    }
    mock->set_finger_indentation(finger);
    if (phases != nullptr) {
      std::size_t pressed = 0;
      std::size_t touched = 0;
      double motion_m = 0.0;
      for (std::size_t i = 0; i < finger.size(); ++i) {
        touched += finger[i] > 0.0 ? 1U : 0U;
        if (finger[i] > 50e-6) {
          ++pressed;
          motion_m = finger[i] - last_finger[i];
        }
      }
      ticks_untouched = touched == 0 ? ticks_untouched + 1 : 0;
      const bool loading = motion_m > 1e-7;
      const bool releasing = motion_m < -1e-7;
      const char* phase = "other";
      if (touched == 0) {
        phase = ticks_untouched > k || ticks_untouched > 1000 ? "idle" : "refill";
      } else if (pressed == finger.size()) {
        phase = loading ? "load_all" : (releasing ? "release_all" : "hold_all");
      } else if (pressed == 1 && touched == 1) {
        phase = loading ? "load1" : (releasing ? "release1" : "hold1");
      }
      std::fprintf(phases, "%s\n", phase);
    }
    mock->step(clock.now());
    CALLGRIND_TOGGLE_COLLECT;
    (void)loop.step(clock.now());
    CALLGRIND_TOGGLE_COLLECT;
    CALLGRIND_DUMP_STATS;
    if (print_inverse && k % 25 == 0) {
      const model::InverseReport& r = loop.inverse().report();
      std::printf("tick %d loaded %zu comps %zu it %d conv %d cache %d dirty %zu resid %.4f max %.4f\n", k,
                  r.loaded_cells, r.components_solved, r.iterations, r.converged ? 1 : 0,
                  r.from_cache ? 1 : 0, r.dirty_cells, r.residual_norm_N, r.max_residual_N);
    }
    const std::span<const double> velocity = loop.observer().velocity_m_per_s();
    for (std::size_t i = 0; i < finger.size() && i < velocity.size(); ++i) {
      const double e = velocity[i] - (finger[i] - last_finger[i]) / 1e-3;
      if (finger[i] <= 0.0 && last_finger[i] <= 0.0) {
        idle_sq += e * e;
        ++idle_n;
      } else if (finger[i] > 1e-4) {
        contact_sq += e * e;
        ++contact_n;
      }
    }
    last_finger = finger;
    clock.advance(std::chrono::milliseconds(1));
  }
  CALLGRIND_STOP_INSTRUMENTATION;
  if (phases != nullptr) {
    std::fclose(phases);
  }
  const bridge::BridgeStats& s = loop.stats();
  std::printf("ticks %d observer_errors %llu sensor_faults %llu halts %llu\n", ticks,
              static_cast<unsigned long long>(s.observer_errors),
              static_cast<unsigned long long>(s.sensor_faults),
              static_cast<unsigned long long>(s.sensor_fault_halts));
  std::printf("rate_rms_idle_mm_per_s %.3f rate_rms_contact_mm_per_s %.3f\n",
              1e3 * std::sqrt(idle_sq / static_cast<double>(std::max(idle_n, 1L))),
              1e3 * std::sqrt(contact_sq / static_cast<double>(std::max(contact_n, 1L))));
  return 0;
}
