#include "mrskin/driver/model/observer.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <string>
#include <vector>

#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/model/coil.hpp"
#include "mrskin/driver/model/magnetic.hpp"
#include "rate_tracker.hpp"

namespace mrskin::model {

namespace {

struct Entry {
  std::size_t index = 0;  // cell (in a sensor's row) or sensor (in a cell's column)
  double weight = 0.0;    // already divided by the sensor's standard deviation
};

const ObserverOptions& validated(const ObserverOptions& o) {
  if (!(o.prior_spread_m > 0.0) || !(o.sparsity_scale_m > 0.0) || o.sweeps < 1 ||
      !(o.rate_filter_time_constant_s >= 0.0) || !(o.contact_threshold_m >= 0.0) ||
      !(o.sweep_tolerance_m >= 0.0) || !(o.hold_rate_m_per_s >= 0.0) || !(o.noise_floor_sigma >= 0.0) ||
      !std::isfinite(o.noise_floor_sigma) || o.residual_refresh_ticks < 1 || !(o.rate_memory_s > 0.0) ||
      !std::isfinite(o.rate_memory_s) || !(o.rate_change_threshold_sigma > 0.0) ||
      !std::isfinite(o.rate_change_threshold_sigma) || !(o.rest_gate_sigma >= 0.0) || o.rest_sweeps < 1 ||
      o.small_grid_sweeps < 1) {
    throw InvalidArgument(
        "observer options: prior_spread_m and sparsity_scale_m must be > 0, sweeps >= 1, "
        "rate_filter_time_constant_s, contact_threshold_m, sweep_tolerance_m, hold_rate_m_per_s and "
        "noise_floor_sigma >= 0, residual_refresh_ticks >= 1, rate_memory_s and "
        "rate_change_threshold_sigma finite and > 0, rest_gate_sigma >= 0, rest_sweeps and small_grid_sweeps "
        ">= 1");
  }
  return o;
}

ObserverForceModel resolved_force_model(const ObserverOptions& o, std::size_t cells) noexcept {
  if (o.force_model != ObserverForceModel::automatic) {
    return o.force_model;
  }
  return cells <= o.network_max_cells ? ObserverForceModel::network : ObserverForceModel::local;
}

}  // namespace

struct __attribute__((visibility("hidden"))) CellObserver::Impl {
  Impl(const DeviceModel& m, const ObserverOptions& o)
      : model(m), options(validated(o)), force_model(resolved_force_model(o, m.layout().fluid_cell_count())) {
    const DeviceProfile& p = m.profile();
    const GridLayout& grid = m.layout();
    const std::size_t cells = grid.fluid_cell_count();
    if (force_model == ObserverForceModel::network) {
      network = std::make_unique<NetworkSimulation>(m, network_options(o));
    }
    std::vector<std::vector<Entry>> rows;
    for (std::size_t k = 0; k < p.sensors.size(); ++k) {
      const SensorSpec& s = p.sensors[k];
      if (s.quantity != SensorQuantity::displacement || s.place == PlaceKind::reservoir) {
        continue;
      }
      // A reading's spread: its noise, or at least the quantisation step's.
      const double sigma = std::max(s.noise_std, s.resolution / std::sqrt(12.0));
      const double inv = 1.0 / std::max(sigma, 1e-9);
      std::vector<Entry> row;
      if (s.place == PlaceKind::fluid_cell) {
        row.push_back({s.index, inv});
      } else {
        const std::vector<std::size_t>& joined = grid.cells_of_valve(s.index);
        for (const std::size_t c : joined) {
          row.push_back({c, inv / static_cast<double>(joined.size())});
        }
      }
      sensor_of_row.push_back(k);
      sensor_scale.push_back(inv);
      rows.push_back(std::move(row));
    }
    if (rows.empty()) {
      throw InvalidArgument(p.origin + ": the observer needs at least one displacement sensor ([sensors])");
    }
    std::vector<std::vector<Entry>> columns(cells);
    row_begin.push_back(0);
    for (std::size_t r = 0; r < rows.size(); ++r) {
      for (const Entry& e : rows[r]) {
        row_entries.push_back(e);
        columns[e.index].push_back({r, e.weight});
      }
      row_begin.push_back(row_entries.size());
    }
    col_begin.push_back(0);
    for (std::size_t c = 0; c < cells; ++c) {
      double diag = 0.0;
      for (const Entry& e : columns[c]) {
        col_entries.push_back(e);
        diag += e.weight * e.weight;
      }
      col_begin.push_back(col_entries.size());
      column_norm2.push_back(diag);
    }
    base_row_entries = row_entries;
    base_col_entries = col_entries;
    base_column_norm2 = column_norm2;
    row_of_sensor.assign(p.sensors.size(), kNoRow);
    for (std::size_t r = 0; r < sensor_of_row.size(); ++r) {
      row_of_sensor[sensor_of_row[r]] = r;
    }
    row_excluded.assign(rows.size(), 0);
    sensor_residual.assign(p.sensors.size(), 0.0);
    prior_weight = 1.0 / (o.prior_spread_m * o.prior_spread_m);
    // One sensor sigma of misfit (cost 1) per sparsity_scale_m of summed depth.
    l1_weight = 1.0 / o.sparsity_scale_m;
    if (cells > o.network_max_cells) {
      // Noise alone must not give a cell depth: at least noise_floor_sigma of the least noisy
      // sensor's standard deviations (sensor_scale is 1 / sigma) per unit of weighted reading.
      const double finest = *std::max_element(sensor_scale.begin(), sensor_scale.end());
      l1_weight = std::max(l1_weight, o.noise_floor_sigma * finest);
    }
    residual.assign(rows.size(), 0.0);
    used_reading.assign(rows.size(), 0.0);
    row_changed.assign(rows.size(), 0);
    depth_m.assign(cells, 0.0);
    contact_depth_m.assign(cells, 0.0);
    previous_m.assign(cells, 0.0);
    predicted_m.assign(cells, 0.0);
    velocity.assign(cells, 0.0);
    if (o.rate_estimator == RateEstimator::segmented_line) {
      rate_tracker = std::make_unique<RateTracker>(
          cells, RateTrackerOptions{.filter_time_constant_s = o.rate_filter_time_constant_s,
                                    .memory_s = o.rate_memory_s,
                                    .change_threshold_sigma = o.rate_change_threshold_sigma});
      set_depth_sigmas();
    }
    coil.resize(grid.valve_count());
    yield_Pa.assign(grid.valve_count(), 0.0);
    valve_gain.assign(grid.valve_count(), 1.0);
    command_A.assign(grid.valve_count(), 0.0);
    input_A.assign(grid.valve_count(), 0.0);
    play_index.assign(grid.valve_count(), 0.0);
    if (o.steel_hysteresis && p.magnetic.steel.coercivity_A_per_m > 0.0) {
      tabulate_play();
    }
    force.assign(cells, 0.0);
    last_force.assign(cells, 0.0);
    if (network) {
      outflow.assign(cells, 0.0);
    }
    visit.reserve(cells);
    next_visit.reserve(cells);
    mark.assign(cells, 0);
    valves_of_cell_begin.push_back(0);
    for (std::size_t c = 0; c < cells; ++c) {
      for (const std::size_t v : grid.valves_of_cell(c)) {
        valves_of_cell.push_back(v);
      }
      valves_of_cell_begin.push_back(valves_of_cell.size());
    }
  }

