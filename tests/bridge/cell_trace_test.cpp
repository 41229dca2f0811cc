// One cell of a unit traced tick by tick against the mock's truth (docs/bridge.md, "Where the
// 16x16's hold goes"): two measurements run by hand (DISABLED_, their variables below) and one
// check of the plant they rely on, that the fingertip can hold the demo's force at all.
//   MRSKIN_TRACE_DEVICE   the unit (default mock://fingertip-16x16?seed=7)
//   MRSKIN_TRACE_SCENE    the scene (default demo)
//   MRSKIN_TRACE_FROM_S, MRSKIN_TRACE_TO_S, MRSKIN_TRACE_EVERY   the ticks printed (0-3 s, every 50th)
//   MRSKIN_TRACE_CURRENT  the open loop's current on every valve, as a fraction of the maximum
//   MRSKIN_TRACE_ONLY_DEEPEST=1   the open loop's current on the deepest cell's valves only
//   MRSKIN_TRACE_INTEGRATION, MRSKIN_TRACE_SUBSTEPS_PER_MS   the plant alone's integration
//     (automatic, discrete_gradient or backward_euler) and substeps a tick (default 10)
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/driver/model/device_model.hpp"
#include "mrskin/driver/model/profile.hpp"
#include "mrskin/sim/network_plant.hpp"
#include "scene_rig.hpp"

