// Bridge I on every built-in scene, on the simulated clock, against the perturbed plant of the
// mock device (seed 7), scored by the finger's true motion against the tissue law clamped into
// the envelope. Every scene but step holds the product's figures (docs/requirements.md); step holds a
// regression bound at its measured value (docs/bridge.md has the table and what limits it).
// Then the same under a network of 50 ms +- 20 ms delay and 5 % loss.
#include <gtest/gtest.h>

#include <cstdio>
#include <cstdlib>
#include <limits>
#include <string>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/bridge/impairment.hpp"
#include "mrskin/driver/device.hpp"
#include "scene_rig.hpp"

namespace mrskin::bridge {
namespace {

using LoopRun = test::SceneRun;

LoopRun simulate(const std::string& scene_name, double seconds, const ImpairmentOptions* network) {
  // MRSKIN_CLOSED_LOOP_SEED picks another perturbed unit (docs/bridge.md: the spread over seeds);
  // the bounds below are for seed 7.
  // MRSKIN_RATE_FILTER_S sets the observer's rate filter (docs/bridge.md: chosen on the true state);
  // MRSKIN_RATE_LINE_S selects the segmented-line rate with that memory, MRSKIN_RATE_CHANGE_SIGMA
  // its change threshold (docs/bridge.md, "A segmented-line rate"); MRSKIN_NETWORK_STEP_S the
  // observer's network_step_s (docs/bridge.md, "The network in phases"); MRSKIN_SMALL_GRID_SWEEPS
  // its small_grid_sweeps (docs/bridge.md, "Cost per tick").
  const char* seed = std::getenv("MRSKIN_CLOSED_LOOP_SEED");
  BridgeOptions options;
  if (const char* tau = std::getenv("MRSKIN_RATE_FILTER_S"); tau != nullptr) {
    options.observer.rate_filter_time_constant_s = std::strtod(tau, nullptr);
  }
  if (const char* memory = std::getenv("MRSKIN_RATE_LINE_S"); memory != nullptr) {
    options.observer.rate_estimator = model::RateEstimator::segmented_line;
    options.observer.rate_memory_s = std::strtod(memory, nullptr);
  }
  if (const char* h = std::getenv("MRSKIN_RATE_CHANGE_SIGMA"); h != nullptr) {
    options.observer.rate_change_threshold_sigma = std::strtod(h, nullptr);
  }
  if (const char* n = std::getenv("MRSKIN_NETWORK_STEP_S"); n != nullptr) {
    options.observer.network_step_s = std::strtod(n, nullptr);
  }
  if (const char* n = std::getenv("MRSKIN_SMALL_GRID_SWEEPS"); n != nullptr) {
    options.observer.small_grid_sweeps = static_cast<int>(std::strtol(n, nullptr, 10));
  }
  return test::run_scene(scene_name, seconds, std::string("mock://?seed=") + (seed != nullptr ? seed : "7"),
                         network, 0, options);
}

void print(const std::string& name, const LoopRun& r) {
  std::printf(
      "closed loop %-8s rms %.4f N  p95 %5.1f %%  (true state: rms %.4f N  p95 %5.1f %%)  release rms %.3f N "
      " "
      "outside %4.1f %%  max %.4f A  energy %.2f mJ\n",
      name.c_str(), r.stats.force_rms_error_N(), 100.0 * r.stats.relative_error.percentile(0.95),
      r.stats.true_state_rms_error_N(), 100.0 * r.stats.true_state_relative_error.percentile(0.95),
      r.stats.release_rms_error_N(), 100.0 * r.stats.clamped_fraction(), r.stats.max_current_A,
      1e3 * r.stats.passivity_energy_J);
}

struct Bound {
  const char* scene;
  double seconds;
  double rms_N;
  double p95;
  double true_state_rms_N;  // the same, against the law at the finger's true depth and rate
  double true_state_p95;
};

// Measured (seed 7, g++ 12 release): demo 0.012 N / 2.2 %; the organs 0.012-0.018 N RMS, p95
// 1.6-3.7 %; sweep 0.016 N / 2.8 %; tumour 0.011 N / 1.9 %; step 0.077 N / 23 % (its force step is
// faster than the device can follow, docs/bridge.md "Settling"); force_step 0.053 N / 14.8 % (its
// quick press lifts the force above the law by the open valves' drag). Bounds: the product's
// 0.04 N RMS and 7 % p95 on every scene but the two step scenes, which hold their measured values
// + ~20 %. Against the law at the finger's true state every other scene is within 0.001 N and 0.2
// points of the above; step reads 0.050 N / 10.1 %: a third of its 0.077 N is the target
// chattering with the observer's rate noise (heavy damping), which the plant does not follow and
// the finger does not feel. Since loading cells above their law open their valves
// (BridgeOptions::loading_open_fraction): step 0.064 N / 20.8 %, true state 0.046 N / 17.4 %
// (over seeds 1-8 its true-state RMS fell 0.050 -> 0.044 N and its p95 rose 14.5 -> 15.6 %,
// while every organ scene got better: docs/bridge.md), so its true-state p95 bound is 19 %.
constexpr Bound kBounds[] = {
    {"demo", 10.0, 0.040, 0.07, 0.040, 0.07},       {"hand", 8.6, 0.040, 0.07, 0.040, 0.07},
    {"neck", 8.6, 0.040, 0.07, 0.040, 0.07},        {"abdomen", 8.6, 0.040, 0.07, 0.040, 0.07},
    {"thigh", 8.6, 0.040, 0.07, 0.040, 0.07},       {"back", 8.6, 0.040, 0.07, 0.040, 0.07},
    {"stomach", 8.6, 0.040, 0.07, 0.040, 0.07},     {"sweep", 7.5, 0.040, 0.07, 0.040, 0.07},
    {"tumour", 7.5, 0.040, 0.07, 0.040, 0.07},      {"step", 7.0, 0.095, 0.31, 0.065, 0.19},
    {"force_step", 10.9, 0.065, 0.18, 0.065, 0.18},
};

class ClosedLoop : public ::testing::TestWithParam<Bound> {};

// Sanitizer builds run each scene for 2 s: they look for memory and threading errors, and the
// figures are the release build's.
#ifdef MRSKIN_SANITIZED
constexpr bool kScored = false;
#else
constexpr bool kScored = true;
#endif

TEST_P(ClosedLoop, RendersTheSceneWithinItsBound) {
  const Bound b = GetParam();
  const LoopRun r = simulate(b.scene, kScored ? b.seconds : 2.0, nullptr);
  print(b.scene, r);
  if (kScored) {
    EXPECT_GT(r.stats.force_samples, 1000U);
    EXPECT_LE(r.stats.force_rms_error_N(), b.rms_N);
    EXPECT_LE(r.stats.relative_error.percentile(0.95), b.p95);
    EXPECT_LE(r.stats.true_state_rms_error_N(), b.true_state_rms_N);
    EXPECT_LE(r.stats.true_state_relative_error.percentile(0.95), b.true_state_p95);
  }
  EXPECT_EQ(r.stats.active_ticks, 0U) << "the rendering gave energy";
  EXPECT_EQ(r.stats.observer_errors, 0U);
  EXPECT_EQ(r.stats.sensor_faults, 0U) << "a false alarm (sensor_faults_test sweeps seeds 1-8)";
  EXPECT_EQ(r.stats.inverse_errors, 0U);
  EXPECT_EQ(r.stats.send_failures, 0U);
  EXPECT_LE(r.stats.max_current_A, 0.1 + 1e-12);
  EXPECT_EQ(r.faults, 0U);
}

std::string scene_of(const ::testing::TestParamInfo<Bound>& param) { return param.param.scene; }

INSTANTIATE_TEST_SUITE_P(EveryScene, ClosedLoop, ::testing::ValuesIn(kBounds), scene_of);

// The daemon moves the mock's finger from its main thread every ~1.1 ms, so some ticks see no
// finger motion in the middle of a release. Those ticks are not presses: scored as such against
// a releasing cell, the real-time demo read 0.08-0.09 N RMS where the simulated one reads 0.012.
TEST(ClosedLoopStalledFinger, AMissedFingerUpdateIsNotAPress) {
  const LoopRun r = test::run_scene("demo", kScored ? 10.0 : 2.0, "mock://?seed=7", nullptr, 10);
  print("demo/stall", r);
  if (kScored) {
    EXPECT_LE(r.stats.force_rms_error_N(), 0.04);
    EXPECT_LE(r.stats.relative_error.percentile(0.95), 0.07);
  }
}

// Issue 21: the 5x5 at 10 kHz, on high-speed USB (the bus that carries it), within the product's
// figures. The mock samples at 1 kHz: the loop ticks ten times a sample. The finger moves every
// 11 ticks, as the daemon's main thread moves it (every ~1.1 ms): scored with a still-hold of 5
// ticks instead of 5 ms, its releases counted as presses and the demo read 0.101 N (the 0.107 N of
// a real-time daemon run that issue 21 quotes).
TEST(ClosedLoopTenKilohertz, RendersTheDemoWithinTheFigures) {
  BridgeOptions options;
  options.rate_hz = 10'000.0;
  const LoopRun r =
      test::run_scene("demo", kScored ? 10.0 : 2.0, "mock://?seed=7&bus=hid-hs", nullptr, 0, options, 11);
  print("demo/10k", r);
  if (kScored) {
    EXPECT_LE(r.stats.force_rms_error_N(), 0.04);
    EXPECT_LE(r.stats.relative_error.percentile(0.95), 0.07);
  }
  EXPECT_EQ(r.stats.active_ticks, 0U) << "the rendering gave energy";
  EXPECT_EQ(r.stats.observer_errors, 0U);
  EXPECT_EQ(r.stats.sensor_faults, 0U);
  EXPECT_EQ(r.faults, 0U);
}

// `hand` at seed 7 with the defaults and with one rule off: the rule must lower the true-state RMS
// by more than 2 mN and its p95 by at least min_p95_gain, and never give energy.
void expect_hand_renders_closer_with(const BridgeOptions& off, const char* rule, double min_p95_gain) {
  const double seconds = kScored ? 8.6 : 2.0;
  const LoopRun with = test::run_scene("hand", seconds, "mock://?seed=7");
  const LoopRun without = test::run_scene("hand", seconds, "mock://?seed=7", nullptr, 0, off);
  print(std::string("hand/") + rule, with);
  print(std::string("hand/no-") + rule, without);
  if (kScored) {
    EXPECT_LT(with.stats.true_state_rms_error_N(), without.stats.true_state_rms_error_N() - 0.002);
    EXPECT_LE(with.stats.true_state_relative_error.percentile(0.95),
              without.stats.true_state_relative_error.percentile(0.95) - min_p95_gain);
  }
  EXPECT_EQ(with.stats.active_ticks, 0U) << "the rendering gave energy";
}

// A loading cell pushing well above its law opens its valves (BridgeOptions::
// loading_open_fraction): on `hand` at seed 7 the true-state error falls from 0.0142 to
// 0.0108 N RMS, p95 1.8 % both (measured; 0.0180 -> 0.0140 N and 3.6 -> 3.1 % before loading cells
// short of their law locked). Off, the inverse's feed-forward and the slow feedback shed the
// surplus only as the rate estimate catches up.
TEST(ClosedLoopLoadingOpen, OpeningALoadingCellAboveItsLawRendersHandCloser) {
  BridgeOptions off;
  off.loading_open_fraction = std::numeric_limits<double>::infinity();
  expect_hand_renders_closer_with(off, "open", 0.0);
}

// A loading cell short of its law holds its valves even where the feedback wound its request
// below the law (BridgeOptions::lock_short_of_law): on `hand` at seed 7 the true-state error falls
// from 0.0140 to 0.0108 N RMS and 3.1 to 1.8 % p95 (measured). Off, the cell sags under its law as
// the finger slows into a hold, and stays there.
TEST(ClosedLoopLockShort, ALoadingCellShortOfItsLawRendersHandCloser) {
  BridgeOptions off;
  off.lock_short_of_law = false;
  expect_hand_renders_closer_with(off, "lock", 0.005);
}

TEST(ClosedLoopLoadingOpen, ANegativeFractionIsRefused) {
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  OpenedDevice dev = open_device("mock://?seed=7", clock, open);
  auto scene = make_scene("hand");
  for (const double bad : {-0.1, std::numeric_limits<double>::quiet_NaN()}) {
    BridgeOptions options;
    options.loading_open_fraction = bad;
    EXPECT_THROW(Bridge(*dev.session, *scene, options), InvalidArgument);
  }
}

// A coarser plant substep (mock://?physics_dt=, issue 21: what lets a large grid's plant keep
// real time) costs the 5x5 little: within 0.002 N RMS and 1 point p95 of the default 0.1 ms
// (0.5 points until loading cells above their law opened their valves: +0.0019 N, +0.6 points
// since, docs/bridge.md "Every grid in real time").
TEST(ClosedLoopCoarsePlant, AMillisecondSubstepRendersTheDemoAsTheDefaultDoes) {
  const double seconds = kScored ? 8.0 : 2.0;
  const LoopRun fine = test::run_scene("demo", seconds, "mock://?seed=7");
  const LoopRun coarse = test::run_scene("demo", seconds, "mock://?seed=7&physics_dt=1e-3");
  print("demo/dt1ms", coarse);
  if (kScored) {
    EXPECT_LE(coarse.stats.force_rms_error_N(), fine.stats.force_rms_error_N() + 0.002);
    EXPECT_LE(coarse.stats.relative_error.percentile(0.95),
              fine.stats.relative_error.percentile(0.95) + 0.01);
  }
  EXPECT_EQ(coarse.stats.active_ticks, 0U) << "the rendering gave energy";
  EXPECT_EQ(coarse.stats.observer_errors, 0U);
  EXPECT_EQ(coarse.faults, 0U);
}

TEST(ClosedLoopNetwork, DelayJitterAndLossStayConsistentAndPassive) {
  ImpairmentOptions net;  // 50 ms +- 20 ms, 5 % loss
  net.seed = 3;
  const double seconds = kScored ? 10.0 : 3.0;
  const LoopRun clean = simulate("demo", seconds, nullptr);
  const LoopRun r = simulate("demo", seconds, &net);
  print("demo/net", r);
  // The network did what it says: about 5 % lost, the rest delivered, some out of order.
  EXPECT_NEAR(static_cast<double>(r.network.lost) / static_cast<double>(r.network.sent), 0.05, 0.01);
  EXPECT_GT(r.network.reordered, 0U);
  EXPECT_EQ(r.network.overflowed, 0U);
  // Consistent: the model is the delayed tissue's, so the rendering stays close to the clean run,
  // and nothing gives energy back.
  EXPECT_EQ(r.stats.active_ticks, 0U);
  EXPECT_GE(r.stats.passivity_min_energy_J, -50e-6);
  EXPECT_LE(r.stats.force_rms_error_N(), clean.stats.force_rms_error_N() + 0.02);
  EXPECT_EQ(r.stats.observer_errors, 0U);
  EXPECT_EQ(r.stats.inverse_errors, 0U);
  // End to end runs from a sample's arrival (not from the robot's stamp): at most the tick
  // period on the simulated clock, whatever the network's delay.
  EXPECT_GT(r.stats.end_to_end_latency.count(), kScored ? 5000U : 1000U);
  EXPECT_LE(r.stats.end_to_end_latency.percentile_ns(0.99), 1e6);
}

TEST(ClosedLoopNetwork, AStoppedStreamFadesToReleased) {
  // The stream stops for good (loss 1 is not allowed: a delay longer than the run instead).
  ImpairmentOptions net;
  net.delay_s = 100.0;
  net.jitter_s = 0.0;
  net.loss = 0.0;
  net.capacity = 20000;
  const LoopRun r = simulate("demo", 3.0, &net);
  EXPECT_EQ(r.network.delivered, 0U);
  EXPECT_EQ(r.stats.max_current_A, 0.0);  // no data: the safe state, valves released
  EXPECT_EQ(r.stats.slave_samples, 0U);
}

}  // namespace
}  // namespace mrskin::bridge
