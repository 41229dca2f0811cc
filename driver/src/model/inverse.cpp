#include "mrskin/driver/model/inverse.hpp"

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include "inverse_impl.hpp"
#include "mrskin/driver/errors.hpp"

namespace mrskin::model {

const char* to_string(CellRole r) noexcept {
  switch (r) {
    case CellRole::no_contact:
      return "no_contact";
    case CellRole::expired:
      return "expired";
    case CellRole::unloading:
      return "unloading";
    case CellRole::holding:
      return "holding";
    case CellRole::loading:
      return "loading";
  }
  return "unknown";
}

CellRole classify_cell(const CellState& state, bool expired, double hold_rate_tolerance_m_per_s) noexcept {
  return classify(state, expired, hold_rate_tolerance_m_per_s);
}

double impedance_force_N(const CellImpedanceTarget& target, const CellState& state) noexcept {
  const double x = state.indentation_m - target.surface_offset_m;
  if (!(x > 0.0)) {
    return 0.0;
  }
  const double xn = target.exponent == 1.0 ? x : std::pow(x, target.exponent);
  return law_force_N(target, xn, state.rate_m_per_s);
}

// ---- public surface ------------------------------------------------------------------------

CellInverse::CellInverse(const DeviceModel& model, const InverseOptions& options)
    : impl_(std::make_unique<Impl>(model, options)) {}
CellInverse::~CellInverse() = default;
CellInverse::CellInverse(CellInverse&&) noexcept = default;
CellInverse& CellInverse::operator=(CellInverse&&) noexcept = default;

std::size_t CellInverse::fluid_cell_count() const noexcept { return impl_->topo.graph.cells; }
std::size_t CellInverse::valve_count() const noexcept { return impl_->topo.graph.valves; }

Status CellInverse::solve(std::span<const CellImpedanceTarget> targets, std::span<const CellState> states,
                          double now_s) noexcept {
  return impl_->solve(targets, states, now_s);
}

std::span<const double> CellInverse::currents_A() const noexcept { return impl_->levels.current; }
std::span<const double> CellInverse::valve_yield_stress_Pa() const noexcept { return impl_->levels.tau; }
std::span<const CellSolution> CellInverse::cells() const noexcept { return impl_->output.cells; }
bool CellInverse::renew_at_rest(double valid_until_s, double now_s) noexcept {
  return impl_->renew_at_rest(valid_until_s, now_s);
}
std::span<const std::uint32_t> CellInverse::loaded_cells() const noexcept {
  return impl_->memory.loaded_list;
}
const InverseReport& CellInverse::report() const noexcept { return impl_->output.rep; }

CellInverse::FloorParts CellInverse::floor_parts(double indentation_m) const noexcept {
  // The same terms as the solve's floor (InverseTopology::derive: fm and base).
  const InverseTopology& m = impl_->topo;
  const double d = indentation_m;
  return FloorParts{(m.membrane_linear_N_per_m + m.membrane_cubic_N_per_m3 * d * d) * d, m.area_m2 * m.p0_Pa};
}

void CellInverse::invalidate() noexcept {
  for (CellCache& c : impl_->memory.cache) {
    c.valid = false;
    c.gn_last = false;
  }
  impl_->factors.reset(impl_->partition);  // no search or wait outlives the cells it was for
  impl_->changes.all_untouched = false;
  impl_->changes.rest_unscanned = false;
}

Result<double> CellInverse::valve_pressure_Pa(std::size_t cell, double flow_m3_per_s,
                                              std::span<const double> valve_yield_Pa) const noexcept {
  const InverseTopology& m = impl_->topo;
  if (cell >= m.graph.cells || valve_yield_Pa.size() != m.graph.valves) {
    return failure<double>(Status::out_of_range);
  }
  if (!std::isfinite(flow_m3_per_s)) {
    return failure<double>(Status::not_finite);
  }
  if (flow_m3_per_s < 0.0) {
    return failure<double>(Status::negative);
  }
  for (const double y : valve_yield_Pa) {
    if (!std::isfinite(y)) {
      return failure<double>(Status::not_finite);
    }
    if (y < 0.0) {
      return failure<double>(Status::negative);
    }
  }
  const double k = m.yield_k;
  return {m.forward(cell, flow_m3_per_s, [&](std::size_t v) { return k * valve_yield_Pa[v]; })};
}

Result<double> CellInverse::uniform_valve_pressure_Pa(std::size_t cell, double flow_m3_per_s,
                                                      double yield_stress_Pa) const noexcept {
  const InverseTopology& m = impl_->topo;
  if (cell >= m.graph.cells) {
    return failure<double>(Status::out_of_range);
  }
  if (!std::isfinite(flow_m3_per_s) || !std::isfinite(yield_stress_Pa)) {
    return failure<double>(Status::not_finite);
  }
  if (flow_m3_per_s < 0.0 || yield_stress_Pa < 0.0) {
    return failure<double>(Status::negative);
  }
  const double level = m.yield_k * yield_stress_Pa;
  return {m.forward(cell, flow_m3_per_s, [level](std::size_t) { return level; })};
}

Status CellInverse::set_valve_yield_gain(std::span<const double> gain) noexcept {
  if (gain.size() != impl_->levels.inv_gain.size()) {
    return Status::out_of_range;
  }
  for (const double g : gain) {
    if (!std::isfinite(g) || !(g > 0.0)) {
      return Status::out_of_range;
    }
  }
  for (std::size_t v = 0; v < gain.size(); ++v) {
    impl_->levels.inv_gain[v] = 1.0 / gain[v];
  }
  return Status::ok;
}

Result<double> CellInverse::current_for_yield_stress_A(double yield_stress_Pa) const noexcept {
  if (!std::isfinite(yield_stress_Pa)) {
    return failure<double>(Status::not_finite);
  }
  if (yield_stress_Pa < 0.0) {
    return failure<double>(Status::negative);
  }
  if (yield_stress_Pa > impl_->topo.tau_max) {
    return failure<double>(Status::out_of_range);
  }
  return {impl_->topo.current_for_tau(yield_stress_Pa)};
}

double CellInverse::current_table_max_error_Pa() const noexcept { return impl_->topo.current_table_error; }
double CellInverse::branch_table_max_relative_error() const noexcept {
  return impl_->topo.branch_table_error;
}

}  // namespace mrskin::model
