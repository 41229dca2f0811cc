// CellObserver's private parts, shared by its sources (only they include this header): the
// options' check, the constants and the state behind CellObserver (Impl). observer.cpp fits the
// depths, tracks the rates and coils and runs the local force model; observer_network.cpp steps
// the network force model.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "inverse_impl.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/model/coil.hpp"
#include "mrskin/driver/model/magnetic.hpp"
#include "mrskin/driver/model/observer.hpp"
#include "rate_tracker.hpp"

namespace mrskin::model::observer_detail {

struct Entry {
  std::size_t index = 0;  // cell (in a sensor's row) or sensor (in a cell's column)
  double weight = 0.0;    // already divided by the sensor's standard deviation
};

// The options, checked: InvalidArgument naming what is wrong (observer.cpp).
__attribute__((visibility("hidden"))) const ObserverOptions& validated(const ObserverOptions& o);
// Every value finite (observer.cpp).
__attribute__((visibility("hidden"))) bool all_finite(std::span<const double> values) noexcept;
__attribute__((visibility("hidden"))) void used_rows_residuals(
    std::size_t rows, const double* __restrict readings, const double* __restrict scale,
    const double* __restrict used, const double* __restrict residual, double* __restrict out) noexcept;

inline ObserverForceModel resolved_force_model(const ObserverOptions& o, std::size_t cells) noexcept {
  if (o.force_model != ObserverForceModel::automatic) {
    return o.force_model;
  }
  return cells <= o.network_max_cells ? ObserverForceModel::network : ObserverForceModel::local;
}

inline constexpr std::uint32_t kNoMark = 0;
inline constexpr double kSettledFlow_m3_per_s = 1e-13;  // 0.1 nL/s: nothing left to relax
// Untouched, on unchanged inputs, the network takes a step of several ticks at once while its
// largest link moves at most this volume in the ticks the step runs ahead (1 nL: 0.04 um of
// membrane over a 5x5 cell; the settled test above is the same volume over 10 s) ...
inline constexpr double kAheadVolume_m3 = 1e-12;
// ... and at most this many ticks (a released skin's flow decays about as 1/t^2: its own time
// scale is the time since the release, seconds).
inline constexpr int kMaxAheadTicks = 64;
// network_step_s: a step spread over at most this many ticks.
inline constexpr int kMaxSpreadTicks = 64;

}  // namespace mrskin::model::observer_detail

