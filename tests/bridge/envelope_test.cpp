// The allocation's per-cell outputs (targets_N, envelope_floor_N, envelope_ceiling_N) against the
// inverse's roles on every tick of a scene that presses, holds and releases many cells: the
// allocation walks only the loaded cells, so a cell that leaves the loaded set must be reset.
#include <gtest/gtest.h>

#include <cmath>
#include <cstddef>
#include <vector>

#include "scene_rig.hpp"

namespace mrskin::bridge {
namespace {

TEST(Envelope, OnlyLoadedCellsHaveAnEnvelopeAndATargetOnEveryTick) {
  std::size_t loaded_ticks = 0;
  std::size_t released = 0;  // a cell loaded on one tick and not on the next
  std::size_t wrong = 0;
  std::vector<unsigned char> was_loaded;
  const auto check = [&](const Bridge& loop, int k) {
    const std::span<const model::CellSolution> cells = loop.inverse().cells();
    was_loaded.resize(cells.size(), 0);
    for (std::size_t i = 0; i < cells.size(); ++i) {
      const bool loaded =
          cells[i].role == model::CellRole::holding || cells[i].role == model::CellRole::loading;
      const double floor_N = loop.envelope_floor_N()[i];
      const double ceiling_N = loop.envelope_ceiling_N()[i];
      const double target_N = loop.targets_N()[i];
      const bool ok = loaded ? std::isfinite(floor_N) && std::isfinite(ceiling_N) && target_N >= floor_N &&
                                   target_N <= ceiling_N
                             : std::isnan(floor_N) && std::isnan(ceiling_N) && target_N == 0.0;
      if (!ok && ++wrong <= 3) {
        ADD_FAILURE() << "tick " << k << " cell " << i << (loaded ? " loaded" : " not loaded") << ": floor "
                      << floor_N << " N, ceiling " << ceiling_N << " N, target " << target_N << " N";
      }
      loaded_ticks += loaded ? 1 : 0;
      released += !loaded && was_loaded[i] != 0 ? 1 : 0;
      was_loaded[i] = loaded ? 1 : 0;
    }
  };
  // The sweep's finger crosses the skin: cells load and unload in turn.
  (void)test::run_scene("sweep", 6.0, "mock://?seed=5", nullptr, 0, {}, 1, check);
  EXPECT_EQ(wrong, 0U);
  EXPECT_GT(loaded_ticks, 1000U);
  EXPECT_GT(released, 5U) << "the scene must release cells for the test to mean anything";
}

}  // namespace
}  // namespace mrskin::bridge
