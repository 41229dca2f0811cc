// The tick's second stage: the slave stream into the online tissue estimate, and per cell the
// law the finger should feel, as the impedance target and state the inverse takes.
// Private to the bridge library (bridge.cpp runs it).
#pragma once

#include <span>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "tick_record.hpp"

namespace mrskin::bridge::detail {

class RenderStage {
 public:
  // Setup: sizes every per-cell array. options and layout are the bridge's and outlive this.
  // scale: the unit's design point; the slave's tissue law is rendered through it.
  RenderStage(const BridgeOptions& options, const GridLayout& layout, DesignScale scale);

  // The newest slave sample into the estimate; the cells under the mapped contact point take it.
  // Counts samples, stale ticks and stalls in stats; writes the fresh-sample fields of out.
  void take_stream(SlaveSource& source, TimePoint now, TimePoint start, BridgeStats& stats,
                   Rendering& out) noexcept;
  // Per cell: contact, direction, the law at the state and the feedback's shift of it.
  // last_solve: the inverse's last roles and clamps; last_target_N: the last allocation's targets.
  // last_drain_held: cells whose valves the drain-then-seal held last tick (their feedback waits).
  void render(const Observation& observed, std::span<const model::CellSolution> last_solve,
              std::span<const double> last_target_N, std::span<const unsigned char> last_drain_held,
              double dt_s, Rendering& out) noexcept;

  void clear_feedback() noexcept;  // the valves were released: no integral carries over
  void retune_rate() noexcept;     // options' rate changed: the latch's smoothing follows it
  [[nodiscard]] std::span<const CellMemory> cells() const noexcept { return cell_; }
  [[nodiscard]] const TissueEstimator& estimator() const noexcept { return estimator_; }
  [[nodiscard]] TissueEstimator& estimator() noexcept { return estimator_; }
  [[nodiscard]] const TissueEstimate& estimate() const noexcept { return estimate_; }

 private:
  double direction_rate(CellMemory& cell, bool contact, double depth_m, double rate_m_per_s) const noexcept;

  const BridgeOptions& options_;
  const GridLayout& layout_;
  TissueEstimator estimator_;
  TissueEstimate estimate_{};
  // The estimate's law at the unit's design point: law_ on another design, the estimate's own on
  // the reference (no copy a tick).
  [[nodiscard]] const TissueModel& law() const noexcept { return rescale_ ? law_ : estimate_.model; }
  DesignScale scale_{};
  bool rescale_ = false;
  TissueModel law_{};
  SlaveSample slave_{};  // the newest sample taken
  double unload_filter_alpha_ = 1.0;
  std::vector<CellMemory> cell_;
};

}  // namespace mrskin::bridge::detail