  static NetworkOptions network_options(const ObserverOptions& o) {
    NetworkOptions n;
    n.stepper = o.force_stepper;
    return n;
  }

  void reset() noexcept {
    std::fill(depth_m.begin(), depth_m.end(), 0.0);
    std::fill(previous_m.begin(), previous_m.end(), 0.0);
    std::fill(used_reading.begin(), used_reading.end(), 0.0);
    std::fill(velocity.begin(), velocity.end(), 0.0);
    if (rate_tracker) {
      rate_tracker->reset();
    }
    std::fill(coil.begin(), coil.end(), CoilState{});
    std::fill(play_index.begin(), play_index.end(), 0.0);
    std::fill(yield_Pa.begin(), yield_Pa.end(), 0.0);
    std::fill(command_A.begin(), command_A.end(), 0.0);
    coils_settled = false;
    std::fill(force.begin(), force.end(), 0.0);
    std::fill(last_force.begin(), last_force.end(), 0.0);
    std::fill(outflow.begin(), outflow.end(), 0.0);
    if (network) {
      network->reset();
    }
    network_primed = false;
    network_ahead_s = 0.0;
    network_flow_m3_per_s = 0.0;
    misfit_m = 0.0;
    residual_current = false;
  }

  // The steel's play operator (magnetic.hpp) in the current domain. The flux, hence the yield,
  // depends on the played field p alone; p moves only when the coil's current leaves the band
  // I_base(p) +- half_width around it (I_base: the current that holds the steel at p without
  // hysteresis, half_width = H_c l_steel / N). Both are tabulated along the rising branch from
  // the virgin state at setup; each valve's state is its fractional index into the tables. Exact
  // for the plant's model, at a table lookup per changed valve.
  void tabulate_play() {
    const DeviceProfile& p = model.profile();
    constexpr std::size_t kSteps = 512;
    play_half_width_A = p.magnetic.steel.coercivity_A_per_m * p.magnetic.steel_path_length_m /
                        static_cast<double>(p.magnetic.turns);
    const double top_A = p.coil.max_current_A + play_half_width_A;
    play_base_A.assign(kSteps + 1, 0.0);
    play_yield_Pa.assign(kSteps + 1, 0.0);
    anhysteretic_Pa.assign(kSteps + 1, 0.0);
    anhysteretic_step_A = p.coil.max_current_A / static_cast<double>(kSteps);
    HysteresisState state{};
    for (std::size_t k = 0; k <= kSteps; ++k) {
      // Along the rising branch the play sits at the band's lower edge: I = I_base(p) + half_width.
      const double current_A = play_half_width_A + static_cast<double>(k) * (top_A - play_half_width_A) /
                                                       static_cast<double>(kSteps);
      const Result<GapField> g = gap_field_hysteretic(p.magnetic, p.fluid, current_A, state);
      play_base_A[k] = current_A - play_half_width_A;
      play_yield_Pa[k] = g.ok() ? g.value.yield_stress_Pa : (k > 0 ? play_yield_Pa[k - 1] : 0.0);
      const Result<double> y = model.yield_stress_at_current_Pa(static_cast<double>(k) * anhysteretic_step_A);
      anhysteretic_Pa[k] = y.ok() ? y.value : (k > 0 ? anhysteretic_Pa[k - 1] : 0.0);
    }
  }
  // Linear interpolation in a table at a fractional index.
  [[nodiscard]] static double at_index(const std::vector<double>& table, double u) noexcept {
    const std::size_t last = table.size() - 1;
    const auto k = std::min(static_cast<std::size_t>(std::max(u, 0.0)), last - 1);
    const double t = std::clamp(u - static_cast<double>(k), 0.0, 1.0);
    return table[k] + t * (table[k + 1] - table[k]);
  }
  // The fractional index at which a non-decreasing table reaches value (clamped to its ends).
  [[nodiscard]] static double index_of(const std::vector<double>& table, double value) noexcept {
    if (!(value > table.front())) {
      return 0.0;
    }
    if (!(value < table.back())) {
      return static_cast<double>(table.size() - 1);
    }
    const auto above = std::upper_bound(table.begin(), table.end(), value);
    const auto k = static_cast<std::size_t>(above - table.begin()) - 1;
    const double span = table[k + 1] - table[k];
    return static_cast<double>(k) + (span > 0.0 ? (value - table[k]) / span : 0.0);
  }
  // Moves a valve's play to the current field_A; returns its (nominal) yield stress.
  double play_to(std::size_t v, double field_A) noexcept {
    double& u = play_index[v];
    const double base_A = at_index(play_base_A, u);
    if (field_A - play_half_width_A > base_A) {
      u = index_of(play_base_A, field_A - play_half_width_A);
    } else if (field_A + play_half_width_A < base_A) {
      u = index_of(play_base_A, field_A + play_half_width_A);
    }
    return at_index(play_yield_Pa, u);
  }

