// The session's tick path and the mock firmware allocate nothing after start-up: polling,
// commands, state requests (enable re-seeding included), faults and their frozen ring log.
#include <gtest/gtest.h>

#include <algorithm>
#include <vector>

#include "counting_new.hpp"
#include "mrskin/protocol/units.hpp"
#include "rig.hpp"

namespace mrskin {
namespace {

TEST(DriverAllocation, SessionAndMockTicksAllocateNothing) {
  test::Rig rig("mock://?seed=40&faults=drop:0.01,dup:0.01,corrupt:0.01,reorder:0.01");
  DeviceSession& session = *rig.dev.session;
  int calls = 0;
  session.set_telemetry_callback(
      [](void* ctx, const TelemetryView& /*view*/) noexcept { ++*static_cast<int*>(ctx); }, &calls);
  const auto target = protocol::quantize_cell_target({800.0, 1e-4, 1.5, 0.3});
  ASSERT_EQ(target.error, protocol::Error::ok);
  const std::vector<protocol::CellTarget> targets(rig.finger.size(), target.counts);
  std::fill(rig.currents.begin(), rig.currents.end(), 0.04);
  ASSERT_EQ(session.request_enable(), ResultCode::ok);
  rig.finger[6] = 2e-3;
  rig.run(300);  // start-up: the first fault freezes the ring log into its preallocated copy
  (void)session.request_estop();
  rig.run(20);
  (void)session.request_enable();
  rig.run(20);

  const std::uint64_t before = test::allocation_count();
  for (int cycle = 0; cycle < 4; ++cycle) {
    (void)session.send_cell_targets(0, targets);
    rig.run(100);
    (void)session.request_pause();
    rig.run(20);
    (void)session.request_enable();  // re-seeds and sends
    rig.run(50);
    (void)session.request_estop();  // FAULT: the ring log is frozen again
    rig.run(20);
    (void)session.request_enable();
    rig.run(50);
    rig.run(150, /*host_alive=*/false);  // watchdog: heartbeat lost
    (void)session.request_enable();
    rig.run(20);
  }
  const std::uint64_t allocations = test::allocation_count() - before;
  EXPECT_EQ(allocations, 0U);
  EXPECT_GE(session.counters().faults, 5U);  // a lossy link may hide a FAULT status between two enables
  EXPECT_GT(calls, 1000);
}

}  // namespace
}  // namespace mrskin
