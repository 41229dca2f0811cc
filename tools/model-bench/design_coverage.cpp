#include "design_coverage.hpp"

#include <algorithm>
#include <cmath>
#include <memory>

#include "mrskin/bridge/scene.hpp"
#include "mrskin/eval/truth_scorer.hpp"

namespace mrskin::bench {

FrozenScene freeze_scene(const std::string& name, const GridLayout& layout, const FreezeOptions& o) {
  const std::unique_ptr<bridge::Scene> scene = bridge::make_scene(name);
  const std::size_t n = layout.fluid_cell_count();
  std::vector<double> depth(n, 0.0);
  std::vector<double> prev(n, 0.0);
  std::vector<int> still(n, 0);
  std::vector<unsigned char> retreated(n, 0);
  // The same hold logic as eval::TruthScorer: a cell still after a retreat holds after 5 ticks.
  constexpr double kHoldRate_m_per_s = 1e-6;
  constexpr int kStillTicks = 5;
  const double dt_s = 1.0 / o.tick_rate_Hz;
  const auto ticks = static_cast<long>(std::lround(o.duration_s * o.tick_rate_Hz));
  FrozenScene out{name, {}};
  for (long k = 0; k < ticks; ++k) {
    const double t_s = static_cast<double>(k) * dt_s;
    eval::press_scene_finger(*scene, t_s, layout, depth);
    const bridge::SlaveTruth slave = scene->slave_truth(t_s);
    // The bridge gives the cells around the contact the tissue there (uniform but for tumour).
    const bridge::TissueModel law = scene->tissue_at(slave.contact_x_m, slave.contact_y_m);
    for (std::size_t i = 0; i < n; ++i) {
      const double rate = k == 0 ? 0.0 : (depth[i] - prev[i]) / dt_s;
      if (rate < -kHoldRate_m_per_s) {
        still[i] = 0;
        retreated[i] = 1;
      } else if (rate > kHoldRate_m_per_s) {
        still[i] = 0;
        retreated[i] = 0;
      } else if (still[i] < kStillTicks) {
        ++still[i];
      }
      const bool holding = still[i] >= kStillTicks || retreated[i] == 0;
      if (depth[i] > o.contact_threshold_m && rate >= -kHoldRate_m_per_s && holding) {
        out.ticks.push_back({static_cast<std::uint32_t>(i), depth[i], std::max(rate, 0.0),
                             std::min(law.force_N(depth[i], rate), o.max_force_N)});
      }
    }
    prev = depth;
  }
  return out;
}

Coverage coverage_of(const model::DeviceModel& m, const FrozenScene& scene) noexcept {
  Coverage c;
  for (const LoadedTick& t : scene.ticks) {
    ++c.ticks;
    const model::Result<model::CellEnvelope> e = m.envelope(t.cell, t.depth_m, t.rate_m_per_s);
    if (!e.ok()) {
      ++c.model_errors;
      continue;
    }
    // The inverse's own slack (inverse_solve.cpp): outside by more than round-off is clamped.
    const double slack_N = 1e-9 * (1.0 + e.value.force_max_N);
    if (t.law_N < e.value.force_min_N - slack_N) {
      ++c.below_floor;
      const model::CellLoad& f = e.value.at_min;
      c.below_bulge_floor += f.mode == model::CellMode::bulging ? 1 : 0;
      const double p0_N = f.effective_area_m2 * m.profile().reservoir.initial_pressure_Pa;
      const double viscous_N = f.effective_area_m2 * f.pressure_Pa;
      if (viscous_N >= f.membrane_force_N && viscous_N >= p0_N) {
        ++c.floor_viscous;
      } else if (f.membrane_force_N >= p0_N) {
        ++c.floor_membrane;
      } else {
        ++c.floor_p0;
      }
    } else if (t.law_N > e.value.force_max_N + slack_N) {
      ++c.above_ceiling;
      c.above_bulge_ceiling += e.value.at_max.mode == model::CellMode::bulging ? 1 : 0;
    } else {
      ++c.inside;
    }
  }
  return c;
}

}  // namespace mrskin::bench
