// NetworkSimulation's construction: the options checked, then the nodes and links, the cells'
// laws, the sensors' plans and every state and workspace array, sized once.
#include <string>
#include <utility>
#include <vector>

#include "mrskin/driver/errors.hpp"
#include "network_impl.hpp"

namespace mrskin::model {

NetworkSimulation::Impl::Impl(DeviceModel m, const NetworkOptions& o)
    : model(std::move(m)), opt(o), ldl(0, {}) {
  const DeviceProfile& prof = model.profile();
  const std::string origin = prof.origin + ": network: ";
  check_options(origin);
  const GridLayout& lay = model.layout();
  cells = lay.fluid_cell_count();
  valves = lay.valve_count();
  p0 = prof.reservoir.initial_pressure_Pa;
  cell_depth = prof.cell_depth_m;
  build_nodes_and_links(origin);
  build_cell_laws(origin);
  plan_sensors();
  size_state();
  plan_phases();
  reset();
}

void NetworkSimulation::Impl::check_options(const std::string& origin) const {
  if (!(opt.chamber_compliance_m3_per_Pa > 0.0) || !std::isfinite(opt.chamber_compliance_m3_per_Pa)) {
    throw InvalidArgument(origin + "chamber_compliance_m3_per_Pa must be > 0");
  }
  if (!(opt.regularisation_viscosity_factor > 0.0) || !std::isfinite(opt.regularisation_viscosity_factor)) {
    throw InvalidArgument(origin + "regularisation_viscosity_factor must be > 0");
  }
  if (opt.max_newton_iterations < 1) {
    throw InvalidArgument(origin + "max_newton_iterations must be >= 1");
  }
  if (!(opt.volume_tolerance_m3 > 0.0) || !(opt.pressure_tolerance_Pa > 0.0) ||
      !(opt.force_tolerance_N > 0.0)) {
    throw InvalidArgument(origin + "tolerances must be > 0");
  }
}

// Nodes: fluid cells, then the chambers the links use, then the reservoir if linked; the links
// between them and the sparse factorisation's pattern.
void NetworkSimulation::Impl::build_nodes_and_links(const std::string& origin) {
  const DeviceProfile& prof = model.profile();
  chamber_node.assign(valves, kNone);
  for (const HydraulicLink& k : prof.links) {
    for (const NodeRef n : {k.a, k.b}) {
      if (n.kind == NodeKind::chamber && n.index < valves) {
        chamber_node[n.index] = 0;
      }
    }
  }
  nodes = cells;
  node_compliance.assign(cells, 0.0);
  for (std::size_t v = 0; v < valves; ++v) {
    if (chamber_node[v] != kNone) {
      chamber_node[v] = static_cast<std::int64_t>(nodes++);
      node_compliance.push_back(opt.chamber_compliance_m3_per_Pa);
    }
  }
  auto node_of = [&](const NodeRef& n) -> std::uint32_t {
    switch (n.kind) {
      case NodeKind::fluid_cell:
        if (n.index >= cells) {
          throw InvalidArgument(origin + "a link names fluid cell " + std::to_string(n.index) +
                                " of a grid with " + std::to_string(cells));
        }
        return n.index;
      case NodeKind::chamber:
        if (n.index >= valves) {
          throw InvalidArgument(origin + "a link names chamber " + std::to_string(n.index) +
                                " of a grid with " + std::to_string(valves) + " valves");
        }
        return static_cast<std::uint32_t>(chamber_node[n.index]);
      case NodeKind::reservoir:
        if (reservoir_node == kNone) {
          reservoir_node = static_cast<std::int64_t>(nodes++);
          node_compliance.push_back(prof.reservoir.compliance_m3_per_Pa);
        }
        return static_cast<std::uint32_t>(reservoir_node);
    }
    return 0;
  };
  std::vector<detail::SparseLdl::Pair> pairs;
  for (const HydraulicLink& k : prof.links) {
    Link l;
    l.a = node_of(k.a);
    l.b = node_of(k.b);
    l.valve = k.valve;
    links.push_back(l);
    pairs.emplace_back(l.a, l.b);
  }
  ldl = detail::SparseLdl(nodes, pairs);
}

void NetworkSimulation::Impl::build_cell_laws(const std::string& origin) {
  const DeviceProfile& prof = model.profile();
  const GridLayout& lay = model.layout();
  // Cell laws: the contact patch of the profile's finger (cell.hpp). The pad's energy
  // coefficients come from the point-load law itself at unit depth.
  const ContactPatch& patch = model.contact();
  area = patch.effective_area_m2;
  const Result<LoadSplit> unit =
      point_load_force_N(patch.membrane, patch.cell_radius_m, patch.contact_radius_m, 1.0);
  if (!unit.ok()) {
    throw InvalidArgument(origin + "membrane point-load law: " + to_string(unit.status));
  }
  pad = Quartic{unit.value.bending + unit.value.pretension, unit.value.stretching};
  bulge = Quartic{patch.bulge_linear_Pa_per_m3, patch.bulge_cubic_Pa_per_m9};
  if (!(pad.k1 > 0.0) || !(bulge.k1 > 0.0)) {
    throw InvalidArgument(origin + "the membrane needs a positive linear stiffness (pre-tension or bending)");
  }
  const Result<double> rest = bulge_volume_m3(patch, p0);
  if (!rest.ok()) {
    throw InvalidArgument(origin + "[reservoir] initial_pressure_Pa: " + to_string(rest.status));
  }
  s_rest = rest.value;
  const double newton_k = model.valve_law().newtonian_pressure_Pa(1.0);
  floor_conductance = 1.0 / (opt.regularisation_viscosity_factor * newton_k);
  newtonian_conductance = model.valve_law().newtonian_conductance_m3_per_s_Pa();
  critical_flow = model.valve_law().critical_flow_m3_per_s();
  for (const GridCell& gc : lay.fluid_cells()) {
    cell_x.push_back(gc.col * prof.cell_pitch_m);
    cell_y.push_back(gc.row * prof.cell_pitch_m);
  }
}

void NetworkSimulation::Impl::plan_sensors() {
  const DeviceProfile& prof = model.profile();
  const GridLayout& lay = model.layout();
  for (const SensorSpec& s : prof.sensors) {
    SensorPlan sp;
    sp.quantity = s.quantity;
    sp.place = s.place;
    sp.index = s.index;
    sp.cells_begin = static_cast<std::uint32_t>(sensor_cells.size());
    if (s.place == PlaceKind::valve && s.index < valves) {
      for (const std::size_t c : lay.cells_of_valve(s.index)) {
        sensor_cells.push_back(static_cast<std::uint32_t>(c));
      }
    }
    sp.cells_end = static_cast<std::uint32_t>(sensor_cells.size());
    sensors.push_back(sp);
  }
}

void NetworkSimulation::Impl::size_state() {
  valve_tau.assign(valves, 0.0);
  direct_depth.assign(cells, 0.0);
  e.assign(nodes, 0.0);
  prev_e.assign(nodes, 0.0);
  d.assign(cells, 0.0);
  velocity.assign(cells, 0.0);
  node_p.assign(nodes, p0);
  force.assign(cells, 0.0);
  chamber_p.assign(valves, 0.0);
  q.assign(links.size(), 0.0);
  dc.assign(cells, 0.0);
  owner.assign(cells, kNone);
  cur.resize(nodes, cells, links.size());
  trial.resize(nodes, cells, links.size());
  y.assign(nodes, 0.0);
  de.assign(nodes, 0.0);
  new_e.assign(nodes, 0.0);
  new_d.assign(cells, 0.0);
  new_in_contact.assign(cells, 1);
  new_q.assign(links.size(), 0.0);
  new_p.assign(nodes, p0);
  new_force.assign(cells, 0.0);
  between_p.assign(nodes, 0.0);
  // Each fluid cell's links in link order (a counting sort: the palm has thousands).
  cell_links_begin.assign(cells + 1, 0);
  for (const Link& k : links) {
    for (const std::uint32_t n : {k.a, k.b}) {
      if (n < cells) {
        ++cell_links_begin[n + 1];
      }
    }
  }
  for (std::size_t i = 0; i < cells; ++i) {
    cell_links_begin[i + 1] += cell_links_begin[i];
  }
  cell_links.assign(cell_links_begin[cells], 0);
  std::vector<std::uint32_t> next(cell_links_begin.begin(), cell_links_begin.end() - 1);
  for (std::size_t l = 0; l < links.size(); ++l) {
    for (const std::uint32_t n : {links[l].a, links[l].b}) {
      if (n < cells) {
        cell_links[next[n]++] = static_cast<std::uint32_t>(l);
      }
    }
  }
}

}  // namespace mrskin::model
