// The 5 x 5 tick's instruction count per tick over the demo on the perturbed mock (seed 7, its
// network plant and sensor noise), the reference issue 19's refactoring must not exceed. Run
// under
//   valgrind --tool=callgrind --instr-atstart=no --collect-atstart=no --dump-instr=no
// (demo_callgrind_max.sh): collection is on around Bridge::step only and the counts are dumped
// after every tick, one file per tick, so the script can take the maximum and percentiles.
//   demo_callgrind_probe [TICKS]   (default 3000: idle, the first press, its hold and release)
#include <valgrind/callgrind.h>

#include <cstdio>
#include <cstdlib>
#include <memory>
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
    std::fputs("usage: demo_callgrind_probe [TICKS > 0]\n", stderr);
    return 2;
  }
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  OpenedDevice dev = open_device("mock://?seed=7", clock, open);
  auto scene = bridge::make_scene("demo");
  bridge::Bridge loop(*dev.session, *scene);
  loop.set_perf_clock(&clock);
  scene->set_start(clock.now());
  if (loop.enable() != ResultCode::ok) {
    std::fputs("enable failed\n", stderr);
    return 1;
  }
  const std::shared_ptr<sim::MockDevice> mock = sim::mock_of(dev);
  std::vector<double> finger(mock->layout().fluid_cell_count());
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
    clock.advance(std::chrono::milliseconds(1));
  }
  CALLGRIND_STOP_INSTRUMENTATION;
  const bridge::BridgeStats& s = loop.stats();
  std::printf("ticks %d force_samples %llu observer_errors %llu\n", ticks,
              static_cast<unsigned long long>(s.force_samples),
              static_cast<unsigned long long>(s.observer_errors));
  return 0;
}
