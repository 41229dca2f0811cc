// Design suite, part 1: the scenes frozen into loaded cell-ticks, and a profile's coverage of
// them (the fraction whose tissue-law force lies inside the quasi-static envelope at that cell's
// depth and rate). docs/model.md, "The design study".
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "mrskin/driver/layout.hpp"
#include "mrskin/driver/model/device_model.hpp"

namespace mrskin::bench {

// One loaded cell-tick of a scene: the finger's depth and rate on that cell and the law's force.
struct LoadedTick {
  std::uint32_t cell = 0;
  double depth_m = 0.0;
  double rate_m_per_s = 0.0;  // >= 0: a hold's rounding-level retreat counts as a hold
  double law_N = 0.0;         // the scene's tissue law, capped at the device range
};

struct FrozenScene {
  std::string name;
  std::vector<LoadedTick> ticks;
};

struct FreezeOptions {
  double duration_s = 8.0;  // as the closed loop's golden statistics
  double tick_rate_Hz = 1000.0;
  double contact_threshold_m = 50e-6;  // BridgeOptions' (TruthScorer's "touching")
  double max_force_N = 2.0;            // BridgeOptions::max_force_N
};

// Samples a built-in scene's scripted finger (eval::press_scene_finger) and keeps the cell-ticks
// that TruthScorer would score: deeper than the contact threshold and not retreating.
FrozenScene freeze_scene(const std::string& name, const GridLayout& layout, const FreezeOptions& o);

struct Coverage {
  std::size_t ticks = 0;
  std::size_t inside = 0;
  std::size_t below_floor = 0;
  std::size_t above_ceiling = 0;
  // Of those, where the bound is the pad's own bulge (the cell's membrane takes the volume below
  // the valves' pressure): the envelope's edge that no current moves.
  std::size_t below_bulge_floor = 0;
  std::size_t above_bulge_ceiling = 0;
  // Below the floor, by its largest part (as the bridge's clamp causes): the viscous drag of the
  // open valves (or the bulge), the membrane, the reservoir's p0 on the pad.
  std::size_t floor_viscous = 0;
  std::size_t floor_membrane = 0;
  std::size_t floor_p0 = 0;
  std::size_t model_errors = 0;  // envelope not computable: counted outside
  [[nodiscard]] double fraction() const noexcept {
    return ticks == 0 ? 1.0 : static_cast<double>(inside) / static_cast<double>(ticks);
  }
};

Coverage coverage_of(const model::DeviceModel& m, const FrozenScene& scene) noexcept;

}  // namespace mrskin::bench