namespace mrskin::model {

using namespace observer_detail;

struct __attribute__((visibility("hidden"))) CellObserver::Impl {
  Impl(const DeviceModel& m, const ObserverOptions& o)
      : model(m), options(validated(o)), force_model(resolved_force_model(o, m.layout().fluid_cell_count())) {
    const DeviceProfile& p = m.profile();
    const GridLayout& grid = m.layout();
    const std::size_t cells = grid.fluid_cell_count();
    if (force_model == ObserverForceModel::network) {
      network = std::make_unique<NetworkSimulation>(m, network_options(o));
    } else {
      try {
        valve_law = std::make_unique<inverse_detail::InverseTopology>(m, InverseOptions{});
      } catch (const InvalidArgument&) {
        // A graph the inverse refuses (a branch on two coils): the exact law, a cell at a time.
      }
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
    rows_are_sensors = sensor_of_row.size() == p.sensors.size();
    for (std::size_t r = 0; r < sensor_of_row.size() && rows_are_sensors; ++r) {
      rows_are_sensors = sensor_of_row[r] == r;
    }
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
    step_depth_m.assign(cells, 0.0);
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
    gain_m3.assign(cells, 0.0);
    last_force.assign(cells, 0.0);
    if (network) {
      outflow.assign(cells, 0.0);
    }
    visit.reserve(cells);
    next_visit.reserve(cells);
    mark.assign(cells, 0);
  }

  static NetworkOptions network_options(const ObserverOptions& o) {
    NetworkOptions n;
    n.stepper = o.force_stepper;
    n.linearisation_tolerance = o.network_linearisation_tolerance;
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
    std::fill(contact_depth_m.begin(), contact_depth_m.end(), 0.0);
    std::fill(step_depth_m.begin(), step_depth_m.end(), 0.0);
    network_contact = false;
    force_zero = true;
    state_age_s = 0.0;
    std::fill(gain_m3.begin(), gain_m3.end(), 0.0);
    gain_moved = false;
    std::fill(last_force.begin(), last_force.end(), 0.0);
    std::fill(outflow.begin(), outflow.end(), 0.0);
    if (network) {
      network->reset();
    }
    network_primed = false;
    network_ahead_s = 0.0;
    network_flow_m3_per_s = 0.0;
    network_inputs_changed = false;
    step_ticks = 0;
    step_tick = 0;
    step_phases = 0;
    misfit_m = 0.0;
    misfit_pending = false;
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
  // The fractional index at which a non-decreasing table reaches value (clamped to its ends),
  // searched from near_u, a fractional index near the answer (a valve's play moves little a
  // tick): the last entry not above value, as a binary search finds it, in a step or two.
  [[nodiscard]] static double index_of(const std::vector<double>& table, double value,
                                       double near_u) noexcept {
    if (!(value > table.front())) {
      return 0.0;
    }
    if (!(value < table.back())) {
      return static_cast<double>(table.size() - 1);
    }
    // front < value < back: the answer is in [0, size - 2]. Gallop from near_u to a bracket
    // [lo, hi) with table[lo] <= value < table[hi], then search it (a long move costs a log).
    const std::size_t last = table.size() - 1;
    const auto near =
        static_cast<std::size_t>(near_u > 0.0 ? std::min(near_u, static_cast<double>(last - 1)) : 0.0);
    std::size_t lo = near;
    std::size_t hi = near;
    if (table[near] > value) {
      for (std::size_t step = 1; table[lo] > value; step *= 2) {
        hi = lo;
        lo = lo > step ? lo - step : 0;
      }
    } else {
      for (std::size_t step = 1; table[hi] <= value; step *= 2) {
        lo = hi;
        hi = std::min(hi + step, last);
      }
    }
    const auto above = std::upper_bound(table.begin() + static_cast<std::ptrdiff_t>(lo),
                                        table.begin() + static_cast<std::ptrdiff_t>(hi), value);
    const auto k = static_cast<std::size_t>(above - table.begin()) - 1;
    const double span = table[k + 1] - table[k];
    return static_cast<double>(k) + (span > 0.0 ? (value - table[k]) / span : 0.0);
  }
  // Moves a valve's play to the current field_A; returns its (nominal) yield stress.
  double play_to(std::size_t v, double field_A) noexcept {
    double& u = play_index[v];
    const double base_A = at_index(play_base_A, u);
    if (field_A - play_half_width_A > base_A) {
      u = index_of(play_base_A, field_A - play_half_width_A, u);
    } else if (field_A + play_half_width_A < base_A) {
      u = index_of(play_base_A, field_A + play_half_width_A, u);
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
  Status advance_network(double dt_s) noexcept;
  Status recover_network(Status failed, double dt_s, int ticks) noexcept;
  void finish_network_step(int tick, double dt_s) noexcept;
  void network_cell_forces(double dt_s) noexcept;
  std::span<const double> step_depths(double dt_s, int spread) noexcept;
  [[nodiscard]] int step_spread_for(double dt_s) const noexcept;
  void restart_gain() noexcept {
    if (gain_moved) {
      std::fill(gain_m3.begin(), gain_m3.end(), 0.0);
      gain_moved = false;
    }
  }
  void local_force() noexcept;

  const DeviceModel& model;
  ObserverOptions options;
  ObserverForceModel force_model = ObserverForceModel::network;
  std::unique_ptr<NetworkSimulation> network;  // network force model only
  // Local force model only: the inverse's fast law of a cell's valves, each at its own yield
  // stress (CellInverse::valve_pressure_Pa), in place of DeviceModel's nested Newton solves.
  std::unique_ptr<inverse_detail::InverseTopology> valve_law;
  std::vector<std::size_t> sensor_of_row;  // row -> index in the reading span
  std::vector<double> sensor_scale;        // 1 / sigma per row
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
  std::size_t rows_excluded = 0;            // how many
  bool rows_are_sensors = false;            // row r is sensor r, for every sensor (the built-in grids)
  std::vector<double> sensor_residual;      // per sensor: (y - H d) / sigma, base weights
  std::vector<double> residual;             // scaled: (H d - y) / sigma
  std::vector<double> used_reading;         // y / sigma last used per row (large grids: deadband)
  std::vector<unsigned char> row_changed;
  std::vector<double> depth_m;
  std::vector<double> contact_depth_m;  // depth_m with sub-threshold depths as no contact
  std::vector<double> step_depth_m;     // the depths a step spread over ticks is given
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
  std::vector<double> force;     // each cell's force on the finger, N (either model)
  bool network_contact = false;  // network model: a contact depth this tick
  bool force_zero = true;        // network model: every force 0 (skips the law at rest)
  double state_age_s = 0.0;      // network model: this tick's time less its state's
  std::vector<double> gain_m3;   // network model: each cell's flow since its state, m^3
  bool gain_moved = false;
  std::vector<double> last_force;       // network model: forces before the last step
  std::vector<double> outflow;          // network model: each fluid cell's net outflow, m^3/s
  std::vector<std::size_t> visit;       // the fit's cells to visit this sweep...
  std::vector<std::size_t> next_visit;  // ...and next sweep
  std::vector<std::uint32_t> mark;      // generation stamp per cell (dedupes next_visit)
  std::uint32_t generation = 0;
  bool network_primed = false;       // the network has been stepped at least once since reset
  std::size_t network_refusals = 0;  // steps the linearisation refused, since construction
  bool network_settled = false;
  double network_ahead_s = 0.0;        // untouched: how far the network's last step ran ahead of the tick
  double network_flow_m3_per_s = 0.0;  // the largest link flow of the last step
  // The step in phases (network_step_s): whether an input changed since the last step
  // began, the ticks it covers, the ticks it has run and its phases done (0: none in progress).
  bool network_inputs_changed = false;
  int step_ticks = 0;
  int step_spread = 1;     // the ticks its phases are spread over
  double step_dt_s = 0.0;  // the tick length it began at
  int step_tick = 0;
  int step_phases = 0;
  double alpha_dt_s = -1.0;  // the rate filter's coefficient, cached per tick length
  double alpha = 1.0;
  double prior_weight = 0.0;
  double l1_weight = 0.0;
  double misfit_m = 0.0;
  // The last update's misfit is computed from its residual when asked (misfit_m holds it once a
  // sensor's exclusion is about to change that residual).
  bool misfit_pending = false;
  [[nodiscard]] double fit_misfit_m() const noexcept;
  // The fit's residual carried over from the last tick (large grids; see fit()).
  bool residual_current = false;
  std::uint32_t residual_age_ticks = 0;
};

}  // namespace mrskin::model
