// The 5 x 5 tick's instruction count per tick over the demo on the perturbed mock (seed 7, its
// network plant and sensor noise), the reference issue 19's refactoring must not exceed. Run
// under
//   valgrind --tool=callgrind --instr-atstart=no --collect-atstart=no --dump-instr=no
// (demo_callgrind_max.sh): collection is on around Bridge::step only and the counts are dumped
// after every tick, one file per tick, so the script can take the maximum and percentiles.
//   demo_callgrind_probe [TICKS [URI]]   (default 3000: idle, the first press, its hold and
//                                         release; URI default mock://?seed=7)
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

int main(int argc, char** argv) {
  using namespace mrskin;
  const int ticks = argc > 1 ? std::atoi(argv[1]) : 3000;
  if (ticks <= 0) {
    std::fputs("usage: demo_callgrind_probe [TICKS > 0 [URI]]\n", stderr);
    return 2;
  }
  const std::string uri = argc > 2 ? argv[2] : "mock://?seed=7";
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  OpenedDevice dev = open_device(uri, clock, open);
  auto scene = bridge::make_scene("demo");
  bridge::BridgeOptions options;
  options.sensor_faults.enabled = std::getenv("MRSKIN_PROBE_NO_SENSOR_FAULTS") == nullptr;
  bridge::Bridge loop(*dev.session, *scene, options);
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
  CALLGRIND_START_INSTRUMENTATION;
  for (int k = 0; k < ticks; ++k) {
    mrskin::eval::press_scene_finger(*scene, to_seconds(clock.now() - scene->start()), mock->layout(),
                                     finger);
    mock->set_finger_indentation(finger);
    mock->step(clock.now());
    CALLGRIND_TOGGLE_COLLECT;
    (void)loop.step(clock.now());
    CALLGRIND_TOGGLE_COLLECT;
    CALLGRIND_DUMP_STATS;
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
