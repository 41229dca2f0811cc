#include "mrskin/driver/model/observer.hpp"

#include <algorithm>
#include <cmath>
#include <string>
#include <vector>

#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/model/coil.hpp"

namespace mrskin::model {

namespace {

struct Entry {
  std::size_t index = 0;  // cell (in a sensor's row) or sensor (in a cell's column)
  double weight = 0.0;    // already divided by the sensor's standard deviation
};

}  // namespace

struct CellObserver::Impl {
  Impl(const DeviceModel& m, const ObserverOptions& o)
      : model(m), options(o), network(m, network_options(o)) {
    const DeviceProfile& p = m.profile();
    const GridLayout& grid = m.layout();
    const std::size_t cells = grid.fluid_cell_count();
    if (!(o.prior_spread_m > 0.0) || !(o.sparsity_scale_m > 0.0) || o.sweeps < 1 ||
        !(o.rate_filter_time_constant_s >= 0.0) || !(o.contact_threshold_m >= 0.0)) {
      throw InvalidArgument(
          "observer options: prior_spread_m and sparsity_scale_m must be > 0, sweeps >= 1, "
          "rate_filter_time_constant_s >= 0");
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
    prior_weight = 1.0 / (o.prior_spread_m * o.prior_spread_m);
    // One sensor sigma of misfit (cost 1) per sparsity_scale_m of summed depth.
    l1_weight = 1.0 / o.sparsity_scale_m;
    residual.assign(rows.size(), 0.0);
    depth_m.assign(cells, 0.0);
    contact_depth_m.assign(cells, 0.0);
    previous_m.assign(cells, 0.0);
    predicted_m.assign(cells, 0.0);
    velocity.assign(cells, 0.0);
    coil.resize(grid.valve_count());
    yield_Pa.assign(grid.valve_count(), 0.0);
    valve_gain.assign(grid.valve_count(), 1.0);
  }

  static NetworkOptions network_options(const ObserverOptions& o) {
    NetworkOptions n;
    n.stepper = o.force_stepper;
    return n;
  }

  void reset() noexcept {
    std::fill(depth_m.begin(), depth_m.end(), 0.0);
    std::fill(previous_m.begin(), previous_m.end(), 0.0);
    std::fill(velocity.begin(), velocity.end(), 0.0);
    std::fill(coil.begin(), coil.end(), CoilState{});
    std::fill(yield_Pa.begin(), yield_Pa.end(), 0.0);
    network.reset();
    misfit_m = 0.0;
  }

  const DeviceModel& model;
  ObserverOptions options;
  NetworkSimulation network;
  std::vector<std::size_t> sensor_of_row;  // row -> index in the reading span
  std::vector<double> sensor_scale;        // 1 / sigma per row
  std::vector<std::size_t> row_begin;
  std::vector<Entry> row_entries;
  std::vector<std::size_t> col_begin;
  std::vector<Entry> col_entries;
  std::vector<double> column_norm2;
  std::vector<double> residual;  // scaled: (H d - y) / sigma
  std::vector<double> depth_m;
  std::vector<double> contact_depth_m;  // depth_m with sub-threshold depths as no contact
  std::vector<double> previous_m;
  std::vector<double> predicted_m;
  std::vector<double> velocity;
  std::vector<CoilState> coil;
  std::vector<double> yield_Pa;
  std::vector<double> valve_gain;  // calibrated true / nominal yield stress per valve
  double prior_weight = 0.0;
  double l1_weight = 0.0;
  double misfit_m = 0.0;
};

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
  for (std::size_t r = 0; r < m.residual.size(); ++r) {
    double h_d = 0.0;
    for (std::size_t e = m.row_begin[r]; e < m.row_begin[r + 1]; ++e) {
      h_d += m.row_entries[e].weight * m.depth_m[m.row_entries[e].index];
    }
    m.residual[r] = h_d - sensor_readings[m.sensor_of_row[r]] * m.sensor_scale[r];
  }
  // Projected coordinate descent on 1/2 |r|^2 + 1/2 w_p |d - d_pred|^2 + w_1 sum d, d >= 0.
  for (int sweep = 0; sweep < m.options.sweeps; ++sweep) {
    for (std::size_t c = 0; c < cells; ++c) {
      double gradient = m.prior_weight * (m.depth_m[c] - m.predicted_m[c]) + m.l1_weight;
      for (std::size_t e = m.col_begin[c]; e < m.col_begin[c + 1]; ++e) {
        gradient += m.col_entries[e].weight * m.residual[m.col_entries[e].index];
      }
      const double next = std::max(0.0, m.depth_m[c] - gradient / (m.column_norm2[c] + m.prior_weight));
      const double delta = next - m.depth_m[c];
      if (delta != 0.0) {
        for (std::size_t e = m.col_begin[c]; e < m.col_begin[c + 1]; ++e) {
          m.residual[m.col_entries[e].index] += m.col_entries[e].weight * delta;
        }
        m.depth_m[c] = next;
      }
    }
  }
  double misfit2 = 0.0;
  for (std::size_t r = 0; r < m.residual.size(); ++r) {
    const double unscaled = m.residual[r] / m.sensor_scale[r];
    misfit2 += unscaled * unscaled;
  }
  m.misfit_m = std::sqrt(misfit2 / static_cast<double>(m.residual.size()));
  // Rate: first-order filter on the difference (exact discretisation of the lag).
  const double tau = m.options.rate_filter_time_constant_s;
  const double alpha = tau > 0.0 ? 1.0 - std::exp(-dt_s / tau) : 1.0;
  for (std::size_t c = 0; c < cells; ++c) {
    const double raw = (m.depth_m[c] - m.previous_m[c]) / dt_s;
    m.velocity[c] += alpha * (raw - m.velocity[c]);
  }
  // Force through the nominal network: nominal coil lag and yield curve.
  const CoilParams& coil_params = p.coil;
  for (std::size_t v = 0; v < m.coil.size(); ++v) {
    const double command = std::clamp(valve_current_A[v], 0.0, coil_params.max_current_A);
    const Result<CoilState> next = coil_step(coil_params, m.coil[v], command, dt_s);
    if (next.ok()) {
      m.coil[v] = next.value;
    }
    const double field_A = std::clamp(m.coil[v].field_current_A, 0.0, coil_params.max_current_A);
    const Result<double> tau_y = m.model.yield_stress_at_current_Pa(field_A);
    m.yield_Pa[v] = tau_y.ok() ? tau_y.value * m.valve_gain[v] : m.yield_Pa[v];
  }
  Status s = m.network.set_valve_yield_stress_Pa(m.yield_Pa);
  if (s == Status::ok) {
    for (std::size_t c = 0; c < cells; ++c) {
      m.contact_depth_m[c] = m.depth_m[c] > m.options.contact_threshold_m ? m.depth_m[c] : 0.0;
    }
    s = m.network.set_cell_indentation_m(m.contact_depth_m);
  }
  if (s != Status::ok) {
    return s;
  }
  const Result<StepReport> stepped = m.network.step(dt_s);
  return stepped.status;
}

std::span<const double> CellObserver::indentation_m() const noexcept { return impl_->depth_m; }
std::span<const double> CellObserver::velocity_m_per_s() const noexcept { return impl_->velocity; }
std::span<const double> CellObserver::force_N() const noexcept { return impl_->network.cell_force_N(); }
double CellObserver::sensor_misfit_m() const noexcept { return impl_->misfit_m; }
std::size_t CellObserver::fluid_cell_count() const noexcept { return impl_->depth_m.size(); }

}  // namespace mrskin::model
