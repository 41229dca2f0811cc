// CellInverse: the topology (valve graph, constants, tables) made once at construction, and the
// preallocation of the parts sized by it.
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

InverseTopology::InverseTopology(const DeviceModel& model, const InverseOptions& options) : opt(options) {
  const DeviceProfile& p = model.profile();
  const std::string& origin = p.origin;
  if (!(opt.hold_rate_tolerance_m_per_s >= 0.0) || !(opt.indentation_tolerance_m >= 0.0) ||
      !(opt.rate_tolerance_m_per_s >= 0.0) || !(opt.force_tolerance_N > 0.0) || opt.max_iterations < 0 ||
      opt.large_component_steps < 0 || opt.small_component_steps < 0 || !(opt.regularisation > 0.0) ||
      !std::isfinite(opt.hold_rate_tolerance_m_per_s) || !std::isfinite(opt.indentation_tolerance_m) ||
      !std::isfinite(opt.rate_tolerance_m_per_s) || !std::isfinite(opt.force_tolerance_N) ||
      !std::isfinite(opt.regularisation)) {
    throw InvalidArgument(
        "InverseOptions: tolerances must be finite and >= 0, force_tolerance_N and regularisation > 0, "
        "max_iterations, large_component_steps and small_component_steps >= 0");
  }
  graph.cells = model.layout().fluid_cell_count();
  graph.valves = model.layout().valve_count();
  const ContactPatch& patch = model.contact();
  area_m2 = patch.effective_area_m2;
  p0_Pa = p.reservoir.initial_pressure_Pa;
  depth_m = p.cell_depth_m;
  // Pad membrane force F_m(d) = k1 d + k3 d^3 (membrane.hpp, point load through the pad).
  const MembraneParams& mem = patch.membrane;
  const double a2 = patch.cell_radius_m * patch.cell_radius_m;
  const double qn = point_load_q(mem.poisson_ratio);
  membrane_linear_N_per_m =
      16.0 * kPi * bending_stiffness_N_m(mem) / a2 +
      2.0 * kPi * mem.pretension_N_per_m / std::log(patch.cell_radius_m / patch.contact_radius_m);
  membrane_cubic_N_per_m3 = mem.youngs_modulus_Pa * mem.thickness_m / (a2 * qn * qn * qn);
  bulge_linear = patch.bulge_linear_Pa_per_m3;
  bulge_cubic = patch.bulge_cubic_Pa_per_m9;
  newton_k = model.valve_law().newtonian_pressure_Pa(1.0);
  yield_k = model.valve_law().yield_pressure_Pa(1.0);
  max_current = p.coil.max_current_A;
  tol_Pa = opt.force_tolerance_N / area_m2;
  chord_floor_Pa = kChordFloor_N / area_m2;
  if (!(area_m2 > 0.0) || !(newton_k > 0.0) || !(yield_k > 0.0)) {
    throw InvalidArgument(origin + ": the inverse needs a positive contact area and valve constants");
  }
  build_graph(model);
  build_tables();
  for (Branch& b : graph.branches) {
    if (b.valve >= 0) {
      const BranchType& ty = types[b.type];
      b.a = ty.shape.a;
      b.psi = ty.psi_linear.data();
    }
  }
  build_current_table(model);
  for (CellInfo& ci : graph.info) {
    if (ci.uniform_type >= 0) {
      ci.full_r_per_flow = newton_k / (ci.branches * t_max);
      ci.full_outlets = types[static_cast<std::size_t>(ci.uniform_type)].shape.m;
    }
  }
}

ComponentPartition::ComponentPartition(const ValveGraph& g)
    : cells(g.cells, 0),
      cell_begin(g.cells + 1, 0),
      valves(g.valves, 0),
      valve_begin(g.cells + 1, 0),
      inc_begin(g.valves + g.cells + 1, 0),
      inc_row(g.valve_cells.size(), 0),
      inc_slot(g.valve_cells.size(), 0),
      comp_of_cell(g.cells, 0),
      valve_comp(g.valves, -1),
      row_of(g.cells, 0),
      local_of(g.valves, 0),
      visited(g.cells, 0),
      components(g.cells) {}

