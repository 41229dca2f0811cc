// A console linked against mrskin::bridge and mrskin::sim that registers mock:// at start-up, as
// docs/api.md says: it opens the simulated unit and renders a few ticks of the demo.
#include <cstdio>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/sim/open_mock.hpp"

int main() {
  mrskin::sim::register_mock_scheme();
  mrskin::SimulatedClock clock;
  mrskin::OpenOptions open;
  open.synchronous_mock = true;
  try {
    mrskin::OpenedDevice dev = mrskin::open_device("mock://", clock, open);
    const auto scene = mrskin::bridge::make_scene("demo");
    mrskin::bridge::Bridge loop(*dev.session, *scene);
    for (int k = 0; k < 10; ++k) {
      mrskin::sim::mock_of(dev)->step(clock.now());
      (void)loop.step(clock.now());
      clock.advance(std::chrono::milliseconds(1));
    }
    std::printf("sim console: mock:// opened, %llu ticks\n",
                static_cast<unsigned long long>(loop.stats().ticks));
    return loop.stats().ticks == 10 ? 0 : 1;
  } catch (const std::exception& e) {
    std::printf("sim console: %s\n", e.what());
    return 1;
  }
}
