#include "render_stage.hpp"

#include <algorithm>
#include <cmath>

namespace mrskin::bridge::detail {

namespace {
double unload_filter_alpha(const BridgeOptions& o) noexcept {
  return 1.0 - std::exp(-1.0 / (o.rate_hz * std::max(o.unload_filter_s, 1e-9)));
}
// No finger in the cell: the direction latch starts again from nothing.
void release_direction_latch(CellMemory& cell) noexcept {
  cell.loading = 0;
  cell.unloading = 0;
  cell.extreme_m = 0.0;
  cell.smooth_depth_m = 0.0;
}
// Contact lost. A cell that was unloading keeps its latch while its pad is still down (deeper
// than the contact threshold): a finger that leaves a stiff cell faster than the cell refills
// leaves the pad down, its depth and (by the local force model) the valves' hold meet the contact
// rule again, and taking it as a new press sealed the pad with no finger on it (docs/bridge.md,
// "Phantom presses"). The kept latch loads again one retreat above its trough, as any.
void lose_contact(CellMemory& cell, double depth_m, double pad_down_m) noexcept {
  if (cell.unloading != 0 && depth_m > pad_down_m) {
    return;
  }
  release_direction_latch(cell);
}
}  // namespace

RenderStage::RenderStage(const BridgeOptions& options, const GridLayout& layout, DesignScale scale)
    : options_(options),
      layout_(layout),
      estimator_(options.estimator),
      scale_(scale),
      rescale_(scale.length != 1.0 || scale.force != 1.0),
      unload_filter_alpha_(unload_filter_alpha(options)),
      cell_(layout.fluid_cell_count()) {}

void RenderStage::retune_rate() noexcept { unload_filter_alpha_ = unload_filter_alpha(options_); }

void RenderStage::clear_feedback() noexcept {
  for (CellMemory& c : cell_) {
    c.feedback_N = 0.0;
  }
}

void RenderStage::take_stream(SlaveSource& source, TimePoint now, TimePoint start, BridgeStats& stats,
                              Rendering& out) noexcept {
  // Model-mediated rendering: the slave stream updates the online tissue estimate, and the cells
  // under the mapped contact point take it; the stale policy (hold, then fade to released) is the
  // estimator's.
  out.fresh_sample = false;
  SlaveSample sample;
  if (source.latest(now, sample) && sample.valid) {
    ++stats.slave_samples;
    if (!slave_.valid || sample.stamp != slave_.stamp) {
      out.fresh_sample = true;  // its effect leaves with this tick's frame (latency figures)
      stats.slave_force.add(sample.force_N);
      out.fresh_arrival = sample.received.count() != 0 ? sample.received : sample.stamp;
    }
    slave_ = sample;
    // Out-of-order, duplicate and malformed samples are refused and counted by the estimator.
    (void)estimator_.push(
        TissueSample{to_seconds(sample.stamp - start), sample.force_N, sample.indentation_m});
    if (sample.ended) {
      estimator_.end_stream(to_seconds(now - start));
    }
  }
  const bool was_fresh = estimate_.freshness == TissueFreshness::fresh;
  estimate_ = estimator_.estimate(to_seconds(now - start));
  if (rescale_) {
    law_ = estimate_.model.rescaled(scale_.force, scale_.length);
  }
  if (estimate_.freshness != TissueFreshness::fresh) {
    ++stats.stale_ticks;
    stats.stream_stalls += was_fresh ? 1 : 0;
  }
  if (estimate_.freshness == TissueFreshness::fresh && slave_.indentation_m > 0.0) {
    // The cells around the mapped contact point take the current estimate; the others keep
    // theirs (a map of the tissue as the instrument went over it).
    const CellPoint at =
        options_.mapping.to_cell(slave_.contact_x_m, slave_.contact_y_m, layout_.rows(), layout_.cols());
    const double reach = std::max(options_.footprint_cells, options_.mapping.to_cells(slave_.tip_radius_m));
    const auto& cells = layout_.fluid_cells();
    const TissueModel& fresh = law();
    for (std::size_t i = 0; i < cells.size(); ++i) {
      const double dr = cells[i].row - at.row;
      const double dc = cells[i].col - at.col;
      if (dr * dr + dc * dc <= reach * reach) {
        cell_[i].mapped_model = fresh;  // fresh: scale 1
        cell_[i].mapped = 1;
      }
    }
  }
}

double RenderStage::direction_rate(CellMemory& cell, bool contact, double depth_m,
                                   double rate_m_per_s) const noexcept {
  // Hysteresis in position, not in rate: the observer's rate noise (~0.5 mm/s RMS) must neither
  // release a held press nor re-hold a release that is under way. A cell unloads once its depth
  // has fallen retreat_m below its peak, and loads again once it has risen retreat_m above its
  // trough. Between the two, rates within the deadband count as holding.
  const double retreat_m = options_.unload_retreat_m;
  if (!contact) {
    lose_contact(cell, depth_m, options_.contact_threshold_m);
    return 0.0;
  }
  // On a smoothed depth: the fit's noise (2-3 um RMS, ~20 um peaks) shrinks well below retreat_m.
  cell.smooth_depth_m += unload_filter_alpha_ * (depth_m - cell.smooth_depth_m);
  depth_m = cell.smooth_depth_m;
  if (cell.unloading == 0) {
    cell.extreme_m = std::max(cell.extreme_m, depth_m);
    if (depth_m < cell.extreme_m - retreat_m) {
      cell.unloading = 1;
      cell.extreme_m = depth_m;
    }
  } else {
    cell.extreme_m = std::min(cell.extreme_m, depth_m);
    if (depth_m > cell.extreme_m + retreat_m) {
      cell.unloading = 0;
      cell.extreme_m = depth_m;
    }
  }
  if (cell.unloading != 0) {
    cell.loading = 0;
    // Released: the inverse sees a retreating finger whatever the noise says.
    return std::min(rate_m_per_s, -options_.unload_rate_m_per_s);
  }
  // Loading starts above the deadband and lasts until the rate falls below load_exit_rate:
  // hysteresis in rate, so the noise at a press's smooth start does not flip the inverse between
  // loading and holding every few ticks (docs/bridge.md).
  if (rate_m_per_s > options_.unload_rate_m_per_s ||
      (cell.loading != 0 && rate_m_per_s > options_.load_exit_rate_m_per_s)) {
    cell.loading = 1;
    return rate_m_per_s;
  }
  cell.loading = 0;
  return 0.0;
}

void RenderStage::render(const Observation& observed, std::span<const model::CellSolution> last_solve,
                         std::span<const double> last_target_N,
                         std::span<const unsigned char> last_drain_held, double dt_s,
                         Rendering& out) noexcept {
  const std::span<const double> depth_m = observed.depth_m;
  const std::span<const double> force_N = observed.force_N;
  const std::span<const double> outflow = observed.outflow_m3_per_s;
  const TissueModel& unmapped = law();  // the cells the instrument never mapped
  const double valid_until_s = estimate_.valid_until_s;
  std::size_t standing = 0;  // cells whose outputs stand from the last tick
  std::size_t contacts = 0;
  // In locals: the stores into the outputs below would otherwise reload them on every cell.
  const double contact_threshold_m = options_.contact_threshold_m;
  const double contact_force_N = options_.contact_force_N;
  const double max_force_N = options_.max_force_N;
  model::CellImpedanceTarget* const targets = out.target.data();
  for (std::size_t i = 0; i < cell_.size(); ++i) {
    CellMemory& cell = cell_[i];
    model::CellState& state = out.state[i];
    // A membrane sucked in after a release reads as depth with no force on it: no finger.
    const bool contact = depth_m[i] > contact_threshold_m && force_N[i] > contact_force_N;
    contacts += contact ? 1 : 0;
    PassiveTissueUpdate& law = cell.law;
    if (!contact && law.surface_offset_m() == 0.0 && !(law.tank_J() > 0.0)) {
      // Untouched, and the law at rest: what the general path below gives, without evaluating
      // the law (no force at zero depth, no feedback, the same target but for its validity).
      if (cell.rest_valid == 1 && cell.rest_ceiling_N == max_force_N) {
        // At rest last tick too (any other path clears rest_valid): its outputs stand.
        targets[i].valid_until_s = valid_until_s;
        ++standing;
        continue;
      }
      // A latch kept while the pad is down is looked at every tick until the pad is back; the
      // outputs it writes are last tick's, so it stands all the same.
      standing += cell.rest_valid == 2 && cell.rest_ceiling_N == max_force_N ? 1 : 0;
      lose_contact(cell, depth_m[i], contact_threshold_m);
      state.indentation_m = 0.0;
      state.rate_m_per_s = 0.0;
      out.contact[i] = 0;
      out.tissue_N[i] = 0.0;
      cell.feedback_N = 0.0;
      if (cell.rest_valid == 0 || cell.rest_ceiling_N != options_.max_force_N) {
        cell.rest_target = law.target(0.0, options_.max_force_N, valid_until_s);
        cell.rest_ceiling_N = options_.max_force_N;
      }
      cell.rest_valid = cell.unloading != 0 ? 2 : 1;  // 2: a latch kept while the pad is down
      model::CellImpedanceTarget& t = out.target[i];
      t = cell.rest_target;
      t.valid_until_s = valid_until_s;
      continue;
    }
    cell.rest_valid = 0;  // the law may change below
    const double rate = direction_rate(cell, contact, depth_m[i], observed.rate_m_per_s[i]);
    state.indentation_m = contact ? depth_m[i] : 0.0;
    state.rate_m_per_s = contact ? rate : 0.0;
    out.contact[i] = contact ? 1 : 0;
    const model::CellRole role = last_solve[i].role;
    const bool loaded = contact && (role == model::CellRole::loading || role == model::CellRole::holding);
    // The cell's law: its mapped tissue (or the current estimate where the instrument never was),
    // scaled by the stale policy, changed passively while the finger is in the cell.
    if (contact || law.surface_offset_m() > 0.0 || law.tank_J() > 0.0) {
      law.update(cell.mapped != 0 ? cell.mapped_model.scaled(estimate_.scale) : unmapped,
                 state.indentation_m);
    }
    // What the finger should feel (the feedback's shift is not part of it); allocate clamps it
    // into the envelope after the solve.
    out.tissue_N[i] = std::min(law.force_N(state.indentation_m, rate), options_.max_force_N);
    if (!loaded) {
      cell.feedback_N = 0.0;
    } else {
      const double error_N = last_target_N[i] - force_N[i];
      // Optionally frozen while holding: the force is then mostly the trapped volume's. Off by
      // default: the valves hold near their threshold and the integral still trims the slow leak
      // (docs/bridge.md).
      const bool sealed = i < outflow.size() && outflow[i] < options_.sealed_outflow_m3_per_s;
      const bool wound_up = (error_N > 0.0 && (last_solve[i].clamped_high || sealed)) ||
                            (error_N < 0.0 && last_solve[i].clamped_low) ||
                            (options_.freeze_feedback_while_holding && role == model::CellRole::holding) ||
                            // The drain's open valves and the seal after it own the cell: a lower
                            // request cannot drain it faster, a higher one cannot refill it.
                            (i < last_drain_held.size() && last_drain_held[i] != 0);
      if (!wound_up) {
        cell.feedback_N = std::clamp(cell.feedback_N + options_.feedback_gain_per_s * dt_s * error_N,
                                     -options_.feedback_limit_N, options_.feedback_limit_N);
      }
    }
    model::CellImpedanceTarget& t = out.target[i];
    t = law.target(state.indentation_m, options_.max_force_N, valid_until_s);
    // The correction enters as a shift of the tissue's surface: F(x - offset) ~ F(x) + feedback,
    // through the law's tangent stiffness at the state (no correction: no shift to compute).
    if (cell.feedback_N != 0.0) {
      const double tangent =
          law.model().tangent_stiffness_N_per_m(state.indentation_m - law.surface_offset_m());
      if (tangent > 1.0) {
        t.surface_offset_m -= cell.feedback_N / tangent;
      }
    }
  }
  out.unchanged_at_rest = standing == cell_.size();
  out.contact_cells = contacts;
}

}  // namespace mrskin::bridge::detail