InverseSolver::InverseSolver(const ValveGraph& g)
    : jac(g.cell_valves.size(), 0.0),
      e(g.cells, 0.0),
      aim_row(g.cells, 0.0),
      one_sided(g.cells, 0),
      included(g.cells, 0),
      crow(g.cells, 0.0),
      t0(g.valves, 0.0),
      t1(g.valves, 0.0),
      tu(g.valves, 0.0),
      bound(g.valves, 0),
      bound_was(g.valves, 0),
      feasible(g.valves, 0.0),
      rank_one(kDenseRows, 0.0),
      excluded_once(g.cells, 0),
      predicted(g.cells, 0.0),
      mat(kDenseRows * kDenseRows, 0.0),
      rhs(kDenseRows, 0.0),
      dual(kDenseRows, 0.0),
      res(g.cells, 0.0),
      best(g.valves, 0.0) {}

void InverseTopology::build_graph(const DeviceModel& model) {
  const std::size_t cells = graph.cells;
  const std::size_t valves = graph.valves;
  std::vector<Branch>& branches = graph.branches;
  std::vector<CellInfo>& info = graph.info;
  std::vector<std::uint32_t>& cell_valves = graph.cell_valves;
  std::vector<std::uint32_t>& valve_cells = graph.valve_cells;
  const DeviceProfile& p = model.profile();
  const std::vector<HydraulicLink>& links = p.links;
  std::vector<std::vector<std::uint32_t>> chamber_links(valves);
  for (std::size_t i = 0; i < links.size(); ++i) {
    for (const NodeRef n : {links[i].a, links[i].b}) {
      if (n.kind == NodeKind::chamber) {
        chamber_links[n.index].push_back(static_cast<std::uint32_t>(i));
      }
    }
  }
  // Each cell's links in the profile's order (one pass over the links, not one per cell: the
  // palm's 2,048 cells made that 0.74e9 instructions of its opening).
  std::vector<std::vector<std::uint32_t>> links_of_cell(cells);
  for (std::size_t i = 0; i < links.size(); ++i) {
    const HydraulicLink& k = links[i];
    const bool a_cell = k.a.kind == NodeKind::fluid_cell && k.a.index < cells;
    if (a_cell) {
      links_of_cell[k.a.index].push_back(static_cast<std::uint32_t>(i));
    }
    if (k.b.kind == NodeKind::fluid_cell && k.b.index < cells && !(a_cell && k.a.index == k.b.index)) {
      links_of_cell[k.b.index].push_back(static_cast<std::uint32_t>(i));
    }
  }
  const double open = 1.0 / newton_k;
  std::vector<int> type_of_m;
  info.assign(cells, CellInfo{});
  std::vector<std::vector<std::uint32_t>> cells_of(valves);
  for (std::size_t cell = 0; cell < cells; ++cell) {
    CellInfo& ci = info[cell];
    ci.branch_begin = static_cast<std::uint32_t>(branches.size());
    ci.valve_begin = static_cast<std::uint32_t>(cell_valves.size());
    for (const std::uint32_t i : links_of_cell[cell]) {
      const HydraulicLink& k = links[i];
      const bool a_is = k.a.kind == NodeKind::fluid_cell && k.a.index == cell;
      const NodeRef other = a_is ? k.b : k.a;
      int m = 0;
      if (other.kind == NodeKind::chamber) {
        for (const std::uint32_t j : chamber_links[other.index]) {
          if (j == i) {
            continue;
          }
          if (links[j].valve != k.valve) {
            throw InvalidArgument(p.origin + ": [hydraulics] link " + std::to_string(i) + " and link " +
                                  std::to_string(j) +
                                  " meet in one chamber but are magnetised by different coils; the "
                                  "inverse supports branches whose passages share one coil (the chamber and "
                                  "direct topologies): give them the same valve");
          }
          ++m;
        }
      }
      Branch br;
      br.valve = k.valve;
      const BranchShape sh = shape_of(m);
      br.s = sh.s;
      br.inv_gn = open / sh.g;
      if (k.valve >= 0) {
        if (type_of_m.size() <= static_cast<std::size_t>(m)) {
          type_of_m.resize(static_cast<std::size_t>(m) + 1, -1);
        }
        if (type_of_m[static_cast<std::size_t>(m)] < 0) {
          type_of_m[static_cast<std::size_t>(m)] = static_cast<int>(types.size());
          types.push_back(BranchType{sh, {}, {}, {}, 0.0});
        }
        br.type = static_cast<std::uint32_t>(type_of_m[static_cast<std::size_t>(m)]);
        const auto v = static_cast<std::uint32_t>(k.valve);
        auto first = cell_valves.begin() + ci.valve_begin;
        auto it = std::find(first, cell_valves.end(), v);
        if (it == cell_valves.end()) {
          cell_valves.push_back(v);
          cells_of[v].push_back(static_cast<std::uint32_t>(cell));
          it = cell_valves.end() - 1;
        }
        br.slot = static_cast<std::uint32_t>(it - cell_valves.begin());
      }
      branches.push_back(br);
    }
    ci.branch_end = static_cast<std::uint32_t>(branches.size());
    ci.valve_end = static_cast<std::uint32_t>(cell_valves.size());
    ci.branches = ci.branch_end - ci.branch_begin;
    if (ci.branch_end == ci.branch_begin) {
      throw InvalidArgument(p.origin + ": [hydraulics] fluid cell " + std::to_string(cell) +
                            " has no passage: it could never be indented");
    }
    ci.s_min = std::numeric_limits<double>::infinity();
    bool uniform = ci.branches == static_cast<double>(ci.valve_end - ci.valve_begin);
    for (std::uint32_t b = ci.branch_begin; b < ci.branch_end; ++b) {
      const Branch& br = branches[b];
      ci.open_conductance += br.inv_gn;
      ci.s_min = std::min(ci.s_min, br.valve < 0 ? 0.0 : br.s);
      uniform = uniform && br.valve >= 0 && br.type == branches[ci.branch_begin].type;
    }
    ci.uniform_type = uniform ? static_cast<std::int32_t>(branches[ci.branch_begin].type) : -1;
    ci.open_resistance = 1.0 / ci.open_conductance;
  }
  std::vector<std::uint32_t>& valve_cell_begin = graph.valve_cell_begin;
  valve_cell_begin.assign(valves + 1, 0);
  for (std::size_t v = 0; v < valves; ++v) {
    valve_cell_begin[v] = static_cast<std::uint32_t>(valve_cells.size());
    for (const std::uint32_t cell : cells_of[v]) {
      valve_cells.push_back(cell);
      const CellInfo& ci = info[cell];
      const auto first = cell_valves.begin() + ci.valve_begin;
      const auto last = cell_valves.begin() + ci.valve_end;
      graph.valve_cell_slot.push_back(
          static_cast<std::uint32_t>(std::find(first, last, v) - cell_valves.begin()));
    }
  }
  valve_cell_begin[valves] = static_cast<std::uint32_t>(valve_cells.size());
}

