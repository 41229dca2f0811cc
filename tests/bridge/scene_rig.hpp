// Runs a built-in scene through the whole slice on the simulated clock: scene -> mock device
// bytes -> session -> bridge, the finger driven by the scene, scored against the mock's truth.
#pragma once

#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/bridge/impairment.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/eval/bus_stats.hpp"
#include "mrskin/eval/truth_scorer.hpp"
#include "mrskin/sim/open_mock.hpp"

namespace mrskin::bridge::test {

struct SceneRun {
  BridgeStats stats;
  ImpairmentStats network;  // with a network only
  std::vector<double> currents_A;
  DeviceState state = DeviceState::disabled;
  std::uint64_t faults = 0;
};

// network: nullptr for a direct stream, else the slave stream goes through ImpairedSource.
// stall_every > 0: the finger's script is not advanced on every stall_every-th tick, as when a
// daemon's thread moves it on its own ~1.1 ms period. finger_every > 1: it is advanced only every
// finger_every-th tick (that ~1.1 ms period at a loop rate above 1 kHz: 11 ticks at 10 kHz).
// after_tick: called after every tick with the bridge and the tick's index.
inline SceneRun run_scene(const std::string& scene_name, double seconds, const std::string& device_uri,
                          const ImpairmentOptions* network = nullptr, int stall_every = 0,
                          const BridgeOptions& options = {}, int finger_every = 1,
                          const std::function<void(const Bridge&, int)>& after_tick = {}) {
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  OpenedDevice dev = open_device(device_uri, clock, open);
  auto scene = make_scene(scene_name);
  std::unique_ptr<ImpairedSource> impaired;
  SlaveSource* source = scene.get();
  if (network != nullptr) {
    impaired = std::make_unique<ImpairedSource>(*scene, *network);
    source = impaired.get();
  }
  Bridge loop(*dev.session, *source, options);
  sim::MockDeviceTruth truth(*sim::mock_of(dev));
  eval::TruthScorer scorer(truth, sim::mock_of(dev)->layout().fluid_cell_count(), loop.options());
  loop.set_tick_watcher(&scorer);
  loop.set_perf_clock(&clock);  // deterministic: no wall time anywhere
  scene->set_start(clock.now());
  EXPECT_EQ(loop.enable(), ResultCode::ok);
  std::vector<double> finger(sim::mock_of(dev)->layout().fluid_cell_count());
  // One tick per loop period (options.rate_hz; the mock samples at its own telemetry rate).
  const auto ticks = static_cast<int>(std::lround(seconds * options.rate_hz));
  const auto period =
      std::chrono::duration_cast<Duration>(std::chrono::duration<double>(1.0 / options.rate_hz));
  for (int k = 0; k < ticks; ++k) {
    if ((stall_every <= 0 || k % stall_every != 0) && (finger_every <= 1 || k % finger_every == 0)) {
      mrskin::eval::press_scene_finger(*scene, to_seconds(clock.now() - scene->start()),
                                       sim::mock_of(dev)->layout(), finger, loop.scale().length);
      sim::mock_of(dev)->set_finger_indentation(finger);
    }
    sim::mock_of(dev)->step(clock.now());
    (void)loop.step(clock.now());
    if (after_tick) {
      after_tick(loop, k);
    }
    clock.advance(period);
  }
  SceneRun r;
  r.stats = loop.stats();
  eval::fill_bus_stats(*sim::mock_of(dev), r.stats);
  if (impaired) {
    r.network = impaired->stats();
  }
  r.currents_A.resize(sim::mock_of(dev)->layout().valve_count());
  sim::mock_of(dev)->applied_currents(r.currents_A);
  r.state = dev.session->state();
  r.faults = dev.session->counters().faults;
  return r;
}

}  // namespace mrskin::bridge::test
