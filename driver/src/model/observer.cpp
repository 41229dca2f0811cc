#include "mrskin/driver/model/observer.hpp"

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <string>
#include <vector>

#include "mrskin/driver/errors.hpp"
#include "observer_impl.hpp"

namespace mrskin::model {

namespace observer_detail {

// compute_sensor_residuals' rows where row r is sensor r: the fit's residual is H d - (the
// reading it used), with these weights. Restrict parameters: g++ then vectorises the loop.
void used_rows_residuals(std::size_t rows, const double* __restrict readings, const double* __restrict scale,
                         const double* __restrict used, const double* __restrict residual,
                         double* __restrict out) noexcept {
  for (std::size_t r = 0; r < rows; ++r) {
    out[r] = (readings[r] * scale[r] - used[r]) - residual[r];
  }
}

// x - x is +0 (no bit set) for a finite x and NaN otherwise: OR-ing the bits tells without a
// branch, and g++ vectorises it (2,048 readings and as many currents on the palm each tick).
bool all_finite(std::span<const double> values) noexcept {
  std::uint64_t bits = 0;
  for (const double v : values) {
    bits |= std::bit_cast<std::uint64_t>(v - v);
  }
  return bits == 0;
}

const ObserverOptions& validated(const ObserverOptions& o) {
  if (!(o.prior_spread_m > 0.0) || !(o.sparsity_scale_m > 0.0) || o.sweeps < 1 ||
      !(o.rate_filter_time_constant_s >= 0.0) || !(o.contact_threshold_m >= 0.0) ||
      !(o.sweep_tolerance_m >= 0.0) || !(o.hold_rate_m_per_s >= 0.0) || !(o.noise_floor_sigma >= 0.0) ||
      !std::isfinite(o.noise_floor_sigma) || o.residual_refresh_ticks < 1 || !(o.rate_memory_s > 0.0) ||
      !std::isfinite(o.rate_memory_s) || !(o.rate_change_threshold_sigma > 0.0) ||
      !std::isfinite(o.rate_change_threshold_sigma) || !(o.rest_gate_sigma >= 0.0) || o.rest_sweeps < 1 ||
      o.small_grid_sweeps < 1 || !(o.network_step_s >= 0.0 && o.network_step_s <= 1.0) ||
      !(o.network_linearisation_tolerance > 0.0) || !std::isfinite(o.network_linearisation_tolerance)) {
    throw InvalidArgument(
        "observer options: prior_spread_m and sparsity_scale_m must be > 0, sweeps >= 1, "
        "rate_filter_time_constant_s, contact_threshold_m, sweep_tolerance_m, hold_rate_m_per_s and "
        "noise_floor_sigma >= 0, residual_refresh_ticks >= 1, rate_memory_s and "
        "rate_change_threshold_sigma finite and > 0, rest_gate_sigma >= 0, rest_sweeps and small_grid_sweeps "
        ">= 1, network_step_s in [0, 1], network_linearisation_tolerance finite and > 0");
  }
  return o;
}

}  // namespace observer_detail

// The rows' readings for this fit (which changed: row_changed) and the residual H d - used
// reading at the prior's depths.
void CellObserver::Impl::prepare_residual(std::span<const double> readings, bool sparse,
                                          double deadband) noexcept {
  // Large grids carry the residual (H d - used reading) over from the last fit, updated by the
  // prior's moves and the readings that changed, instead of H d again for every row (computed
  // afresh every ObserverOptions::residual_refresh_ticks, and after a reset or an exclusion).
  const std::size_t cells = depth_m.size();
  const bool carry = sparse && residual_current && residual_age_ticks + 1 < options.residual_refresh_ticks;
  if (carry) {
    ++residual_age_ticks;
    for (std::size_t c = 0; c < cells; ++c) {
      const double moved = depth_m[c] - previous_m[c];  // the prior's step from the last fit
      if (moved != 0.0) {
        for (std::size_t e = col_begin[c]; e < col_begin[c + 1]; ++e) {
          residual[col_entries[e].index] += col_entries[e].weight * moved;
        }
      }
    }
    for (std::size_t r = 0; r < residual.size(); ++r) {
      const double y = readings[sensor_of_row[r]] * sensor_scale[r];  // in sigmas
      const bool changed = std::abs(y - used_reading[r]) > deadband;
      row_changed[r] = changed ? 1 : 0;
      if (changed) {
        residual[r] += used_reading[r] - y;
        used_reading[r] = y;
      }
    }
  } else {
    for (std::size_t r = 0; r < residual.size(); ++r) {
      const double y = readings[sensor_of_row[r]] * sensor_scale[r];  // in sigmas
      row_changed[r] = !sparse || std::abs(y - used_reading[r]) > deadband ? 1 : 0;
      if (row_changed[r] != 0) {
        used_reading[r] = y;
      }
      double h_d = 0.0;
      for (std::size_t e = row_begin[r]; e < row_begin[r + 1]; ++e) {
        h_d += row_entries[e].weight * depth_m[row_entries[e].index];
      }
      residual[r] = h_d - used_reading[r];
    }
    residual_current = sparse;
    residual_age_ticks = 0;
  }
}

// Small grids: no depth was above the contact threshold last tick and no reading is further
// from zero than rest_gate_sigma standard deviations. The depths are zero and the fit is
// skipped: noise alone would spread micrometres of depth over a few cells and relax them for up
// to `sweeps` sweeps a tick. The residual is then the readings' (H 0 - y). Past the gate but
// within twice it (noise, about 8 % of the 5x5's idle ticks; a touch reads far above), the fit
// sweeps rest_sweeps times: the twelve went on the null space's slow convergence.
CellObserver::Impl::RestFit CellObserver::Impl::rest_fit(std::span<const double> readings) noexcept {
  const double gate = options.rest_gate_sigma;
  if (!(gate > 0.0)) {
    return RestFit::full;
  }
  for (const double d : previous_m) {
    if (d > options.contact_threshold_m) {
      return RestFit::full;
    }
  }
  // used_reading is written as it is tested: a small grid's prepare_residual writes it again.
  double largest = 0.0;
  for (std::size_t r = 0; r < residual.size(); ++r) {
    const double y = readings[sensor_of_row[r]] * sensor_scale[r];  // in sigmas
    largest = row_excluded[r] == 0 ? std::max(largest, std::abs(y)) : largest;
    used_reading[r] = y;
    residual[r] = -y;
  }
  if (largest > gate) {
    return largest <= 2.0 * gate ? RestFit::noise : RestFit::full;
  }
  // The prior may have moved a depth by a decaying rate: at rest it is zero.
  std::fill(depth_m.begin(), depth_m.end(), 0.0);
  return RestFit::none;
}

// Noise past the rest gate: only the cells under a reading past the gate, and those the prior
// gives depth, are relaxed; the others stay at zero, as the gate leaves them, since all their
// sensors read within it. rest_fit left the residual at zero depth: the prior's depths are added
// to it. The cells to relax are marked with this generation.
void CellObserver::Impl::mark_noise_cells() noexcept {
  const std::size_t cells = depth_m.size();
  for (std::size_t c = 0; c < cells; ++c) {
    if (depth_m[c] > 0.0) {
      for (std::size_t e = col_begin[c]; e < col_begin[c + 1]; ++e) {
        residual[col_entries[e].index] += col_entries[e].weight * depth_m[c];
      }
      mark[c] = generation;
    }
  }
  for (std::size_t r = 0; r < residual.size(); ++r) {
    if (row_excluded[r] != 0 || !(std::abs(used_reading[r]) > options.rest_gate_sigma)) {
      continue;
    }
    for (std::size_t k = row_begin[r]; k < row_begin[r + 1]; ++k) {
      mark[row_entries[k].index] = generation;
    }
  }
}

// Projected coordinate descent on 1/2 |r|^2 + 1/2 w_p |d - d_pred|^2 + w_1 sum d, d >= 0. A
// cell is revisited only when a sensor it shares changed (a cell whose gradient has not changed
// would not move).
void CellObserver::Impl::fit(std::span<const double> readings) noexcept {
  const std::size_t cells = depth_m.size();
  // Small grids sweep every cell (cheaper than tracking which to visit); large grids revisit
  // only the neighbours of what moved, and a reading within reading_deadband_sigma of the one
  // last used counts as unchanged (noise on an untouched region moves nothing).
  const bool sparse = cells > options.network_max_cells;
  const RestFit rest = sparse ? RestFit::full : rest_fit(readings);
  if (rest == RestFit::none) {
    return;
  }
  const int small_grid = std::min(options.sweeps, options.small_grid_sweeps);
  const int max_sweeps = rest == RestFit::noise ? std::min(small_grid, options.rest_sweeps) : small_grid;
  const double deadband = sparse ? options.reading_deadband_sigma : 0.0;
  if (rest != RestFit::noise) {
    prepare_residual(readings, sparse, deadband);  // (noise: rest_fit left the residual at d = 0)
  }
  const double tolerance = options.sweep_tolerance_m;
  double largest = 0.0;
  auto relax = [&](std::size_t c) {
    double gradient = prior_weight * (depth_m[c] - predicted_m[c]) + l1_weight;
    for (std::size_t e = col_begin[c]; e < col_begin[c + 1]; ++e) {
      gradient += col_entries[e].weight * residual[col_entries[e].index];
    }
    const double next = std::max(0.0, depth_m[c] - gradient / (column_norm2[c] + prior_weight));
    const double delta = next - depth_m[c];
    if (delta == 0.0) {
      return;
    }
    for (std::size_t e = col_begin[c]; e < col_begin[c + 1]; ++e) {
      residual[col_entries[e].index] += col_entries[e].weight * delta;
    }
    depth_m[c] = next;
    largest = std::max(largest, std::abs(delta));
    if (!sparse || std::abs(delta) <= tolerance) {
      return;
    }
    // Its sensors' cells see a new residual: visit them next sweep.
    for (std::size_t e = col_begin[c]; e < col_begin[c + 1]; ++e) {
      const std::size_t r = col_entries[e].index;
      for (std::size_t k = row_begin[r]; k < row_begin[r + 1]; ++k) {
        const std::size_t n = row_entries[k].index;
        if (mark[n] != generation) {
          mark[n] = generation;
          next_visit.push_back(n);
        }
      }
    }
  };
  auto next_generation = [&] {
    if (++generation == kNoMark) {  // wrapped: clear the stamps
      std::fill(mark.begin(), mark.end(), kNoMark);
      generation = 1;
    }
  };
  next_generation();
  next_visit.clear();
  if (rest == RestFit::noise) {
    mark_noise_cells();
    for (int sweep = 0; sweep < max_sweeps && (sweep == 0 || largest > tolerance); ++sweep) {
      largest = 0.0;
      for (std::size_t c = 0; c < cells; ++c) {
        if (mark[c] == generation) {
          relax(c);
        }
      }
    }
    return;
  }
  if (!sparse) {
    for (int sweep = 0; sweep < max_sweeps && (sweep == 0 || largest > tolerance); ++sweep) {
      largest = 0.0;
      for (std::size_t c = 0; c < cells; ++c) {
        relax(c);
      }
    }
    return;
  }
  // First sweep: the cells with depth (their prior moves) and those whose sensors changed.
  for (std::size_t c = 0; c < cells; ++c) {
    if (depth_m[c] > 0.0 || previous_m[c] > 0.0) {
      mark[c] = generation;
      next_visit.push_back(c);
    }
  }
  // A changed row read within the rest gate moves none of its cells at zero depth (the small
  // grids' rest gate, row by row): those with depth are visited above, the others stay at zero.
  const double gate = options.rest_gate_sigma > 0.0 ? options.rest_gate_sigma : -1.0;
  for (std::size_t r = 0; r < residual.size(); ++r) {
    if (row_changed[r] == 0 || std::abs(used_reading[r]) <= gate) {
      continue;
    }
    for (std::size_t k = row_begin[r]; k < row_begin[r + 1]; ++k) {
      const std::size_t n = row_entries[k].index;
      if (mark[n] != generation) {
        mark[n] = generation;
        next_visit.push_back(n);
      }
    }
  }
  for (int sweep = 0; sweep < options.sweeps && !next_visit.empty(); ++sweep) {
    visit.swap(next_visit);
    next_visit.clear();
    next_generation();
    for (const std::size_t c : visit) {
      relax(c);
    }
  }
}

// Every displacement sensor's misfit against the fitted depths with its full weights, so an
// excluded sensor stays watched (a fault that clears shows).
void CellObserver::Impl::compute_sensor_residuals(std::span<const double> readings) noexcept {
  if (rows_are_sensors) {
    // Row r is sensor r (the built-in grids): every row in one pass that g++ vectorises, then
    // the excluded rows afresh below.
    used_rows_residuals(residual.size(), readings.data(), sensor_scale.data(), used_reading.data(),
                        residual.data(), sensor_residual.data());
    if (rows_excluded == 0) {
      return;
    }
  }
  for (std::size_t r = 0; r < sensor_of_row.size(); ++r) {
    const std::size_t k = sensor_of_row[r];
    const double y = readings[k] * sensor_scale[r];
    if (row_excluded[r] == 0) {
      if (!rows_are_sensors) {
        // The fit's residual is H d - (the reading it used), with these weights.
        sensor_residual[k] = (y - used_reading[r]) - residual[r];
      }
      continue;
    }
    double h_d = 0.0;
    for (std::size_t e = row_begin[r]; e < row_begin[r + 1]; ++e) {
      h_d += base_row_entries[e].weight * depth_m[base_row_entries[e].index];
    }
    sensor_residual[k] = y - h_d;
  }
}

// Nominal coil lag and yield curve per valve; a valve whose command has not changed and whose
// coil has settled on it is not stepped. Returns whether any yield stress changed.
bool CellObserver::Impl::update_coils(std::span<const double> valve_current_A, double dt_s) noexcept {
  const CoilParams& coil_params = model.profile().coil;
  const double settled_A = 1e-12 * coil_params.max_current_A;
  const std::size_t bytes = coil.size() * sizeof(double);
  if (coils_settled && std::memcmp(valve_current_A.data(), input_A.data(), bytes) == 0) {
    return false;  // what the pass below does then: every valve settled on its command
  }
  bool changed = false;
  std::size_t unmoved = 0;
  for (std::size_t v = 0; v < coil.size(); ++v) {
    const double command = std::clamp(valve_current_A[v], 0.0, coil_params.max_current_A);
    CoilState& state = coil[v];
    if (command == command_A[v] && std::abs(state.current_A - command) <= settled_A &&
        std::abs(state.field_current_A - command) <= settled_A) {
      ++unmoved;
      continue;
    }
    command_A[v] = command;
    if (coil_decay_step.dt_s != dt_s) {
      coil_decay_step = coil_decay(coil_params, dt_s);  // two exponentials per tick length, not per coil
    }
    const Result<CoilState> next = coil_step(coil_params, state, command, coil_decay_step);
    if (next.ok()) {
      state = next.value;
    }
    const double field_A = std::clamp(state.field_current_A, 0.0, coil_params.max_current_A);
    double y = yield_Pa[v];
    if (!play_base_A.empty()) {
      // The steel's hysteresis, as the plant has it: after any current the valve keeps a
      // remanent yield at 0 A (about 1 Pa on the 5 x 5, where a press is held from 3-6 Pa).
      y = play_to(v, field_A) * valve_gain[v];
    } else {
      const Result<double> tau_y = model.yield_stress_at_current_Pa(field_A);
      y = tau_y.ok() ? tau_y.value * valve_gain[v] : y;
    }
    changed = changed || y != yield_Pa[v];
    yield_Pa[v] = y;
  }
  // Every coil settled on these currents: the same currents next tick would move none either.
  coils_settled = unmoved == coil.size();
  if (coils_settled) {
    std::memcpy(input_A.data(), valve_current_A.data(), bytes);
  }
  return changed;
}

// The quasi-static cell law of each contacted cell; no contact, no force, no cost.
void CellObserver::Impl::local_force() noexcept {
  const std::size_t cells = depth_m.size();
  const double hold = options.hold_rate_m_per_s;
  const inverse_detail::InverseTopology* const law = valve_law.get();
  const double area_m2 = model.contact().effective_area_m2;
  for (std::size_t c = 0; c < cells; ++c) {
    if (!(depth_m[c] > options.contact_threshold_m)) {
      force[c] = 0.0;
      continue;
    }
    const double v = velocity[c];
    const double rate = v > hold ? v - hold : (v < -hold ? v + hold : 0.0);
    // Each valve at its own yield: at rest the cell holds up to its weakest valve, so a current
    // on a valve it shares with a pressed neighbour is not its force unless every valve of it is
    // on (docs/bridge.md, "Phantoms that spread through shared valves").
    const double flow_m3_per_s = std::fabs(area_m2 * rate);
    Result<double> valve_pressure_Pa;
    if (law != nullptr) {
      // The valves' pressure by the inverse's tables, not DeviceModel's nested Newton solves
      // (9k instructions a flowing cell on the palm; docs/bridge.md, "The local force by tables").
      const double yield_k = law->yield_k;
      const double* const yield = yield_Pa.data();
      valve_pressure_Pa.value = law->forward(
          c, flow_m3_per_s, [yield_k, yield](std::size_t valve) { return yield_k * yield[valve]; });
    } else {
      valve_pressure_Pa = model.valve_network_pressure_Pa(c, flow_m3_per_s, yield_Pa);
    }
    const Result<CellLoad> load = valve_pressure_Pa.ok() ? model.cell_force_at_valve_pressure(
                                                               c, depth_m[c], rate, valve_pressure_Pa.value)
                                                         : failure<CellLoad>(valve_pressure_Pa.status);
    if (load.ok()) {
      force[c] = load.value.force_N;
    }
  }
}

CellObserver::CellObserver(const DeviceModel& nominal, const ObserverOptions& options)
    : impl_(std::make_unique<Impl>(nominal, options)) {}

CellObserver::~CellObserver() = default;

void CellObserver::reset() noexcept { impl_->reset(); }

Status CellObserver::set_valve_yield_gain(std::span<const double> gain) noexcept {
  if (gain.size() != impl_->valve_gain.size()) {
    return Status::out_of_range;
  }
  for (const double g : gain) {
    if (!std::isfinite(g) || !(g > 0.0)) {
      return Status::out_of_range;
    }
  }
  std::copy(gain.begin(), gain.end(), impl_->valve_gain.begin());
  return Status::ok;
}

Status CellObserver::update(std::span<const double> sensor_readings, std::span<const double> valve_current_A,
                            double dt_s) noexcept {
  Impl& m = *impl_;
  const DeviceProfile& p = m.model.profile();
  if (sensor_readings.size() != p.sensors.size() || valve_current_A.size() != m.coil.size() ||
      !(dt_s > 0.0 && dt_s < 1.0)) {
    return Status::out_of_range;
  }
  if (!observer_detail::all_finite(sensor_readings) || !observer_detail::all_finite(valve_current_A)) {
    return Status::not_finite;
  }
  const std::size_t cells = m.depth_m.size();
  // Prior: previous estimate moved by its rate.
  for (std::size_t c = 0; c < cells; ++c) {
    m.previous_m[c] = m.depth_m[c];
    m.predicted_m[c] = std::max(0.0, m.depth_m[c] + m.velocity[c] * dt_s);
    m.depth_m[c] = m.predicted_m[c];
  }
  m.fit(sensor_readings);
  m.compute_sensor_residuals(sensor_readings);
  m.misfit_pending = true;  // nothing in the tick reads it: computed when asked (sensor_misfit_m)
  if (m.rate_tracker) {
    m.rate_tracker->update(m.depth_m, m.previous_m, dt_s, m.velocity);
  } else {
    // Rate: first-order filter on the difference (exact discretisation of the lag).
    if (dt_s != m.alpha_dt_s) {
      const double tau = m.options.rate_filter_time_constant_s;
      m.alpha = tau > 0.0 ? 1.0 - std::exp(-dt_s / tau) : 1.0;
      m.alpha_dt_s = dt_s;
    }
    for (std::size_t c = 0; c < cells; ++c) {
      const double raw = (m.depth_m[c] - m.previous_m[c]) / dt_s;
      m.velocity[c] += m.alpha * (raw - m.velocity[c]);
    }
  }
  // Force: nominal coil lag and yield curve, then the force model.
  const bool yields_changed = m.update_coils(valve_current_A, dt_s);
  if (m.force_model == ObserverForceModel::local) {
    m.local_force();
    return Status::ok;
  }
  const Status s = m.network_force(dt_s, yields_changed);
  if (s == Status::ok) {
    m.network_cell_forces(dt_s);
  }
  return s;
}

std::span<const double> CellObserver::indentation_m() const noexcept { return impl_->depth_m; }
std::span<const double> CellObserver::velocity_m_per_s() const noexcept { return impl_->velocity; }
std::span<const double> CellObserver::force_N() const noexcept { return impl_->force; }
std::span<const double> CellObserver::outflow_m3_per_s() const noexcept { return impl_->outflow; }

double CellObserver::hysteresis_compensated_current_A(std::size_t valve, double current_A) const noexcept {
  const Impl& m = *impl_;
  if (m.play_base_A.empty() || valve >= m.play_index.size() || !(current_A > 0.0)) {
    return current_A;
  }
  // The play that yields what the anhysteretic curve gives at current_A (nominal units: the
  // valve's gain cancels), and the current that moves the valve's play there: the band's upper
  // edge going up, its lower edge going down (0 A at most: the remanence is the floor).
  const double wanted_Pa = Impl::at_index(m.anhysteretic_Pa, current_A / m.anhysteretic_step_A);
  const double u = m.play_index[valve];
  const double wanted_u = Impl::index_of(m.play_yield_Pa, wanted_Pa, u);
  const double wanted_base_A = Impl::at_index(m.play_base_A, wanted_u);
  if (wanted_u > u) {
    return wanted_base_A + m.play_half_width_A;
  }
  if (wanted_u < u) {
    return std::max(0.0, wanted_base_A - m.play_half_width_A);
  }
  const double base_A = Impl::at_index(m.play_base_A, u);
  return std::clamp(current_A, std::max(0.0, base_A - m.play_half_width_A), base_A + m.play_half_width_A);
}
ObserverForceModel CellObserver::force_model() const noexcept { return impl_->force_model; }
std::size_t CellObserver::network_steps_refused() const noexcept { return impl_->network_refusals; }
double CellObserver::sensor_misfit_m() const noexcept {
  return impl_->misfit_pending ? impl_->fit_misfit_m() : impl_->misfit_m;
}

double CellObserver::Impl::fit_misfit_m() const noexcept {
  double misfit2 = 0.0;
  std::size_t used = 0;
  for (std::size_t r = 0; r < residual.size(); ++r) {
    if (row_excluded[r] == 0) {
      const double unscaled = residual[r] / sensor_scale[r];
      misfit2 += unscaled * unscaled;
      ++used;
    }
  }
  return used > 0 ? std::sqrt(misfit2 / static_cast<double>(used)) : 0.0;
}
std::span<const double> CellObserver::sensor_residual_sigma() const noexcept {
  return impl_->sensor_residual;
}

Status CellObserver::set_sensor_excluded(std::size_t sensor, bool excluded) noexcept {
  Impl& m = *impl_;
  if (sensor >= m.row_of_sensor.size() || m.row_of_sensor[sensor] == Impl::kNoRow) {
    return Status::out_of_range;
  }
  const std::size_t r = m.row_of_sensor[sensor];
  if (m.misfit_pending) {  // the last update's misfit, before its residual and rows change
    m.misfit_m = m.fit_misfit_m();
    m.misfit_pending = false;
  }
  m.rows_excluded = m.rows_excluded - (m.row_excluded[r] != 0 ? 1 : 0) + (excluded ? 1 : 0);
  m.row_excluded[r] = excluded ? 1 : 0;
  const double keep = excluded ? 0.0 : 1.0;
  for (std::size_t e = m.row_begin[r]; e < m.row_begin[r + 1]; ++e) {
    m.row_entries[e].weight = keep * m.base_row_entries[e].weight;
  }
  // The columns hold the same weights by cell: zero this row's and sum the norms again.
  for (std::size_t c = 0; c + 1 < m.col_begin.size(); ++c) {
    double norm2 = 0.0;
    for (std::size_t e = m.col_begin[c]; e < m.col_begin[c + 1]; ++e) {
      if (m.col_entries[e].index == r) {
        m.col_entries[e].weight = keep * m.base_col_entries[e].weight;
      }
      norm2 += m.col_entries[e].weight * m.col_entries[e].weight;
    }
    m.column_norm2[c] = norm2;
  }
  if (m.rate_tracker) {
    m.set_depth_sigmas();
  }
  // Its residual must not pull on the depths any more: rebuilt by the next fit.
  m.residual[r] = 0.0;
  m.residual_current = false;
  return Status::ok;
}
std::size_t CellObserver::fluid_cell_count() const noexcept { return impl_->depth_m.size(); }

}  // namespace mrskin::model