void InverseTopology::build_tables() {
  constexpr int kK = kTableSegments;
  for (BranchType& ty : types) {
    const BranchShape& sh = ty.shape;
    ty.psi.y.assign(kK + 1, 0.0);
    ty.psi.dy.assign(kK + 1, 0.0);
    ty.omega.y.assign(kK + 1, 0.0);
    ty.omega.dy.assign(kK + 1, 0.0);
    // Near the threshold Phi - s ~ a' sqrt(r); far above it Phi -> g r + a.
    const double a1 =
        std::sqrt(2.0 / 3.0) * (1.0 + (sh.m > 0 ? 1.0 / std::sqrt(static_cast<double>(sh.m)) : 0.0));
    ty.psi.y[0] = 0.0;
    ty.psi.dy[0] = sh.g / (a1 * a1);
    ty.psi.y[kK] = 1.0;
    ty.psi.dy[kK] = sh.a - sh.s;
    for (int k = 1; k < kK; ++k) {
      const double zk = static_cast<double>(k) / kK;
      const double over = zk / (1.0 - zk);  // phi - s
      const double r = sh.r_of_phi(sh.s + over);
      const double gp = 1.0 / sh.dphi(r);
      const auto ku = static_cast<std::size_t>(k);
      ty.psi.y[ku] = r * sh.g / over;
      ty.psi.dy[ku] = sh.g * (gp * over - r) / (over * over) / ((1.0 - zk) * (1.0 - zk));
    }
    // Uniform demand: phi solves Phi(kappa phi) = phi; omega = s / phi.
    ty.omega.y[0] = 1.0;
    ty.omega.dy[0] = -a1 / std::sqrt(sh.s * sh.g);
    ty.omega_slope0 = ty.omega.dy[0];
    ty.omega.y[kK] = 0.0;
    ty.omega.dy[kK] = -2.0 * sh.s / sh.a;
    for (int k = 1; k < kK; ++k) {
      const double sigma = static_cast<double>(k) / kK;
      const double kappa = sigma * sigma / sh.g;
      double lo = sh.s;
      double hi = sh.a / (1.0 - kappa * sh.g) * 1.0000001 + 1.0;
      for (int i = 0; i < 400 && hi - lo > 1e-16 * hi; ++i) {
        const double mid = 0.5 * (lo + hi);
        if (!(mid > lo && mid < hi)) {
          break;  // adjacent doubles (as in r_of_phi): mid is the answer
        }
        (sh.phi(kappa * mid) - mid > 0.0 ? lo : hi) = mid;
      }
      const double phi = 0.5 * (lo + hi);
      const double dp = sh.dphi(kappa * phi);
      const double dphi_dkappa = -dp * phi / (dp * kappa - 1.0);
      const auto ku = static_cast<std::size_t>(k);
      ty.omega.y[ku] = sh.s / phi;
      ty.omega.dy[ku] = -sh.s / (phi * phi) * dphi_dkappa * 2.0 * sigma / sh.g;
    }
    ty.psi_linear.assign(2 * (static_cast<std::size_t>(kLinearSegments) + 1), 0.0);
    for (int k = 0; k <= kLinearSegments; ++k) {
      const double zk = static_cast<double>(k) / kLinearSegments;
      ty.psi_linear[2 * static_cast<std::size_t>(k)] = hermite(ty.psi.y.data(), ty.psi.dy.data(), zk).value;
    }
    for (int k = 0; k < kLinearSegments; ++k) {
      const auto ku = 2 * static_cast<std::size_t>(k);
      ty.psi_linear[ku + 1] = ty.psi_linear[ku + 2] - ty.psi_linear[ku];
    }
    // The loop table's error against the exact law, as a relative flow error: at the Hermite
    // table's midpoints (its own worst places) and at the linear table's, near the threshold
    // where the curvature is largest.
    auto check = [&](double zk) {
      const double over = zk / (1.0 - zk);
      const double r = sh.r_of_phi(sh.s + over);
      const double exact = r * sh.g / over;
      const double fast = linear(ty.psi_linear.data(), zk).value;
      branch_table_error = std::max(branch_table_error, std::fabs(fast - exact) / exact);
    };
    for (int k = 0; k < kK; ++k) {
      check((k + 0.5) / kK);
    }
    for (int k = 0; k < 64; ++k) {
      check((k + 0.5) / kLinearSegments);
    }
  }
}

