// Counts heap allocations: after start-up, a tick of the whole slice allocates nothing.
#include <gtest/gtest.h>

#include <atomic>
#include <cstdlib>
#include <new>
#include <vector>

#include "counting_new.hpp"
#include "mrskin/bridge/bridge.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/eval/truth_scorer.hpp"
#include "mrskin/sim/open_mock.hpp"

namespace mrskin::bridge {
namespace {

TEST(Allocation, NoHeapAllocationPerTickAfterStartUp) {
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  OpenedDevice dev = open_device("mock://?seed=5", clock, open);
  auto scene = make_scene("demo");
  Bridge loop(*dev.session, *scene);
  loop.set_perf_clock(&clock);
  scene->set_start(clock.now());
  ASSERT_EQ(loop.enable(), ResultCode::ok);
  std::vector<double> finger(sim::mock_of(dev)->layout().fluid_cell_count());
  auto tick = [&] {
    mrskin::eval::press_scene_finger(*scene, to_seconds(clock.now() - scene->start()),
                                     sim::mock_of(dev)->layout(), finger);
    sim::mock_of(dev)->set_finger_indentation(finger);
    sim::mock_of(dev)->step(clock.now());
    (void)loop.step(clock.now());
    clock.advance(std::chrono::milliseconds(1));
  };
  for (int k = 0; k < 100; ++k) {  // start-up
    tick();
  }
  const std::uint64_t before = mrskin::test::allocation_count();
  for (int k = 0; k < 5000; ++k) {  // press, hold and release: every code path of the tick
    tick();
  }
  EXPECT_EQ(mrskin::test::allocation_count() - before, 0U);
  EXPECT_EQ(loop.stats().ticks, 5100U);
}

}  // namespace
}  // namespace mrskin::bridge