  // Each cell's depth noise as the fit sees it alone (1 / sqrt of its column's weight), m.
  void set_depth_sigmas() noexcept {
    for (std::size_t c = 0; c < column_norm2.size(); ++c) {
      rate_tracker->set_depth_sigma(c, column_norm2[c] > 0.0 ? 1.0 / std::sqrt(column_norm2[c]) : 1.0);
    }
  }
  void fit(std::span<const double> readings) noexcept;
  // Small grids, no depth past the contact threshold last tick: every reading within the rest
  // gate (none: the depths are zero, no fit), the largest within twice it (noise: rest_sweeps
  // sweeps), or not at rest (full: the fit).
  enum class RestFit : unsigned char { none, noise, full };
  RestFit rest_fit(std::span<const double> readings) noexcept;
  void mark_noise_cells() noexcept;
  void prepare_residual(std::span<const double> readings, bool sparse, double deadband) noexcept;
  void compute_sensor_residuals(std::span<const double> readings) noexcept;
  bool update_coils(std::span<const double> valve_current_A, double dt_s) noexcept;
  Status network_force(double dt_s, bool yields_changed) noexcept;
  void local_force() noexcept;

  const DeviceModel& model;
  ObserverOptions options;
  ObserverForceModel force_model = ObserverForceModel::network;
  std::unique_ptr<NetworkSimulation> network;  // network force model only
  std::vector<std::size_t> sensor_of_row;      // row -> index in the reading span
  std::vector<double> sensor_scale;            // 1 / sigma per row
  std::vector<std::size_t> row_begin;
  std::vector<Entry> row_entries;
  std::vector<std::size_t> col_begin;
  std::vector<Entry> col_entries;
  std::vector<double> column_norm2;
  std::vector<Entry> base_row_entries;  // the weights with every sensor in the fit
  std::vector<Entry> base_col_entries;
  std::vector<double> base_column_norm2;
  static constexpr std::size_t kNoRow = static_cast<std::size_t>(-1);
  std::vector<std::size_t> row_of_sensor;   // sensor -> row (kNoRow: not in the fit)
  std::vector<unsigned char> row_excluded;  // a faulty sensor: its weights are zero
  std::vector<double> sensor_residual;      // per sensor: (y - H d) / sigma, base weights
  std::vector<double> residual;             // scaled: (H d - y) / sigma
  std::vector<double> used_reading;         // y / sigma last used per row (large grids: deadband)
  std::vector<unsigned char> row_changed;
  std::vector<double> depth_m;
  std::vector<double> contact_depth_m;  // depth_m with sub-threshold depths as no contact
  std::vector<double> previous_m;
  std::vector<double> predicted_m;
  std::vector<double> velocity;
  std::unique_ptr<RateTracker> rate_tracker;  // RateEstimator::segmented_line only
  std::vector<CoilState> coil;
  CoilDecay coil_decay_step;  // the decays of the last tick length (coil_decay)
  // The steel's hysteresis (a play operator, as in the plant), tabulated by tabulate_play().
  std::vector<double> play_base_A;      // current holding the steel at the k-th play, no hysteresis
  std::vector<double> play_yield_Pa;    // nominal yield stress at the k-th play
  double play_half_width_A = 0.0;       // H_c l_steel / N
  std::vector<double> play_index;       // per valve: fractional index of its play
  std::vector<double> anhysteretic_Pa;  // nominal yield without hysteresis, every anhysteretic_step_A
  double anhysteretic_step_A = 0.0;
  std::vector<double> yield_Pa;
  std::vector<double> valve_gain;  // calibrated true / nominal yield stress per valve
  std::vector<double> command_A;   // last command per valve (a settled coil is not stepped)
  // The currents passed last tick, bit for bit, when no coil moved on them: the same currents
  // again move none, and skip the per-valve pass (2,048 valves on the palm).
  std::vector<double> input_A;
  bool coils_settled = false;
  std::vector<double> force;            // local force model's output, N
  std::vector<double> last_force;       // network model: forces before the last step
  std::vector<double> outflow;          // network model: each fluid cell's net outflow, m^3/s
  std::vector<std::size_t> visit;       // the fit's cells to visit this sweep...
  std::vector<std::size_t> next_visit;  // ...and next sweep
  std::vector<std::uint32_t> mark;      // generation stamp per cell (dedupes next_visit)
  std::uint32_t generation = 0;
  std::vector<std::size_t> valves_of_cell_begin;
  std::vector<std::size_t> valves_of_cell;
  bool network_primed = false;  // the network has been stepped at least once since reset
  bool network_settled = false;
  double network_ahead_s = 0.0;        // untouched: how far the network's last step ran ahead of the tick
  double network_flow_m3_per_s = 0.0;  // the largest link flow of the last step
  double alpha_dt_s = -1.0;            // the rate filter's coefficient, cached per tick length
  double alpha = 1.0;
  double prior_weight = 0.0;
  double l1_weight = 0.0;
  double misfit_m = 0.0;
  // The fit's residual carried over from the last tick (large grids; see fit()).
  bool residual_current = false;
  std::uint32_t residual_age_ticks = 0;
};

namespace {
constexpr std::uint32_t kNoMark = 0;
constexpr double kSettledFlow_m3_per_s = 1e-13;  // 0.1 nL/s: nothing left to relax
// Untouched, on unchanged inputs, the network takes a step of several ticks at once while its
// largest link moves at most this volume in the ticks the step runs ahead (1 nL: 0.04 um of
// membrane over a 5x5 cell; the settled test above is the same volume over 10 s) ...
constexpr double kAheadVolume_m3 = 1e-12;
// ... and at most this many ticks (a released skin's flow decays about as 1/t^2: its own time
// scale is the time since the release, seconds).
constexpr int kMaxAheadTicks = 64;
}  // namespace

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
  for (std::size_t r = 0; r < residual.size(); ++r) {
    if (row_changed[r] == 0) {
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
  for (std::size_t r = 0; r < sensor_of_row.size(); ++r) {
    const std::size_t k = sensor_of_row[r];
    const double y = readings[k] * sensor_scale[r];
    if (row_excluded[r] == 0) {
      // The fit's residual is H d - (the reading it used), with these weights.
      sensor_residual[k] = (y - used_reading[r]) - residual[r];
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

// The whole network, stepped unless its inputs are unchanged and it has settled.
Status CellObserver::Impl::network_force(double dt_s, bool yields_changed) noexcept {
  const std::size_t cells = depth_m.size();
  bool depths_changed = false;
  for (std::size_t c = 0; c < cells; ++c) {
    const double d = depth_m[c] > options.contact_threshold_m ? depth_m[c] : 0.0;
    depths_changed = depths_changed || d != contact_depth_m[c];
    contact_depth_m[c] = d;
  }
  const bool same_inputs = network_primed && !yields_changed && !depths_changed;
  if (options.skip_settled_network && same_inputs && network_settled) {
    return Status::ok;  // at rest on the same inputs: the same forces
  }
  // (Depths unchanged: touched only while a finger holds bitwise still, so the test is rare.)
  const bool untouched = same_inputs && std::all_of(contact_depth_m.begin(), contact_depth_m.end(),
                                                    [](double d) { return d == 0.0; });
  // A released skin's slow tail (docs/bridge.md, "Cost per tick"): untouched, no force depends on
  // it, and the network's last step already ran ahead of this tick.
  if (untouched && network_ahead_s >= 0.5 * dt_s) {
    network_ahead_s -= dt_s;
    return Status::ok;
  }
  int ticks = 1;
  if (options.skip_settled_network && untouched) {
    const double ahead_s = kAheadVolume_m3 / std::max(network_flow_m3_per_s, 1e-300);
    ticks = static_cast<int>(std::clamp(std::floor(ahead_s / dt_s) + 1.0, 1.0, double{kMaxAheadTicks}));
  }
  network_ahead_s = 0.0;
  Status s = network->set_valve_yield_stress_Pa(yield_Pa);
  if (s == Status::ok) {
    s = network->set_cell_indentation_m(contact_depth_m);
  }
  if (s != Status::ok) {
    return s;
  }
  const std::span<const double> f = network->cell_force_N();
  std::copy(f.begin(), f.end(), last_force.begin());
  Result<StepReport> stepped = network->step(dt_s * ticks);
  if (stepped.status != Status::ok && ticks > 1) {
    ticks = 1;  // a step too long for the stepper's linearisation: the tick's own instead
    stepped = network->step(dt_s);
  }
  if (stepped.status != Status::ok) {
    return stepped.status;
  }
  network_ahead_s = (ticks - 1) * dt_s;
  // Settled: no force moved more than a micronewton in the step. (The network double-buffers
  // its state: read the forces again after the step.)
  const std::span<const double> after = network->cell_force_N();
  double moved = 0.0;
  for (std::size_t c = 0; c < cells; ++c) {
    moved = std::max(moved, std::abs(after[c] - last_force[c]));
  }
  // And nothing flows: a released skin still refills with no contact force to show it.
  double flow_m3_per_s = 0.0;
  std::fill(outflow.begin(), outflow.end(), 0.0);
  const std::span<const double> q = network->link_flow_m3_per_s();
  const std::vector<HydraulicLink>& links = model.profile().links;
  for (std::size_t l = 0; l < q.size() && l < links.size(); ++l) {
    flow_m3_per_s = std::max(flow_m3_per_s, std::abs(q[l]));
    if (links[l].a.kind == NodeKind::fluid_cell) {
      outflow[links[l].a.index] += q[l];
    }
    if (links[l].b.kind == NodeKind::fluid_cell) {
      outflow[links[l].b.index] -= q[l];
    }
  }
  network_settled = moved <= 1e-6 && flow_m3_per_s <= kSettledFlow_m3_per_s;
  network_flow_m3_per_s = flow_m3_per_s;
  network_primed = true;
  return Status::ok;
}

// The quasi-static cell law of each contacted cell; no contact, no force, no cost.
void CellObserver::Impl::local_force() noexcept {
  const std::size_t cells = depth_m.size();
  const double hold = options.hold_rate_m_per_s;
  for (std::size_t c = 0; c < cells; ++c) {
    if (!(depth_m[c] > options.contact_threshold_m)) {
      force[c] = 0.0;
      continue;
    }
    double tau = 0.0;
    const std::size_t first = valves_of_cell_begin[c];
    const std::size_t last = valves_of_cell_begin[c + 1];
    for (std::size_t k = first; k < last; ++k) {
      tau += yield_Pa[valves_of_cell[k]];
    }
    tau = last > first ? tau / static_cast<double>(last - first) : 0.0;
    const double v = velocity[c];
    const double rate = v > hold ? v - hold : (v < -hold ? v + hold : 0.0);
    const Result<CellLoad> load = model.cell_force_at_yield(c, depth_m[c], rate, tau);
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
  for (const double y : sensor_readings) {
    if (!std::isfinite(y)) {
      return Status::not_finite;
    }
  }
  for (const double i : valve_current_A) {
    if (!std::isfinite(i)) {
      return Status::not_finite;
    }
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
  double misfit2 = 0.0;
  std::size_t used = 0;
  for (std::size_t r = 0; r < m.residual.size(); ++r) {
    if (m.row_excluded[r] == 0) {
      const double unscaled = m.residual[r] / m.sensor_scale[r];
      misfit2 += unscaled * unscaled;
      ++used;
    }
  }
  m.misfit_m = used > 0 ? std::sqrt(misfit2 / static_cast<double>(used)) : 0.0;
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
  return m.network_force(dt_s, yields_changed);
}

std::span<const double> CellObserver::indentation_m() const noexcept { return impl_->depth_m; }
std::span<const double> CellObserver::velocity_m_per_s() const noexcept { return impl_->velocity; }
std::span<const double> CellObserver::force_N() const noexcept {
  return impl_->network ? impl_->network->cell_force_N() : std::span<const double>(impl_->force);
}
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
  const double wanted_u = Impl::index_of(m.play_yield_Pa, wanted_Pa);
  const double u = m.play_index[valve];
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
double CellObserver::sensor_misfit_m() const noexcept { return impl_->misfit_m; }
std::span<const double> CellObserver::sensor_residual_sigma() const noexcept {
  return impl_->sensor_residual;
}

Status CellObserver::set_sensor_excluded(std::size_t sensor, bool excluded) noexcept {
  Impl& m = *impl_;
  if (sensor >= m.row_of_sensor.size() || m.row_of_sensor[sensor] == Impl::kNoRow) {
    return Status::out_of_range;
  }
  const std::size_t r = m.row_of_sensor[sensor];
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
