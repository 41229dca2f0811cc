#include "mrskin/driver/model/device_model.hpp"

#include <algorithm>
#include <cmath>
#include <initializer_list>
#include <limits>
#include <string>

#include "mrskin/driver/errors.hpp"

namespace mrskin::model {

namespace {

constexpr int kYieldSegments = 512;
constexpr double kRelTol = 1e-12;
// Absolute floor of the pressure tolerances, Pa: subnormal inputs (1e-320 m^3/s through a
// 1e-321 Pa fluid) still converge instead of chasing relative precision below DBL_MIN.
constexpr double kAbsTol_Pa = 1e-280;
constexpr int kMaxIter = 200;

Result<double> exact_yield_at(const DeviceProfile& p, double current_A) noexcept {
  const Result<GapField> g = gap_field(p.magnetic, p.fluid, current_A);
  return {g.value.yield_stress_Pa, g.status};
}

}  // namespace

DeviceModel::DeviceModel(DeviceProfile profile)
    : profile_(std::move(profile)),
      layout_(profile_.rows, profile_.cols),
      valve_(profile_.valve, profile_.fluid.viscosity_Pa_s, profile_.fluid.density_kg_per_m3) {
  const std::string& origin = profile_.origin;
  const Result<ContactPatch> patch =
      contact_patch(profile_.membrane, profile_.cell_radius_m(), profile_.finger_radius_m);
  if (!patch.ok()) {
    throw InvalidArgument(origin + ": [contact] finger_radius_m: " + to_string(patch.status));
  }
  patch_ = patch.value;

  // Branches: every link touching a fluid cell; through a chamber, the chamber's other links.
  const std::size_t cells = layout_.fluid_cell_count();
  const std::size_t valves = layout_.valve_count();
  std::vector<std::vector<std::uint32_t>> chamber_links(valves);
  link_valve_.reserve(profile_.links.size());
  for (std::size_t i = 0; i < profile_.links.size(); ++i) {
    const HydraulicLink& k = profile_.links[i];
    link_valve_.push_back(k.valve);
    for (const NodeRef n : {k.a, k.b}) {
      if (n.kind == NodeKind::chamber) {
        chamber_links[n.index].push_back(static_cast<std::uint32_t>(i));
      }
    }
  }
  cell_branch_begin_.assign(cells + 1, 0);
  for (std::size_t c = 0; c < cells; ++c) {
    cell_branch_begin_[c] = static_cast<std::uint32_t>(branches_.size());
    for (std::size_t i = 0; i < profile_.links.size(); ++i) {
      const HydraulicLink& k = profile_.links[i];
      const bool a_is = k.a.kind == NodeKind::fluid_cell && k.a.index == c;
      const bool b_is = k.b.kind == NodeKind::fluid_cell && k.b.index == c;
      if (!a_is && !b_is) {
        continue;
      }
      const NodeRef other = a_is ? k.b : k.a;
      Branch b;
      b.inlet = static_cast<std::uint32_t>(i);
      b.out_begin = static_cast<std::uint32_t>(outlets_.size());
      if (other.kind == NodeKind::chamber) {
        for (const std::uint32_t j : chamber_links[other.index]) {
          if (j != i) {
            outlets_.push_back(j);
          }
        }
        if (outlets_.size() == b.out_begin) {
          throw InvalidArgument(origin + ": [hydraulics] the chamber of valve " +
                                std::to_string(other.index) +
                                " is a dead end (one link only): flow into it could never leave");
        }
      }
      b.out_end = static_cast<std::uint32_t>(outlets_.size());
      branches_.push_back(b);
    }
  }
  cell_branch_begin_[cells] = static_cast<std::uint32_t>(branches_.size());

  // Yield curve tau_y(I): exact circuit at the nodes, monotone cubic (Fritsch-Carlson) slopes.
  const double imax = profile_.coil.max_current_A;
  table_step_A_ = imax / kYieldSegments;
  table_tau_Pa_.resize(kYieldSegments + 1);
  for (int k = 0; k <= kYieldSegments; ++k) {
    const Result<double> t = exact_yield_at(profile_, table_step_A_ * k);
    if (!t.ok()) {
      throw InvalidArgument(origin + ": [magnetic] the circuit cannot be solved at " +
                            std::to_string(table_step_A_ * k) + " A: " + to_string(t.status));
    }
    table_tau_Pa_[static_cast<std::size_t>(k)] = t.value;
  }
  table_slope_Pa_per_A_.assign(kYieldSegments + 1, 0.0);
  std::vector<double> secant(kYieldSegments);
  for (std::size_t k = 0; k < secant.size(); ++k) {
    secant[k] = (table_tau_Pa_[k + 1] - table_tau_Pa_[k]) / table_step_A_;
  }
  table_slope_Pa_per_A_[0] = secant.front();
  table_slope_Pa_per_A_[kYieldSegments] = secant.back();
  for (std::size_t k = 1; k < secant.size(); ++k) {
    const double a = secant[k - 1];
    const double b = secant[k];
    table_slope_Pa_per_A_[k] = a * b <= 0.0 ? 0.0 : 2.0 * a * b / (a + b);  // harmonic mean: monotone
  }
  for (int k = 0; k < kYieldSegments; ++k) {
    const double i_mid = table_step_A_ * (k + 0.5);
    const double exact = exact_yield_at(profile_, i_mid).value;
    yield_table_error_Pa_ =
        std::max(yield_table_error_Pa_, std::fabs(yield_stress_at_current_Pa(i_mid).value - exact));
  }
}

Result<std::size_t> DeviceModel::fluid_cell_index(int row, int col) const noexcept {
  if (row < 0 || col < 0 || row >= layout_.rows() || col >= layout_.cols() || (row + col) % 2 != 0) {
    return failure<std::size_t>(Status::out_of_range);
  }
  // Fluid cells are numbered row-major over the checkerboard (GridLayout's order).
  const int first_parity_row = (layout_.cols() + 1) / 2;  // fluid cells in an even row
  const int odd_row = layout_.cols() / 2;                 // fluid cells in an odd row
  const int full_pairs = row / 2;
  int index = full_pairs * (first_parity_row + odd_row);
  if (row % 2 == 1) {
    index += first_parity_row;
  }
  index += col / 2;
  return {static_cast<std::size_t>(index)};
}

Result<GapField> DeviceModel::gap_field(double current_A) const noexcept {
  return model::gap_field(profile_.magnetic, profile_.fluid, current_A);
}

Result<double> DeviceModel::yield_stress_at_current_Pa(double current_A) const noexcept {
  if (!std::isfinite(current_A)) {
    return failure<double>(Status::not_finite);
  }
  const double imax = profile_.coil.max_current_A;
  if (current_A < 0.0 || current_A > imax) {
    return failure<double>(Status::out_of_range);
  }
  const double u = current_A / table_step_A_;
  const auto k = static_cast<std::size_t>(std::min(static_cast<int>(u), kYieldSegments - 1));
  const double t = u - static_cast<double>(k);
  const double h = table_step_A_;
  const double y0 = table_tau_Pa_[k];
  const double y1 = table_tau_Pa_[k + 1];
  const double m0 = table_slope_Pa_per_A_[k] * h;
  const double m1 = table_slope_Pa_per_A_[k + 1] * h;
  const double t2 = t * t;
  const double t3 = t2 * t;
  return {(2 * t3 - 3 * t2 + 1) * y0 + (t3 - 2 * t2 + t) * m0 + (-2 * t3 + 3 * t2) * y1 + (t3 - t2) * m1};
}

std::size_t DeviceModel::branch_count(std::size_t cell) const noexcept {
  if (cell >= layout_.fluid_cell_count()) {
    return 0;
  }
  return cell_branch_begin_[cell + 1] - cell_branch_begin_[cell];
}

double DeviceModel::cell_open_drain_time_s() const noexcept {
  const double stiffness_Pa_per_m3 = patch_.bulge_linear_Pa_per_m3;
  const double conductance_m3_per_s_Pa = valve_.newtonian_conductance_m3_per_s_Pa();
  return stiffness_Pa_per_m3 > 0.0 && conductance_m3_per_s_Pa > 0.0
             ? 1.0 / (stiffness_Pa_per_m3 * conductance_m3_per_s_Pa)
             : std::numeric_limits<double>::infinity();
}

// Flow through one branch at cell pressure p (> 0) above the sinks.
template <class TauOf>
Result<FlowPoint> DeviceModel::branch_flow(const Branch& b, double p, const TauOf& tau_of) const noexcept {
  const double tau_in = tau_of(b.inlet);
  if (b.out_begin == b.out_end) {
    return valve_.flow_point(p, tau_in);
  }
  // Chamber pressure pk: Q_in(p - pk) = sum_j Q_j(pk). Left side falls, right side rises in pk.
  // Flow needs pk above the weakest outlet's threshold and p - pk above the inlet's.
  double lo = std::numeric_limits<double>::infinity();
  for (std::uint32_t j = b.out_begin; j < b.out_end; ++j) {
    lo = std::min(lo, valve_.yield_pressure_Pa(tau_of(outlets_[j])));
  }
  double hi = p - valve_.yield_pressure_Pa(tau_in);
  if (!(hi > lo)) {
    return {FlowPoint{0.0, 0.0}};
  }
  double pk = 0.5 * (lo + hi);
  for (int it = 0; it < kMaxIter; ++it) {
    const Result<FlowPoint> in = valve_.flow_point(p - pk, tau_in);
    if (!in.ok()) {
      return failure<FlowPoint>(in.status);
    }
    double out_q = 0.0;
    double out_g = 0.0;
    for (std::uint32_t j = b.out_begin; j < b.out_end; ++j) {
      const Result<FlowPoint> o = valve_.flow_point(pk, tau_of(outlets_[j]));
      if (!o.ok()) {
        return failure<FlowPoint>(o.status);
      }
      out_q += o.value.flow_m3_per_s;
      out_g += o.value.conductance_m3_per_s_Pa;
    }
    const double f = in.value.flow_m3_per_s - out_q;
    if (f > 0.0) {
      lo = pk;
    } else {
      hi = pk;
    }
    const double df = in.value.conductance_m3_per_s_Pa + out_g;
    double next = df > 0.0 ? pk + f / df : 0.5 * (lo + hi);
    const double tol = std::max(kRelTol * p, kAbsTol_Pa);
    const bool converged = f == 0.0 || std::fabs(next - pk) <= tol;
    if (!converged && !(next > lo && next < hi)) {
      next = 0.5 * (lo + hi);
    }
    if (converged || hi - lo <= tol) {
      const double gi = in.value.conductance_m3_per_s_Pa;
      const double series = gi + out_g > 0.0 ? gi * out_g / (gi + out_g) : 0.0;
      return {FlowPoint{0.5 * (in.value.flow_m3_per_s + out_q), series}};
    }
    pk = next;
  }
  return failure<FlowPoint>(Status::no_convergence);
}

template <class TauOf>
Result<double> DeviceModel::network_pressure(std::size_t cell, double flow,
                                             const TauOf& tau_of) const noexcept {
  const std::uint32_t first = cell_branch_begin_[cell];
  const std::uint32_t last = cell_branch_begin_[cell + 1];
  // Breakaway threshold: the weakest branch (inlet threshold + weakest outlet's).
  double threshold = std::numeric_limits<double>::infinity();
  for (std::uint32_t i = first; i < last; ++i) {
    const Branch& b = branches_[i];
    double t = valve_.yield_pressure_Pa(tau_of(b.inlet));
    if (b.out_begin != b.out_end) {
      double weakest = std::numeric_limits<double>::infinity();
      for (std::uint32_t j = b.out_begin; j < b.out_end; ++j) {
        weakest = std::min(weakest, valve_.yield_pressure_Pa(tau_of(outlets_[j])));
      }
      t += weakest;
    }
    threshold = std::min(threshold, t);
  }
  if (flow == 0.0) {
    return {threshold};
  }
  // Upper bound: any one branch carrying all the flow (through one outlet) needs at least p.
  double hi = std::numeric_limits<double>::infinity();
  for (std::uint32_t i = first; i < last; ++i) {
    const Branch& b = branches_[i];
    const Result<double> in = valve_.pressure_exact_Pa(flow, tau_of(b.inlet));
    if (!in.ok()) {
      return in;
    }
    double t = in.value;
    if (b.out_begin != b.out_end) {
      double weakest = std::numeric_limits<double>::infinity();
      for (std::uint32_t j = b.out_begin; j < b.out_end; ++j) {
        const Result<double> o = valve_.pressure_exact_Pa(flow, tau_of(outlets_[j]));
        if (!o.ok()) {
          return o;
        }
        weakest = std::min(weakest, o.value);
      }
      t += weakest;
    }
    hi = std::min(hi, t);
  }
  double lo = threshold;
  double p = hi;  // Newton from the right
  for (int it = 0; it < kMaxIter; ++it) {
    double q = 0.0;
    double g = 0.0;
    for (std::uint32_t i = first; i < last; ++i) {
      const Result<FlowPoint> f = branch_flow(branches_[i], p, tau_of);
      if (!f.ok()) {
        return failure<double>(f.status);
      }
      q += f.value.flow_m3_per_s;
      g += f.value.conductance_m3_per_s_Pa;
    }
    const double r = q - flow;
    if (r < 0.0) {
      lo = p;
    } else {
      hi = p;
    }
    double next = g > 0.0 ? p - r / g : 0.5 * (lo + hi);
    const double tol = std::max(kRelTol * p, kAbsTol_Pa);
    const bool converged = r == 0.0 || std::fabs(next - p) <= tol;
    if (!converged && !(next > lo && next < hi)) {
      next = 0.5 * (lo + hi);
    }
    if (converged || hi - lo <= std::max(kRelTol * hi, kAbsTol_Pa)) {
      return {std::clamp(next, lo, hi)};
    }
    p = next;
  }
  return failure<double>(Status::no_convergence);
}

Result<double> DeviceModel::valve_network_pressure_Pa(std::size_t cell, double flow_m3_per_s,
                                                      std::span<const double> valve_yield_Pa) const noexcept {
  if (cell >= layout_.fluid_cell_count() || valve_yield_Pa.size() != layout_.valve_count()) {
    return failure<double>(Status::out_of_range);
  }
  if (!std::isfinite(flow_m3_per_s)) {
    return failure<double>(Status::not_finite);
  }
  if (flow_m3_per_s < 0.0) {
    return failure<double>(Status::negative);
  }
  for (const double t : valve_yield_Pa) {
    if (!std::isfinite(t)) {
      return failure<double>(Status::not_finite);
    }
    if (t < 0.0) {
      return failure<double>(Status::negative);
    }
  }
  auto tau_of = [&](std::uint32_t link) {
    const std::int32_t v = link_valve_[link];
    return v < 0 ? 0.0 : valve_yield_Pa[static_cast<std::size_t>(v)];
  };
  return network_pressure(cell, flow_m3_per_s, tau_of);
}

Result<double> DeviceModel::valve_network_pressure_uniform_Pa(std::size_t cell, double flow_m3_per_s,
                                                              double yield_stress_Pa) const noexcept {
  if (cell >= layout_.fluid_cell_count()) {
    return failure<double>(Status::out_of_range);
  }
  if (!std::isfinite(flow_m3_per_s) || !std::isfinite(yield_stress_Pa)) {
    return failure<double>(Status::not_finite);
  }
  if (flow_m3_per_s < 0.0 || yield_stress_Pa < 0.0) {
    return failure<double>(Status::negative);
  }
  auto tau_of = [&](std::uint32_t link) { return link_valve_[link] < 0 ? 0.0 : yield_stress_Pa; };
  return network_pressure(cell, flow_m3_per_s, tau_of);
}

template <class TauOf>
Result<CellLoad> DeviceModel::load(std::size_t cell, double d, double v, const TauOf& tau_of) const noexcept {
  if (!std::isfinite(d) || !std::isfinite(v)) {
    return failure<CellLoad>(Status::not_finite);
  }
  if (cell >= layout_.fluid_cell_count()) {
    return failure<CellLoad>(Status::out_of_range);
  }
  CellLoad out;
  out.effective_area_m2 = patch_.effective_area_m2;
  if (d <= 0.0) {
    out.mode = CellMode::released;  // no contact
    return {out};
  }
  if (d >= profile_.cell_depth_m) {
    return failure<CellLoad>(Status::out_of_range);  // the pad would reach the cell's floor
  }
  const Result<double> pv = network_pressure(cell, std::fabs(patch_.effective_area_m2 * v), tau_of);
  if (!pv.ok()) {
    return failure<CellLoad>(pv.status);
  }
  return load_at_pressure(d, v, pv.value);
}

// The load of a cell in contact (0 < d < depth) whose valves' network stands at pv for the
// cell's flow |area v|: its mode, the bulge and the force.
Result<CellLoad> DeviceModel::load_at_pressure(double d, double v, double pv_Pa) const noexcept {
  CellLoad out;
  out.effective_area_m2 = patch_.effective_area_m2;
  const double area = patch_.effective_area_m2;
  const Result<double> fm = pad_membrane_force_N(patch_, d);
  if (!fm.ok()) {
    return failure<CellLoad>(fm.status);
  }
  out.membrane_force_N = fm.value;
  const double p0 = profile_.reservoir.initial_pressure_Pa;
  const double flow = area * v;
  if (v >= 0.0) {
    const double displaced = area * d;
    const double p_lock = bulge_pressure_Pa(patch_, displaced);
    if (p_lock <= pv_Pa) {
      out.mode = CellMode::bulging;
      out.pressure_Pa = p_lock;
      out.bulge_volume_m3 = displaced;
    } else {
      out.mode = v > 0.0 ? CellMode::flowing : CellMode::holding;
      out.pressure_Pa = pv_Pa;
      out.valve_flow_m3_per_s = flow;
      const Result<double> s = bulge_volume_m3(patch_, pv_Pa);
      if (!s.ok()) {
        return failure<CellLoad>(s.status);
      }
      out.bulge_volume_m3 = s.value;
    }
    out.force_N = out.membrane_force_N + area * (out.pressure_Pa + p0);
  } else {
    out.pressure_Pa = -pv_Pa;
    out.valve_flow_m3_per_s = flow;
    const Result<double> s = bulge_volume_m3(patch_, out.pressure_Pa);
    out.bulge_volume_m3 = s.value;
    out.force_N = out.membrane_force_N + area * (out.pressure_Pa + p0);
    out.mode = CellMode::refilling;
    if (out.force_N <= 0.0) {
      out.force_N = 0.0;
      out.mode = CellMode::released;
    }
  }
  if (!std::isfinite(out.force_N)) {
    return failure<CellLoad>(Status::overflow);
  }
  return {out};
}

Result<CellLoad> DeviceModel::cell_force(std::size_t cell, double indentation_m, double velocity_m_per_s,
                                         std::span<const double> valve_current_A) const noexcept {
  if (valve_current_A.size() != layout_.valve_count()) {
    return failure<CellLoad>(Status::out_of_range);
  }
  for (const double i : valve_current_A) {
    const Result<double> t = yield_stress_at_current_Pa(i);
    if (!t.ok()) {
      return failure<CellLoad>(t.status);
    }
  }
  auto tau_of = [&](std::uint32_t link) {
    const std::int32_t v = link_valve_[link];
    return v < 0 ? 0.0 : yield_stress_at_current_Pa(valve_current_A[static_cast<std::size_t>(v)]).value;
  };
  return load(cell, indentation_m, velocity_m_per_s, tau_of);
}

Result<CellLoad> DeviceModel::cell_force_uniform(std::size_t cell, double indentation_m,
                                                 double velocity_m_per_s, double current_A) const noexcept {
  const Result<double> t = yield_stress_at_current_Pa(current_A);
  if (!t.ok()) {
    return failure<CellLoad>(t.status);
  }
  return cell_force_at_yield(cell, indentation_m, velocity_m_per_s, t.value);
}

Result<CellLoad> DeviceModel::cell_force_at_yield(std::size_t cell, double indentation_m,
                                                  double velocity_m_per_s,
                                                  double yield_stress_Pa) const noexcept {
  if (!std::isfinite(yield_stress_Pa)) {
    return failure<CellLoad>(Status::not_finite);
  }
  if (yield_stress_Pa < 0.0) {
    return failure<CellLoad>(Status::negative);
  }
  auto tau_of = [&](std::uint32_t link) { return link_valve_[link] < 0 ? 0.0 : yield_stress_Pa; };
  return load(cell, indentation_m, velocity_m_per_s, tau_of);
}

Result<CellLoad> DeviceModel::cell_force_at_valve_pressure(std::size_t cell, double indentation_m,
                                                           double velocity_m_per_s,
                                                           double valve_pressure_Pa) const noexcept {
  if (!std::isfinite(indentation_m) || !std::isfinite(velocity_m_per_s) ||
      !std::isfinite(valve_pressure_Pa)) {
    return failure<CellLoad>(Status::not_finite);
  }
  if (valve_pressure_Pa < 0.0) {
    return failure<CellLoad>(Status::negative);
  }
  if (cell >= layout_.fluid_cell_count()) {
    return failure<CellLoad>(Status::out_of_range);
  }
  if (indentation_m <= 0.0) {
    CellLoad out;
    out.effective_area_m2 = patch_.effective_area_m2;
    out.mode = CellMode::released;  // no contact
    return {out};
  }
  if (indentation_m >= profile_.cell_depth_m) {
    return failure<CellLoad>(Status::out_of_range);  // the pad would reach the cell's floor
  }
  return load_at_pressure(indentation_m, velocity_m_per_s, valve_pressure_Pa);
}

Result<CellEnvelope> DeviceModel::envelope(std::size_t cell, double indentation_m,
                                           double velocity_m_per_s) const noexcept {
  const Result<CellLoad> open = cell_force_uniform(cell, indentation_m, velocity_m_per_s, 0.0);
  if (!open.ok()) {
    return failure<CellEnvelope>(open.status);
  }
  const Result<CellLoad> shut =
      cell_force_uniform(cell, indentation_m, velocity_m_per_s, profile_.coil.max_current_A);
  if (!shut.ok()) {
    return failure<CellEnvelope>(shut.status);
  }
  CellEnvelope e;
  const bool loading = velocity_m_per_s >= 0.0;
  e.at_min = loading ? open.value : shut.value;
  e.at_max = loading ? shut.value : open.value;
  e.force_min_N = e.at_min.force_N;
  e.force_max_N = e.at_max.force_N;
  return {e};
}

Result<double> DeviceModel::current_for_force_A(std::size_t cell, double indentation_m,
                                                double velocity_m_per_s, double force_N) const noexcept {
  if (!std::isfinite(force_N)) {
    return failure<double>(Status::not_finite);
  }
  if (velocity_m_per_s < 0.0) {
    return failure<double>(Status::out_of_range);  // unloading: force falls with current
  }
  const Result<CellEnvelope> e = envelope(cell, indentation_m, velocity_m_per_s);
  if (!e.ok()) {
    return failure<double>(e.status);
  }
  if (force_N < e.value.force_min_N || force_N > e.value.force_max_N) {
    return failure<double>(Status::out_of_range);
  }
  double lo = 0.0;
  double hi = profile_.coil.max_current_A;
  for (int it = 0; it < 100 && hi - lo > 1e-12 * profile_.coil.max_current_A; ++it) {
    const double mid = 0.5 * (lo + hi);
    const Result<CellLoad> l = cell_force_uniform(cell, indentation_m, velocity_m_per_s, mid);
    if (!l.ok()) {
      return failure<double>(l.status);
    }
    if (l.value.force_N < force_N) {
      lo = mid;
    } else {
      hi = mid;
    }
  }
  return {0.5 * (lo + hi)};
}

}  // namespace mrskin::model
