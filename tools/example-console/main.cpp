// Example master console: owns its real-time thread and calls Bridge::step(now) from it.
// Setup may throw (typed, with what to do); the loop only sees return codes.
#include <cstdio>
#include <memory>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/eval/truth_scorer.hpp"
#include "mrskin/sim/open_mock.hpp"

int main() {
  using namespace mrskin;
  try {
    sim::register_mock_scheme();  // mock://: the simulated unit, from mrskin::sim
    // Simulated time keeps the example deterministic; a console uses MonotonicClock.
    SimulatedClock clock;
    OpenOptions open;
    open.synchronous_mock = true;
    OpenedDevice dev = open_device("mock://?seed=1", clock, open);
    auto scene = bridge::make_scene("demo");
    bridge::Bridge loop(*dev.session, *scene);
    const std::shared_ptr<sim::MockDevice> mock = sim::mock_of(dev);  // the simulated finger's side
    sim::MockDeviceTruth truth(*mock);
    eval::TruthScorer scorer(truth, mock->layout().fluid_cell_count(), loop.options());
    loop.set_tick_watcher(&scorer);
    loop.set_perf_clock(&clock);
    scene->set_start(clock.now());
    (void)loop.enable();

    std::vector<double> finger(mock->layout().fluid_cell_count());
    int faults = 0;
    for (int k = 0; k < 3500; ++k) {  // the console's 1 kHz loop
      mrskin::eval::press_scene_finger(*scene, to_seconds(clock.now()), mock->layout(), finger);
      mock->set_finger_indentation(finger);
      mock->step(clock.now());
      if (loop.step(clock.now()) != ResultCode::ok) {
        ++faults;  // a console would react: pause, re-enable, alert
      }
      clock.advance(std::chrono::milliseconds(1));
    }
    const auto& s = loop.stats();
    std::printf("example-console: %llu ticks, %d non-ok, rendered-force rms error %.4f N\n",
                static_cast<unsigned long long>(s.ticks), faults, s.force_rms_error_N());
    return s.ticks == 3500 ? 0 : 1;
  } catch (const mrskin::Error& e) {
    std::fprintf(stderr, "example-console: %s\n", e.what());
    return 1;
  }
}
