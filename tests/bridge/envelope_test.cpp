// The allocation's per-cell outputs (targets_N, envelope_floor_N, envelope_ceiling_N) against the
// inverse's roles on every tick of a scene that presses, holds and releases many cells: the
// allocation walks only the loaded cells, so a cell that leaves the loaded set must be reset.
#include <gtest/gtest.h>

#include <cmath>
#include <cstddef>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/eval/truth_scorer.hpp"
#include "mrskin/sim/open_mock.hpp"

namespace mrskin::bridge {
namespace {

TEST(Envelope, OnlyLoadedCellsHaveAnEnvelopeAndATargetOnEveryTick) {
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  OpenedDevice dev = open_device("mock://?seed=5", clock, open);
  auto scene = make_scene("sweep");  // the finger crosses the skin: cells load and unload in turn
  Bridge loop(*dev.session, *scene);
  scene->set_start(clock.now());
  ASSERT_EQ(loop.enable(), ResultCode::ok);
  const std::size_t cells = sim::mock_of(dev)->layout().fluid_cell_count();
  std::vector<double> finger(cells);
  std::size_t loaded_ticks = 0;
  std::size_t released = 0;  // a cell loaded on one tick and not on the next
  std::vector<unsigned char> was_loaded(cells, 0);
  for (int k = 0; k < 6000; ++k) {
    mrskin::eval::press_scene_finger(*scene, to_seconds(clock.now() - scene->start()),
                                     sim::mock_of(dev)->layout(), finger);
    sim::mock_of(dev)->set_finger_indentation(finger);
    sim::mock_of(dev)->step(clock.now());
    (void)loop.step(clock.now());
    clock.advance(std::chrono::milliseconds(1));
    for (std::size_t i = 0; i < cells; ++i) {
      const model::CellRole role = loop.inverse().cells()[i].role;
      const bool loaded = role == model::CellRole::holding || role == model::CellRole::loading;
      const double floor_N = loop.envelope_floor_N()[i];
      const double ceiling_N = loop.envelope_ceiling_N()[i];
      const double target_N = loop.targets_N()[i];
      if (loaded) {
        ++loaded_ticks;
        ASSERT_TRUE(std::isfinite(floor_N) && std::isfinite(ceiling_N)) << "tick " << k << " cell " << i;
        ASSERT_GE(target_N, floor_N) << "tick " << k << " cell " << i;
        ASSERT_LE(target_N, ceiling_N) << "tick " << k << " cell " << i;
      } else {
        released += was_loaded[i];
        ASSERT_TRUE(std::isnan(floor_N) && std::isnan(ceiling_N)) << "tick " << k << " cell " << i;
        ASSERT_EQ(target_N, 0.0) << "tick " << k << " cell " << i;
      }
      was_loaded[i] = loaded ? 1 : 0;
    }
  }
  EXPECT_GT(loaded_ticks, 1000U);
  EXPECT_GT(released, 5U) << "the scene must release cells for the test to mean anything";
}

}  // namespace
}  // namespace mrskin::bridge
