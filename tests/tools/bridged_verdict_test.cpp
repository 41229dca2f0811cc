// The run's verdict (tools/mrskin-bridged/verdict.hpp): each product figure met or not, a plain
// explanation for each one beyond its limit, a machine too busy told apart from a slow tick.
#include <gtest/gtest.h>

#include <string>
#include <vector>

#include "verdict.hpp"

namespace {

using mrskin::bridge::BridgeStats;
using mrskin::bridged::verdict_lines;

// A run that meets every figure: 0.01 N RMS over 100 samples, 2 % relative error, no overrun,
// 50 % bus load.
BridgeStats good_run() {
  BridgeStats s;
  s.ticks = 1000;
  s.force_samples = 100;
  s.force_sq_error_sum_N2 = 100 * 0.01 * 0.01;
  s.true_state_sq_error_sum_N2 = 100 * 0.012 * 0.012;
  for (int i = 0; i < 100; ++i) {
    s.relative_error.add(0.02);
  }
  s.target_cell_ticks = 100;
  s.bus_load = 0.5;  // reports a frame (unmodelled)
  return s;
}

bool contains(const std::vector<std::string>& lines, const std::string& what) {
  for (const std::string& l : lines) {
    if (l.find(what) != std::string::npos) {
      return true;
    }
  }
  return false;
}

TEST(BridgedVerdict, AGoodRunIsOkOnItsLastLine) {
  const std::vector<std::string> v = verdict_lines(good_run(), true, 1e-3);
  ASSERT_EQ(v.size(), 1U);
  EXPECT_EQ(v.back().rfind("verdict: OK: rendering met: 0.0100 N RMS", 0), 0U) << v.back();
  EXPECT_TRUE(contains(v, "against the true state 0.0120 N"));
}

TEST(BridgedVerdict, ARenderingErrorBeyondTheLimitIsNotMetAndExplained) {
  BridgeStats s = good_run();
  s.force_sq_error_sum_N2 = 100 * 0.05 * 0.05;
  const std::vector<std::string> v = verdict_lines(s, true, 1e-3);
  EXPECT_EQ(v.back().rfind("verdict: NOT MET: rendering NOT MET: 0.0500 N RMS", 0), 0U) << v.back();
  EXPECT_TRUE(contains(v, "why: rendering"));
}

TEST(BridgedVerdict, ClampingIsNotedWithoutFailing) {
  BridgeStats s = good_run();
  s.clamped_cell_ticks = 25;
  const std::vector<std::string> v = verdict_lines(s, true, 1e-3);
  EXPECT_TRUE(contains(v, "note: clamped 25.0 %"));
  EXPECT_EQ(v.back().rfind("verdict: OK", 0), 0U) << v.back();
}

// The clamped figure is the product's; the unclamped one stands beside it, and the note gives the
// clamps' causes and the force the surgeon missed.
TEST(BridgedVerdict, TheUnclampedFigureAndTheClampsCausesStandBesideTheProductsFigure) {
  BridgeStats s = good_run();
  s.unclamped.sq_error_sum_N2 = 100 * 0.066 * 0.066;
  for (int i = 0; i < 100; ++i) {
    s.unclamped.relative_error.add(i < 90 ? 0.05 : 0.2);
  }
  s.clamped_cell_ticks = 30;
  s.clamp_causes.floor_p0 = 17;
  s.clamp_causes.floor_viscous = 12;
  s.clamp_causes.ceiling = 1;
  s.clamp_causes.floor_excess_sum_N = 2.9;
  s.clamp_causes.ceiling_missed_sum_N = 0.1;
  const std::vector<std::string> v = verdict_lines(s, true, 1e-3);
  EXPECT_EQ(v.back().rfind("verdict: OK: rendering met: 0.0100 N RMS", 0), 0U) << v.back();
  EXPECT_TRUE(contains(v, "against the unclamped tissue law 0.0660 N RMS, p95 20.1 % (beyond the limits"))
      << v.back();
  EXPECT_TRUE(contains(v,
                       "note: clamped 30.0 % of the loaded cell-ticks (floor: p0 17.0 %, viscous 12.0 %, "
                       "membrane 0.0 %; ceiling 1.0 %)"));
  EXPECT_TRUE(contains(v, "on average 0.100 N away from the tissue"));

  s.unclamped.sq_error_sum_N2 = 100 * 0.01 * 0.01;
  s.unclamped.relative_error = {};
  for (int i = 0; i < 100; ++i) {
    s.unclamped.relative_error.add(2.0);  // beyond the histogram's last bin
  }
  EXPECT_TRUE(contains(verdict_lines(s, true, 1e-3), "p95 above 100 % (beyond the limits"));
}

TEST(BridgedVerdict, ABusyMachineIsToldApartFromASlowTick) {
  BridgeStats busy = good_run();
  busy.skipped_periods = 7;
  busy.tick_time.add(30000);  // ns
  const std::vector<std::string> b = verdict_lines(busy, true, 1e-3);
  EXPECT_TRUE(contains(b, "machine was too busy")) << b.front();
  EXPECT_TRUE(contains(b, "not a rendering failure"));

  BridgeStats slow = good_run();
  slow.overruns = 500;
  for (int i = 0; i < 100; ++i) {
    slow.tick_time.add(1500000);  // ns
  }
  const std::vector<std::string> t = verdict_lines(slow, true, 1e-3);
  EXPECT_TRUE(contains(t, "the tick itself took longer than its period")) << t.front();
  EXPECT_EQ(t.back().rfind("verdict: NOT MET", 0), 0U);
}

// Unmodelled, the bus figure is the reports counted per 1 ms frame: a full-speed frame carries one.
TEST(BridgedVerdict, ACountedBusOverloadNamesTheProtocolAndTheModel) {
  BridgeStats s = good_run();
  s.bus_load = 1.06;
  const std::vector<std::string> v = verdict_lines(s, true, 1e-3);
  EXPECT_TRUE(contains(v, "bus NOT MET: 1.06 reports a frame (limit 1)")) << v.back();
  EXPECT_TRUE(contains(v, "mock://?bus=hid-fs"));
  s.bus_load = 1.0;  // protocol 1.2: one report a frame each way
  EXPECT_TRUE(contains(verdict_lines(s, true, 1e-3), "bus met: 1.00 reports a frame"));
}

TEST(BridgedVerdict, AModelledBusIsHeldTo80PercentOfItsCapacity) {
  BridgeStats s = good_run();
  s.bus.kind = "hid-fs";
  s.bus.device_to_host.load = s.bus_load = 0.853;
  std::vector<std::string> v = verdict_lines(s, true, 1e-3);
  EXPECT_TRUE(contains(v, "bus NOT MET: 85.3 % (limit 80 %)")) << v.back();
  EXPECT_TRUE(contains(v, "of the hid-fs bus"));
  s.bus.device_to_host.load = s.bus_load = 0.586;
  EXPECT_TRUE(contains(verdict_lines(s, true, 1e-3), "bus met: 58.6 %"));
  // CAN: one bus both directions share, held to their sum; classic CAN to half of it.
  s.bus.kind = "can";
  s.bus.host_to_device.load = 0.184;
  s.bus.device_to_host.load = s.bus_load = 0.537;
  v = verdict_lines(s, true, 1e-3);
  EXPECT_TRUE(contains(v, "bus NOT MET: 72.1 % of the shared can bus, both directions (limit 50 %)"))
      << v.back();
  EXPECT_TRUE(contains(v, "sensor deadband"));
  s.bus.device_to_host.load = s.bus_load = 0.223;
  v = verdict_lines(s, true, 1e-3);
  EXPECT_TRUE(contains(v, "bus met: 40.7 % of the shared can bus, both directions")) << v.back();
  s.bus.kind = "canfd";
  s.bus.device_to_host.load = s.bus_load = 0.7;
  EXPECT_TRUE(contains(verdict_lines(s, true, 1e-3),
                       "bus NOT MET: 88.4 % of the shared canfd bus, both "
                       "directions (limit 80 %)"));
}

TEST(BridgedVerdict, WithoutTheTruthTheRenderingIsNotScored) {
  const std::vector<std::string> v = verdict_lines(good_run(), false, 1e-3);
  EXPECT_TRUE(contains(v, "rendering not scored (no true force on this device)"));
}

}  // namespace

// A unit of another design point is held to the figure at its own scale (fingertip-16x16: forces
// times 0.01): 4 mN RMS is within 0.04 N but not within 0.4 mN.
TEST(BridgedVerdict, ASmallerDesignIsHeldToItsOwnScale) {
  BridgeStats s = good_run();
  s.force_sq_error_sum_N2 = 100 * 0.004 * 0.004;
  EXPECT_TRUE(contains(verdict_lines(s, true, 1e-3), "rendering met: 0.0040 N RMS (limit 0.04 N)"));
  mrskin::bridged::VerdictLimits scaled;
  scaled.rms_error_N *= 0.01;
  const std::vector<std::string> lines = verdict_lines(s, true, 1e-3, scaled);
  EXPECT_TRUE(contains(lines, "rendering NOT MET: 0.0040 N RMS (limit 0.0004 N)")) << lines.back();
  EXPECT_TRUE(contains(lines, "beyond the product's 0.0004 N and 7 %"));
}