namespace mrskin::bridge {
namespace {

std::string env_or(const char* name, const char* fallback) {
  const char* v = std::getenv(name);
  return v != nullptr ? v : fallback;
}
double env_or(const char* name, double fallback) {
  const char* v = std::getenv(name);
  return v != nullptr ? std::atof(v) : fallback;
}

// The cell the finger presses deepest (the first one found at the finger's first contact).
struct DeepestCell {
  int index = -1;
  void find(const std::vector<double>& finger_m) {
    double deepest_m = 0.0;
    for (std::size_t c = 0; index < 0 && c < finger_m.size(); ++c) {
      deepest_m = std::max(deepest_m, finger_m[c]);
    }
    for (std::size_t c = 0; index < 0 && deepest_m > 0.0 && c < finger_m.size(); ++c) {
      if (finger_m[c] == deepest_m) {
        index = static_cast<int>(c);
      }
    }
  }
};

// Every valve at one current (no bridge), the scene's finger at the unit's design scale: the true
// force on the deepest cell every tick, with the nominal model's envelope at rest beside it.
struct OpenLoop {
  std::vector<double> true_N;  // per tick
  int cell = -1;
  double floor_at_hold_N = 0.0;
};

OpenLoop run_open_loop(const std::string& device, const std::string& scene_name, double fraction, int ticks,
                       bool print) {
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  OpenedDevice dev = open_device(device, clock, open);
  auto scene = make_scene(scene_name);
  auto mock = sim::mock_of(dev);
  const model::DeviceModel nominal(mock->profile());
  const std::size_t cells = mock->layout().fluid_cell_count();
  const double length = design_scale(nominal.profile().design).length;
  std::vector<double> finger(cells);
  std::vector<double> truth(cells);
  std::vector<double> current(mock->layout().valve_count(), fraction * nominal.profile().coil.max_current_A);
  EXPECT_EQ(dev.session->request_enable(), ResultCode::ok);
  for (int k = 0; k < 50; ++k) {  // the unit's handshake and enable
    mock->step(clock.now());
    (void)dev.session->poll(clock.now());
    clock.advance(std::chrono::milliseconds(1));
  }
  scene->set_start(clock.now());
  OpenLoop out;
  DeepestCell deepest;
  const int every = static_cast<int>(env_or("MRSKIN_TRACE_EVERY", 50.0));
  for (int k = 0; k < ticks; ++k) {
    eval::press_scene_finger(*scene, to_seconds(clock.now() - scene->start()), mock->layout(), finger,
                             length);
    mock->set_finger_indentation(finger);
    (void)dev.session->send_valve_currents(current);
    mock->step(clock.now());
    (void)dev.session->poll(clock.now());
    mock->true_contact_forces(truth);
    const bool was = deepest.index >= 0;
    deepest.find(finger);
    const auto c = static_cast<std::size_t>(std::max(deepest.index, 0));
    if (!was && deepest.index >= 0 && std::getenv("MRSKIN_TRACE_ONLY_DEEPEST") != nullptr) {
      const auto& fluid = mock->layout().fluid_cells();
      const auto& valves = mock->layout().valves();
      for (std::size_t v = 0; v < valves.size(); ++v) {
        if (std::abs(valves[v].row - fluid[c].row) + std::abs(valves[v].col - fluid[c].col) != 1) {
          current[v] = 0.0;
        }
      }
    }
    out.true_N.push_back(deepest.index >= 0 ? truth[c] : 0.0);
    const model::Result<model::CellEnvelope> at_rest = nominal.envelope(c, finger[c], 0.0);
    if (deepest.index >= 0 && at_rest.ok()) {
      out.floor_at_hold_N = at_rest.value.force_min_N;
      if (print && k % every == 0) {
        std::printf(
            "%6.3f s cell %zu finger %7.2f um | true %7.3f mN | nominal envelope at rest %.3f-%.3f mN\n",
            k * 1e-3, c, finger[c] * 1e6, truth[c] * 1e3, at_rest.value.force_min_N * 1e3,
            at_rest.value.force_max_N * 1e3);
      }
    }
    clock.advance(std::chrono::milliseconds(1));
  }
  out.cell = deepest.index;
  return out;
}

// The demo's hold on the fingertip asks about 7.1 mN of its deepest cell (the law at 157 um);
// with every valve held at a quarter of the maximum current the plant holds 13.0 mN there, and
// at the whole current 28.6 mN: the unit can render the hold, so a closed loop that renders
// 2.6 mN (the valves' open floor) loses it in the control, not in the plant.
TEST(CellTrace, TheFingertipHoldsTheDemosForceAtAQuarterOfItsCurrent) {
  const OpenLoop quarter = run_open_loop("mock://fingertip-16x16?seed=7", "demo", 0.25, 1600, false);
  ASSERT_GE(quarter.cell, 0);
  const double hold_N = quarter.true_N[1500];  // 1.5 s: the finger still since 1.0 s
  EXPECT_GT(hold_N, 10e-3);
  EXPECT_GT(hold_N, 4.0 * quarter.floor_at_hold_N);
}

TEST(CellTrace, DISABLED_OpenLoopAtOneCurrent) {
  const double fraction = env_or("MRSKIN_TRACE_CURRENT", 1.0);
  (void)run_open_loop(env_or("MRSKIN_TRACE_DEVICE", "mock://fingertip-16x16?seed=7"),
                      env_or("MRSKIN_TRACE_SCENE", "demo"), fraction,
                      static_cast<int>(1e3 * env_or("MRSKIN_TRACE_TO_S", 3.0)), true);
}

// The deepest cell on one tick of the bridge: what the finger does, what the observer reads,
// the truth, what the bridge asks and the mean current of the cell's valves.
struct CellTick {
  std::size_t cell = 0;
  double finger_m = 0.0;
  double observed_m = 0.0;
  double observed_rate_m_per_s = 0.0;
  double observed_N = 0.0;
  double true_N = 0.0;
  double target_N = 0.0;
  double law_N = 0.0;
  double floor_N = 0.0;
  double ceiling_N = 0.0;
  double current_A = 0.0;
  model::CellRole role = model::CellRole::no_contact;
};

// The bridge (default BridgeOptions) on the unit for `ticks` ticks at 1 kHz; each(tick, cell)
// once the finger has touched.
template <class Each>
void run_closed_loop(const std::string& device, const std::string& scene_name, int ticks, Each&& each) {
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  OpenedDevice dev = open_device(device, clock, open);
  auto scene = make_scene(scene_name);
  Bridge loop(*dev.session, *scene, BridgeOptions{});
  auto mock = sim::mock_of(dev);
  const std::size_t cells = mock->layout().fluid_cell_count();
  sim::MockDeviceTruth truth(*mock);
  eval::TruthScorer scorer(truth, cells, loop.options());
  loop.set_tick_watcher(&scorer);
  loop.set_perf_clock(&clock);
  scene->set_start(clock.now());
  ASSERT_EQ(loop.enable(), ResultCode::ok);
  std::vector<double> finger(cells);
  std::vector<double> true_N(cells);
  const auto& fluid = mock->layout().fluid_cells();
  const auto& valves = mock->layout().valves();
  DeepestCell deepest;
  for (int k = 0; k < ticks; ++k) {
    eval::press_scene_finger(*scene, to_seconds(clock.now() - scene->start()), mock->layout(), finger,
                             loop.scale().length);
    mock->set_finger_indentation(finger);
    mock->step(clock.now());
    (void)loop.step(clock.now());
    mock->true_contact_forces(true_N);
    deepest.find(finger);
    if (deepest.index >= 0) {
      CellTick t;
      t.cell = static_cast<std::size_t>(deepest.index);
      const std::size_t c = t.cell;
      double sum_A = 0.0;
      int around = 0;
      for (std::size_t v = 0; v < valves.size(); ++v) {
        if (std::abs(valves[v].row - fluid[c].row) + std::abs(valves[v].col - fluid[c].col) == 1) {
          sum_A += loop.currents_A()[v];
          ++around;
        }
      }
      t.finger_m = finger[c];
      t.observed_m = loop.observer().indentation_m()[c];
      t.observed_rate_m_per_s = loop.observer().velocity_m_per_s()[c];
      t.observed_N = loop.observer().force_N()[c];
      t.true_N = true_N[c];
      t.target_N = loop.targets_N()[c];
      t.law_N = loop.law_N()[c];
      t.floor_N = loop.envelope_floor_N()[c];
      t.ceiling_N = loop.envelope_ceiling_N()[c];
      t.current_A = around > 0 ? sum_A / around : 0.0;
      t.role = loop.inverse().cells()[c].role;
      each(k, t);
    }
    clock.advance(std::chrono::milliseconds(1));
  }
}

// Until 2026-12-04 the fingertip's valves swung between 0 A and the highest current every few
// ticks of the demo's press (360 ticks of 700 moved by more than a quarter of it, 141 by more
// than half): drain_then_seal drained a cell the observer read above its law, the stiff cell
// emptied within the tick, and the observer's force fell only with its coils. A drain now needs
// a cell that takes at least a tick to empty (AllocateStage: 1.7 s on the 5x5, 3.5 us here).
TEST(CellTrace, TheFingertipsPressMovesItsValvesSmoothly) {
  const double max_current_A =
      model::DeviceModel(model::load_profile("fingertip-16x16")).profile().coil.max_current_A;
  int jumps = 0;
  double last_A = -1.0;
  run_closed_loop("mock://fingertip-16x16?seed=7", "demo", 1000, [&](int tick, const CellTick& t) {
    if (tick >= 300 && last_A >= 0.0 && std::abs(t.current_A - last_A) > 0.25 * max_current_A) {
      ++jumps;
    }
    last_A = t.current_A;
  });
  EXPECT_EQ(jumps, 0);
}

// The demo's hold, from 1.05 s to 2.0 s, with the default options: never released, and the true
// force on the deepest cell on average at least 0.9 of the law (0.950 of it since the plant stopped
// ringing, 0.907 on the ringing plant; 0.370, the open floor, with 607 of the 950 ticks unloading
// before the direction latch's retreat rose above the fit's noise:
// DesignScale.TheDirectionLatchFollowsTheSensorsNoise).
TEST(CellTrace, TheFingertipHoldsTheDemosLaw) {
  int released = 0;
  double true_sum_N = 0.0;
  double law_sum_N = 0.0;
  run_closed_loop("mock://fingertip-16x16?seed=7", "demo", 2000, [&](int tick, const CellTick& t) {
    if (tick >= 1050) {
      released += t.role == model::CellRole::unloading ? 1 : 0;
      true_sum_N += t.true_N;
      law_sum_N += t.law_N;
    }
  });
  std::printf("demo hold 1.05-2.0 s: %d ticks released, true / law %.3f\n", released, true_sum_N / law_sum_N);
  EXPECT_EQ(released, 0);
  EXPECT_GT(true_sum_N, 0.9 * law_sum_N) << "true / law " << true_sum_N / law_sum_N;
}

// The plant alone (sim::NetworkPlant: no perturbation, noise, hysteresis or command delay) under
// the scene's finger, every valve at MRSKIN_TRACE_CURRENT of the maximum (or only the demo's
// deepest cell's, MRSKIN_TRACE_ONLY_DEEPEST=1): every 50th tick from 0.3 s to 1.5 s, the deepest
// cell's depth, force and pressure, and each fluid cell around it with its depth and pressure.
TEST(CellTrace, DISABLED_PlantPressuresAroundTheDeepestCell) {
  const model::DeviceModel nominal(model::load_profile("fingertip-16x16"));
  sim::NetworkPlantOptions exact;
  exact.perturbation = 0.0;
  exact.sensor_noise_scale = 0.0;
  exact.hysteresis_scale = 0.0;
  exact.command_delay_s = 0.0;
  const int substeps_per_ms = static_cast<int>(env_or("MRSKIN_TRACE_SUBSTEPS_PER_MS", 10.0));
  exact.substep_s = 1e-3 / substeps_per_ms;
  const std::string integration = env_or("MRSKIN_TRACE_INTEGRATION", "automatic");
  if (integration == "discrete_gradient") {
    exact.integration = sim::NetworkPlantOptions::Integration::discrete_gradient;
  } else if (integration == "backward_euler") {
    exact.integration = sim::NetworkPlantOptions::Integration::backward_euler;
  } else {
    ASSERT_EQ(integration, "automatic")
        << "MRSKIN_TRACE_INTEGRATION: automatic, discrete_gradient or backward_euler";
  }
  sim::NetworkPlant plant(nominal.profile(), exact);
  const GridLayout& layout = nominal.layout();
  const std::size_t cells = layout.fluid_cell_count();
  const auto& fluid = layout.fluid_cells();
  const auto& valves = layout.valves();
  constexpr std::size_t kDeepest = 59;  // the demo's
  std::vector<double> current(layout.valve_count(),
                              env_or("MRSKIN_TRACE_CURRENT", 0.25) * nominal.profile().coil.max_current_A);
  for (std::size_t v = 0; v < valves.size(); ++v) {
    const int away =
        std::abs(valves[v].row - fluid[kDeepest].row) + std::abs(valves[v].col - fluid[kDeepest].col);
    if (std::getenv("MRSKIN_TRACE_ONLY_DEEPEST") != nullptr && away != 1) {
      current[v] = 0.0;
    }
  }
  plant.set_valve_currents(current);
  std::vector<std::size_t> around;
  for (std::size_t k = 0; k < cells; ++k) {
    const int rows = std::abs(fluid[k].row - fluid[kDeepest].row);
    const int cols = std::abs(fluid[k].col - fluid[kDeepest].col);
    if (rows + cols == 2) {
      around.push_back(k);
    }
  }
  auto scene = make_scene(env_or("MRSKIN_TRACE_SCENE", "demo"));
  std::vector<double> finger(cells);
  std::vector<double> force(cells);
  const double length = design_scale(nominal.profile().design).length;
  for (int k = 0; k <= 1500; ++k) {
    eval::press_scene_finger(*scene, k * 1e-3, layout, finger, length);
    plant.set_finger_indentation(finger);
    for (int s = 0; s < substeps_per_ms; ++s) {
      plant.step(exact.substep_s);
    }
    if (k < 300 || k % 50 != 0) {
      continue;
    }
    plant.contact_forces(force);
    const std::span<const double> pressure_Pa = plant.network().cell_pressure_Pa();
    std::printf("%5.3f s cell %zu %6.1f um %6.2f mN %7.0f Pa | around:", k * 1e-3, kDeepest,
                finger[kDeepest] * 1e6, force[kDeepest] * 1e3, pressure_Pa[kDeepest]);
    for (const std::size_t n : around) {
      std::printf(" %zu %5.1f um %6.0f Pa", n, finger[n] * 1e6, pressure_Pa[n]);
    }
    std::printf("\n");
  }
}

// Per printed tick: the deepest cell's finger, the observer's depth, rate and force, the true
// force, the target, the law, the envelope, the mean current of its valves and the inverse's role.
TEST(CellTrace, DISABLED_WatchTheDeepestCell) {
  const int from = static_cast<int>(1e3 * env_or("MRSKIN_TRACE_FROM_S", 0.0));
  const int to = static_cast<int>(1e3 * env_or("MRSKIN_TRACE_TO_S", 3.0));
  const int every = static_cast<int>(env_or("MRSKIN_TRACE_EVERY", 50.0));
  run_closed_loop(
      env_or("MRSKIN_TRACE_DEVICE", "mock://fingertip-16x16?seed=7"), env_or("MRSKIN_TRACE_SCENE", "demo"),
      to, [&](int k, const CellTick& t) {
        if (k < from || (k - from) % every != 0) {
          return;
        }
        std::printf(
            "%6.3f s cell %zu finger %7.2f um | observed %7.2f um %7.3f mm/s %7.3f mN | true %7.3f mN | "
            "target %7.3f law %7.3f envelope %.3f-%.3f mN | %.4f A %s\n",
            k * 1e-3, t.cell, t.finger_m * 1e6, t.observed_m * 1e6, t.observed_rate_m_per_s * 1e3,
            t.observed_N * 1e3, t.true_N * 1e3, t.target_N * 1e3, t.law_N * 1e3, t.floor_N * 1e3,
            t.ceiling_N * 1e3, t.current_A, model::to_string(t.role));
      });
}

}  // namespace
}  // namespace mrskin::bridge
