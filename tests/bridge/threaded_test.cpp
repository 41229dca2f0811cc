// The real-time arrangement: the mock device on its own thread, the bridge's own loop on
// another, the finger driven from a third. Asserts behaviour only (timing is benchmarked
// elsewhere); its main job is to run the cross-thread paths under TSan.
#include <gtest/gtest.h>

#include <cmath>
#include <thread>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/eval/truth_scorer.hpp"
#include "mrskin/sim/open_mock.hpp"

namespace mrskin::bridge {
namespace {

TEST(Threaded, LibraryLoopAndMockThreadRunTogether) {
  MonotonicClock clock;
  OpenedDevice dev = open_device("mock://?seed=9", clock);  // mock starts its own thread
  auto scene = make_scene("demo");
  BridgeOptions options;
  options.realtime = false;  // as root the default would put the test process on SCHED_FIFO
  Bridge loop(*dev.session, *scene, options);
  scene->set_start(clock.now());
  ASSERT_EQ(loop.enable(), ResultCode::ok);
  EXPECT_EQ(loop.start(clock), "");
  EXPECT_TRUE(loop.running());
  std::vector<double> finger(sim::mock_of(dev)->layout().fluid_cell_count());
  const TimePoint end = clock.now() + std::chrono::milliseconds(300);
  while (clock.now() < end) {
    mrskin::eval::press_scene_finger(*scene, to_seconds(clock.now() - scene->start()),
                                     sim::mock_of(dev)->layout(), finger);
    sim::mock_of(dev)->set_finger_indentation(finger);
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
    (void)loop.live_ticks();
    (void)loop.live_rms_error_N();
  }
  loop.stop();
  EXPECT_FALSE(loop.running());
  sim::mock_of(dev)->stop();
  EXPECT_GT(loop.stats().ticks, 0U);
  EXPECT_GT(dev.session->counters().telemetry, 0U);
  EXPECT_EQ(dev.session->counters().decode_errors, 0U);
  EXPECT_TRUE(std::isfinite(loop.stats().force_rms_error_N()));
}

}  // namespace
}  // namespace mrskin::bridge
