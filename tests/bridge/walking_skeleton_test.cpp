// The whole slice on the simulated clock: scene -> mock device bytes -> session -> bridge.
#include <gtest/gtest.h>

#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/driver/device.hpp"

namespace mrskin::bridge {
namespace {

class MockTruth final : public ForceTruth {
 public:
  explicit MockTruth(const MockDevice& mock) : mock_(mock) {}
  void true_forces(std::span<double> out_N) const noexcept override { mock_.true_contact_forces(out_N); }

 private:
  const MockDevice& mock_;
};

struct SimResult {
  BridgeStats stats;
  std::vector<double> currents_A;
  DeviceState state = DeviceState::disabled;
};

SimResult simulate(double seconds, std::uint64_t seed) {
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  OpenedDevice dev = open_device("mock://?seed=" + std::to_string(seed), clock, open);
  auto scene = make_scene("demo");
  Bridge loop(*dev.session, *scene);
  MockTruth truth(*dev.mock);
  loop.set_force_truth(&truth);
  loop.set_perf_clock(&clock);  // deterministic: no wall time anywhere
  scene->set_start(clock.now());
  EXPECT_EQ(loop.enable(), ResultCode::ok);
  std::vector<double> finger(dev.mock->layout().fluid_cell_count());
  const auto ticks = static_cast<int>(seconds * 1000.0);
  for (int k = 0; k < ticks; ++k) {
    scene->finger(to_seconds(clock.now() - scene->start()), dev.mock->layout(), finger);
    dev.mock->set_finger_indentation(finger);
    dev.mock->step(clock.now());
    (void)loop.step(clock.now());
    clock.advance(std::chrono::milliseconds(1));
  }
  SimResult r;
  r.stats = loop.stats();
  r.currents_A.resize(dev.mock->layout().valve_count());
  dev.mock->applied_currents(r.currents_A);
  r.state = dev.session->state();
  return r;
}

TEST(WalkingSkeleton, DemoConvergesOnSimulatedClock) {
  const SimResult r = simulate(10.0, 7);
  EXPECT_EQ(r.stats.ticks, 10000U);
  EXPECT_EQ(r.stats.send_failures, 0U);
  EXPECT_EQ(r.stats.slave_samples, 10000U);
  EXPECT_GT(r.stats.force_samples, 5000U);
  EXPECT_EQ(r.state, DeviceState::enabled);
  // Regression bounds, not the product's figures: on the +-15 % perturbed network plant,
  // without calibration, the demo renders at ~0.067 N RMS over 10 s (the reservoir's 500 Pa
  // precharge refills a released cell between presses). Bridge I (issue 9) owns the 0.04 N
  // target; what is left is mostly the observer's force model against the perturbed plant.
  EXPECT_LT(r.stats.force_rms_error_N(), 0.1) << to_json(r.stats, 1e-3);
  EXPECT_LT(r.stats.clamped_fraction(), 0.3);
}

TEST(WalkingSkeleton, SameSeedGivesSameResult) {
  const SimResult a = simulate(3.0, 11);
  const SimResult b = simulate(3.0, 11);
  EXPECT_EQ(a.stats.force_samples, b.stats.force_samples);
  EXPECT_EQ(a.stats.force_sq_error_sum_N2, b.stats.force_sq_error_sum_N2);
  EXPECT_EQ(a.currents_A, b.currents_A);
}

TEST(WalkingSkeleton, HeartbeatLossReleasesValves) {
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  OpenedDevice dev = open_device("mock://?seed=3", clock, open);
  auto scene = make_scene("demo");
  Bridge loop(*dev.session, *scene);
  scene->set_start(clock.now());
  ASSERT_EQ(loop.enable(), ResultCode::ok);
  std::vector<double> finger(dev.mock->layout().fluid_cell_count());
  std::vector<double> currents(dev.mock->layout().valve_count());
  auto tick = [&](bool host_alive) {
    scene->finger(to_seconds(clock.now() - scene->start()), dev.mock->layout(), finger);
    dev.mock->set_finger_indentation(finger);
    dev.mock->step(clock.now());
    if (host_alive) {
      (void)loop.step(clock.now());
    }
    clock.advance(std::chrono::milliseconds(1));
  };
  for (int k = 0; k < 1500; ++k) {  // mid-hold: valves carry current
    tick(true);
  }
  dev.mock->applied_currents(currents);
  double held = 0.0;
  for (const double a : currents) {
    held = std::max(held, a);
  }
  ASSERT_GT(held, 0.01);
  for (int k = 0; k < 150; ++k) {  // host silent for longer than the 100 ms watchdog
    tick(false);
  }
  dev.mock->applied_currents(currents);
  for (const double a : currents) {
    EXPECT_EQ(a, 0.0);
  }
  (void)loop.step(clock.now());
  EXPECT_EQ(dev.session->state(), DeviceState::fault);
  EXPECT_STREQ(fault_name(dev.session->fault_code()), "heartbeat lost");
  EXPECT_TRUE(dev.session->valves_released());
}

}  // namespace
}  // namespace mrskin::bridge