void InverseTopology::build_current_table(const DeviceModel& model) {
  const DeviceProfile& p = model.profile();
  tau_min = model.yield_stress_at_current_Pa(0.0).value;
  tau_max = model.yield_stress_at_current_Pa(max_current).value;
  if (!(tau_max > tau_min)) {
    throw InvalidArgument(p.origin + ": [coil] max_current_A: the coil cannot raise the yield stress (" +
                          std::to_string(tau_min) + " Pa at 0 A, " + std::to_string(tau_max) +
                          " Pa at max_current_A): nothing to allocate; raise turns or max_current_A");
  }
  t_min = yield_k * tau_min;
  t_max = yield_k * tau_max;
  current_scale = kCurrentSegments / (tau_max - tau_min);
  inv_yield_k = 1.0 / yield_k;
  // I(tau) by bisection on the model's own (monotone) table, so that the round trip is exact at
  // the nodes.
  auto invert = [&](double tau_Pa) {
    double lo = 0.0;
    double hi = max_current;
    for (int i = 0; i < 200 && hi - lo > 1e-15 * max_current; ++i) {
      const double mid = 0.5 * (lo + hi);
      (model.yield_stress_at_current_Pa(mid).value < tau_Pa ? lo : hi) = mid;
    }
    return 0.5 * (lo + hi);
  };
  std::vector<double> current_table(kCurrentSegments + 1, 0.0);
  for (int k = 0; k <= kCurrentSegments; ++k) {
    current_table[static_cast<std::size_t>(k)] =
        invert(tau_min + (tau_max - tau_min) * static_cast<double>(k) / kCurrentSegments);
  }
  current_table.front() = 0.0;
  current_table.back() = max_current;
  current_lerp.assign(2 * (static_cast<std::size_t>(kCurrentSegments) + 1), 0.0);
  for (int k = 0; k <= kCurrentSegments; ++k) {
    const auto ku = static_cast<std::size_t>(k);
    current_lerp[2 * ku] = current_table[ku];
    current_lerp[2 * ku + 1] = k < kCurrentSegments ? current_table[ku + 1] - current_table[ku] : 0.0;
  }
  for (int k = 0; k < kCurrentSegments; ++k) {
    const double tau_mid = tau_min + (tau_max - tau_min) * (k + 0.5) / kCurrentSegments;
    const double back = model.yield_stress_at_current_Pa(current_for_tau(tau_mid)).value;
    current_table_error = std::max(current_table_error, std::fabs(back - tau_mid));
  }
}

}  // namespace mrskin::model
