#include "mrskin/driver/model/profile.hpp"

#include <dlfcn.h>
#include <fmt/format.h>
#include <toml++/toml.h>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <initializer_list>
#include <optional>
#include <set>
#include <sstream>
#include <utility>

#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/layout.hpp"

#ifndef MRSKIN_PROFILES_FROM_LIBDIR
#define MRSKIN_PROFILES_FROM_LIBDIR "../share/mrskin/profiles"
#endif

namespace mrskin::model {

const char* to_string(SensorQuantity q) noexcept {
  switch (q) {
    case SensorQuantity::displacement:
      return "displacement";
    case SensorQuantity::force:
      return "force";
    case SensorQuantity::pressure:
      return "pressure";
  }
  return "unknown";
}

const char* unit_of(SensorQuantity q) noexcept {
  switch (q) {
    case SensorQuantity::displacement:
      return "m";
    case SensorQuantity::force:
      return "N";
    case SensorQuantity::pressure:
      return "Pa";
  }
  return "?";
}

double DeviceProfile::cell_radius_m() const noexcept { return cell_pitch_m / std::sqrt(kPi); }

namespace {

[[noreturn]] void fail(const std::string& origin, const std::string& what) {
  throw InvalidArgument(origin + ": " + what);
}

std::string number_text(double v) {
  std::ostringstream s;
  s << v;
  return s.str();
}

// One TOML table, read key by key; finish() rejects keys nobody asked for (typos).
class Section {
 public:
  Section(const toml::table* table, std::string name, std::string origin)
      : table_(table), name_(std::move(name)), origin_(std::move(origin)) {}

  [[nodiscard]] bool present() const noexcept { return table_ != nullptr; }
  [[nodiscard]] const std::string& name() const noexcept { return name_; }

  [[noreturn]] void fail_key(std::string_view key, const std::string& reason) const {
    fail(origin_, "[" + name_ + "] " + std::string(key) + ": " + reason);
  }

  const toml::node* node(std::string_view key) {
    used_.insert(std::string(key));
    return table_ == nullptr ? nullptr : table_->get(key);
  }

  double number(std::string_view key, std::optional<double> fallback = std::nullopt) {
    const toml::node* n = node(key);
    if (n == nullptr) {
      if (fallback) {
        return *fallback;
      }
      fail_key(key, "missing (a number in SI units)");
    }
    if (const auto v = n->value<double>(); v && (n->is_floating_point() || n->is_integer())) {
      if (!std::isfinite(*v)) {
        fail_key(key, "must be finite (got " + number_text(*v) + ")");
      }
      return *v;
    }
    fail_key(key, "must be a number");
  }

  double positive(std::string_view key, std::optional<double> fallback = std::nullopt) {
    const double v = number(key, fallback);
    if (!(v > 0.0)) {
      fail_key(key, "must be > 0 (got " + number_text(v) + ")");
    }
    return v;
  }

  double non_negative(std::string_view key, std::optional<double> fallback = std::nullopt) {
    const double v = number(key, fallback);
    if (!(v >= 0.0)) {
      fail_key(key, "must be >= 0 (got " + number_text(v) + ")");
    }
    return v;
  }

  long long integer(std::string_view key, std::optional<long long> fallback = std::nullopt) {
    const toml::node* n = node(key);
    if (n == nullptr) {
      if (fallback) {
        return *fallback;
      }
      fail_key(key, "missing (an integer)");
    }
    if (const auto v = n->value_exact<std::int64_t>()) {
      return static_cast<long long>(*v);
    }
    fail_key(key, "must be an integer");
  }

  std::string text(std::string_view key, std::optional<std::string> fallback = std::nullopt) {
    const toml::node* n = node(key);
    if (n == nullptr) {
      if (fallback) {
        return *fallback;
      }
      fail_key(key, "missing (a string)");
    }
    if (const auto v = n->value_exact<std::string>()) {
      return *v;
    }
    fail_key(key, "must be a string");
  }

  Section sub(std::string_view key) {
    const toml::node* n = node(key);
    if (n != nullptr && !n->is_table()) {
      fail_key(key, "must be a table");
    }
    return {n == nullptr ? nullptr : n->as_table(),
            name_.empty() ? std::string(key) : name_ + "." + std::string(key), origin_};
  }

  const toml::array* array_of_tables(std::string_view key) {
    const toml::node* n = node(key);
    if (n == nullptr) {
      return nullptr;
    }
    if (!n->is_array_of_tables()) {
      fail_key(key, "must be an array of tables ([[" + name_ + "." + std::string(key) + "]])");
    }
    return n->as_array();
  }

  void finish() const {
    if (table_ == nullptr) {
      return;
    }
    for (const auto& [k, v] : *table_) {
      if (!used_.contains(std::string(k.str()))) {
        fail(origin_, "[" + name_ + "] " + std::string(k.str()) +
                          ": unknown key (misspelt, or a unit suffix missing?)");
      }
    }
  }

 private:
  const toml::table* table_;
  std::string name_;
  std::string origin_;
  std::set<std::string> used_;
};

void check(const std::string& origin, const std::string& section, const char* why) {
  if (why != nullptr && *why != '\0') {
    fail(origin, "[" + section + "] " + why);
  }
}

// "R,C" -> row, col
std::pair<int, int> parse_rc(const Section& s, std::string_view key, const std::string& text) {
  int r = 0;
  int c = 0;
  char comma = 0;
  std::istringstream in(text);
  if (!(in >> r >> comma >> c) || comma != ',' || !(in >> std::ws).eof()) {
    s.fail_key(key, "\"" + text + R"(" is not "ROW,COL")");
  }
  return {r, c};
}

struct Grid {
  GridLayout layout;
  std::vector<int> fluid_index;  // row * cols + col -> fluid index or -1
  std::vector<int> valve_index;  // row * cols + col -> valve index or -1
  explicit Grid(int rows, int cols) : layout(rows, cols) {
    fluid_index.assign(static_cast<std::size_t>(rows) * static_cast<std::size_t>(cols), -1);
    valve_index.assign(static_cast<std::size_t>(rows) * static_cast<std::size_t>(cols), -1);
    for (std::size_t i = 0; i < layout.fluid_cells().size(); ++i) {
      const GridCell g = layout.fluid_cells()[i];
      fluid_index[at(g.row, g.col)] = static_cast<int>(i);
    }
    for (std::size_t i = 0; i < layout.valves().size(); ++i) {
      const GridCell g = layout.valves()[i];
      valve_index[at(g.row, g.col)] = static_cast<int>(i);
    }
  }
  [[nodiscard]] std::size_t at(int r, int c) const {
    return static_cast<std::size_t>(r) * static_cast<std::size_t>(layout.cols()) +
           static_cast<std::size_t>(c);
  }
  [[nodiscard]] int fluid_at(int r, int c) const {
    if (r < 0 || c < 0 || r >= layout.rows() || c >= layout.cols()) {
      return -1;
    }
    return fluid_index[at(r, c)];
  }
  [[nodiscard]] int valve_at(int r, int c) const {
    if (r < 0 || c < 0 || r >= layout.rows() || c >= layout.cols()) {
      return -1;
    }
    return valve_index[at(r, c)];
  }
};

// "cell R,C", "chamber R,C" (the chamber inside the valve cell at R,C) or "reservoir".
NodeRef parse_node(const Section& s, std::string_view key, const std::string& text, const Grid& g) {
  if (text == "reservoir") {
    return {NodeKind::reservoir, 0};
  }
  const auto space = text.find(' ');
  const std::string kind = text.substr(0, space);
  if (space == std::string::npos || (kind != "cell" && kind != "chamber")) {
    s.fail_key(key, "\"" + text + R"(" is not "cell R,C", "chamber R,C" or "reservoir")");
  }
  const auto [r, c] = parse_rc(s, key, text.substr(space + 1));
  if (kind == "cell") {
    const int f = g.fluid_at(r, c);
    if (f < 0) {
      s.fail_key(key, "\"" + text + "\" is not a fluid cell of the grid (fluid cells have row + col even)");
    }
    return {NodeKind::fluid_cell, static_cast<std::uint32_t>(f)};
  }
  const int v = g.valve_at(r, c);
  if (v < 0) {
    s.fail_key(key, "\"" + text + "\" is not a valve cell of the grid (valve cells have row + col odd)");
  }
  return {NodeKind::chamber, static_cast<std::uint32_t>(v)};
}

SensorQuantity parse_quantity(const Section& s, std::string_view key, const std::string& text) {
  if (text == "displacement") {
    return SensorQuantity::displacement;
  }
  if (text == "force") {
    return SensorQuantity::force;
  }
  if (text == "pressure") {
    return SensorQuantity::pressure;
  }
  s.fail_key(key, "\"" + text + "\" is not displacement, force or pressure");
}

void generate_links(DeviceProfile& p, const Grid& g, const std::string& reservoir, Section& hyd) {
  const GridLayout& l = g.layout;
  auto reservoir_for = [&](std::size_t v) {
    if (reservoir == "all_valves") {
      return true;
    }
    if (reservoir == "edge_valves") {
      const GridCell gc = l.valves()[v];
      return gc.row == 0 || gc.col == 0 || gc.row == l.rows() - 1 || gc.col == l.cols() - 1;
    }
    return false;
  };
  for (std::size_t v = 0; v < l.valve_count(); ++v) {
    const auto valve = static_cast<std::int32_t>(v);
    const std::vector<std::size_t>& cells = l.cells_of_valve(v);
    if (p.topology == "chamber") {
      for (const std::size_t c : cells) {
        p.links.push_back({{NodeKind::fluid_cell, static_cast<std::uint32_t>(c)},
                           {NodeKind::chamber, static_cast<std::uint32_t>(v)},
                           valve});
      }
      if (reservoir_for(v)) {
        p.links.push_back(
            {{NodeKind::chamber, static_cast<std::uint32_t>(v)}, {NodeKind::reservoir, 0}, valve});
      }
    } else if (p.topology == "direct") {
      for (std::size_t i = 0; i < cells.size(); ++i) {
        for (std::size_t j = i + 1; j < cells.size(); ++j) {
          p.links.push_back({{NodeKind::fluid_cell, static_cast<std::uint32_t>(cells[i])},
                             {NodeKind::fluid_cell, static_cast<std::uint32_t>(cells[j])},
                             valve});
        }
        if (reservoir_for(v)) {
          p.links.push_back({{NodeKind::fluid_cell, static_cast<std::uint32_t>(cells[i])},
                             {NodeKind::reservoir, 0},
                             valve});
        }
      }
    }
  }
  if (p.topology == "explicit" && reservoir != "none") {
    hyd.fail_key("reservoir", R"(must be "none" with topology = "explicit" (list reservoir links yourself))");
  }
}

void validate_graph(const DeviceProfile& p, const Grid& g) {
  const GridLayout& l = g.layout;
  std::vector<int> degree(l.fluid_cell_count(), 0);
  for (std::size_t i = 0; i < p.links.size(); ++i) {
    const HydraulicLink& k = p.links[i];
    const std::string where = "[hydraulics] link " + std::to_string(i) + ": ";
    if (k.a == k.b) {
      fail(p.origin, where + "joins a node to itself");
    }
    if (k.a.kind == NodeKind::chamber && k.b.kind == NodeKind::chamber) {
      fail(p.origin,
           where +
               "joins two chambers; the cell law supports one chamber between a cell and its "
               "sinks (put the chambers' passages in series through a fluid cell or the reservoir)");
    }
    if (k.valve >= static_cast<std::int32_t>(l.valve_count())) {
      fail(p.origin, where + "names a valve the grid does not have");
    }
    for (const NodeRef n : {k.a, k.b}) {
      if (n.kind == NodeKind::fluid_cell) {
        ++degree[n.index];
      }
    }
  }
  for (std::size_t c = 0; c < degree.size(); ++c) {
    if (degree[c] == 0) {
      const GridCell gc = l.fluid_cells()[c];
      fail(p.origin, "[hydraulics] fluid cell " + std::to_string(gc.row) + "," + std::to_string(gc.col) +
                         " has no link: nothing could flow out of it, so it could never be indented");
    }
  }
}

// --- one function per section of the profile ---------------------------------------------

// [profile]
void parse_identity(Section& top, DeviceProfile& p, const std::string& origin) {
  Section prof = top.sub("profile");
  if (!prof.present()) {
    fail(origin, "[profile]: missing (name, description, format_version)");
  }
  p.name = prof.text("name");
  p.description = prof.text("description", "");
  if (prof.integer("format_version") != 1) {
    prof.fail_key("format_version", "this library reads format_version = 1");
  }
  prof.finish();
}

// [grid]
void parse_grid(Section& top, DeviceProfile& p) {
  Section grid = top.sub("grid");
  const long long rows = grid.integer("rows");
  const long long cols = grid.integer("cols");
  if (rows < 1 || rows > 255) {
    grid.fail_key("rows", "must be in 1..255 (got " + std::to_string(rows) + ")");
  }
  if (cols < 1 || cols > 255) {
    grid.fail_key("cols", "must be in 1..255 (got " + std::to_string(cols) + ")");
  }
  p.rows = static_cast<int>(rows);
  p.cols = static_cast<int>(cols);
  p.cell_pitch_m = grid.positive("cell_pitch_m");
  p.cell_depth_m = grid.positive("cell_depth_m");
  grid.finish();
}

// [fluid]
void parse_fluid(Section& top, DeviceProfile& p, const std::string& origin) {
  Section fl = top.sub("fluid");
  p.fluid.volume_fraction = fl.positive("volume_fraction");
  p.fluid.carrier_factor = fl.positive("carrier_factor", 1.0);
  p.fluid.viscosity_Pa_s = fl.positive("viscosity_Pa_s");
  p.fluid.density_kg_per_m3 = fl.positive("density_kg_per_m3");
  p.fluid.yield_coefficient_Pa = fl.positive("yield_coefficient_Pa", p.fluid.yield_coefficient_Pa);
  p.fluid.yield_exponent = fl.positive("yield_exponent", p.fluid.yield_exponent);
  p.fluid.yield_field_scale_m_per_A =
      fl.positive("yield_field_scale_m_per_A", p.fluid.yield_field_scale_m_per_A);
  p.fluid.saturation_coefficient_T =
      fl.positive("saturation_coefficient_T", p.fluid.saturation_coefficient_T);
  p.fluid.saturation_exponent = fl.positive("saturation_exponent", p.fluid.saturation_exponent);
  p.fluid.saturation_rate_per_T = fl.positive("saturation_rate_per_T", p.fluid.saturation_rate_per_T);
  fl.finish();
  check(origin, "fluid", check_fluid(p.fluid));
}

// [valve]
void parse_valve(Section& top, DeviceProfile& p, const std::string& origin) {
  Section va = top.sub("valve");
  const std::string shape = va.text("shape", "slot");
  if (shape == "slot") {
    p.valve = slot_geometry(va.positive("gap_m"), va.positive("width_m"), va.positive("length_m"));
  } else if (shape == "annulus") {
    p.valve = annulus_geometry(va.positive("gap_m"), va.positive("mean_diameter_m"), va.positive("length_m"));
  } else {
    va.fail_key("shape", "\"" + shape + R"(" is not "slot" or "annulus")");
  }
  va.finish();
  check(origin, "valve", check_valve_geometry(p.valve));
}

// [magnetic]
void parse_magnetic(Section& top, DeviceProfile& p, const std::string& origin) {
  Section mg = top.sub("magnetic");
  const long long turns = mg.integer("turns");
  if (turns < 1 || turns > 100000) {
    mg.fail_key("turns", "must be in 1..100000 (got " + std::to_string(turns) + ")");
  }
  p.magnetic.turns = static_cast<int>(turns);
  p.magnetic.fluid_gap_m = p.valve.gap_m;
  p.magnetic.spacer_gap_m = mg.non_negative("spacer_gap_m", 0.0);
  p.magnetic.pole_area_m2 = mg.positive("pole_area_m2");
  p.magnetic.steel_path_length_m = mg.positive("steel_path_length_m");
  p.magnetic.steel_area_m2 = mg.positive("steel_area_m2");
  Section st = mg.sub("steel");
  p.core_material = st.text("material", "");
  p.magnetic.steel.saturation_polarization_T = st.positive("saturation_polarization_T");
  p.magnetic.steel.initial_relative_permeability = st.positive("initial_relative_permeability");
  p.magnetic.steel.coercivity_A_per_m = st.non_negative("coercivity_A_per_m", 0.0);
  st.finish();
  mg.finish();
  check(origin, "magnetic", check_magnetic(p.magnetic));
}

// [coil]
void parse_coil(Section& top, DeviceProfile& p, const std::string& origin) {
  Section co = top.sub("coil");
  p.coil.resistance_ohm = co.positive("resistance_ohm");
  p.coil.inductance_H = co.positive("inductance_H");
  p.coil.supply_voltage_V = co.positive("supply_voltage_V");
  p.coil.max_current_A = co.positive("max_current_A");
  p.coil.current_resolution_A = co.positive("current_resolution_A");
  p.coil.driver_bandwidth_Hz = co.positive("driver_bandwidth_Hz");
  p.coil.eddy_time_constant_s = co.non_negative("eddy_time_constant_s", 0.0);
  co.finish();
  check(origin, "coil", check_coil(p.coil));
}

// [membrane]
void parse_membrane(Section& top, DeviceProfile& p, const std::string& origin) {
  Section me = top.sub("membrane");
  p.membrane.thickness_m = me.positive("thickness_m");
  p.membrane.youngs_modulus_Pa = me.positive("youngs_modulus_Pa");
  p.membrane.poisson_ratio = me.non_negative("poisson_ratio");
  p.membrane.pretension_N_per_m = me.non_negative("pretension_N_per_m", 0.0);
  p.membrane.hencky_K = me.positive("hencky_K", 0.65);
  me.finish();
  check(origin, "membrane", check_membrane(p.membrane));
}

// [contact]
void parse_contact(Section& top, DeviceProfile& p) {
  Section ct = top.sub("contact");
  p.finger_radius_m = ct.positive("finger_radius_m");
  ct.finish();
  if (p.finger_radius_m < 0.01 * p.cell_radius_m()) {
    ct.fail_key("finger_radius_m", "must be at least 1 % of the cell's equivalent radius " +
                                       number_text(p.cell_radius_m()) + " m");
  }
}

// [reservoir]
void parse_reservoir(Section& top, DeviceProfile& p) {
  Section re = top.sub("reservoir");
  p.reservoir.initial_pressure_Pa = re.number("initial_pressure_Pa", 0.0);
  p.reservoir.compliance_m3_per_Pa = re.positive("compliance_m3_per_Pa");
  re.finish();
}

// [hydraulics]
void parse_hydraulics(Section& top, DeviceProfile& p, const std::string& origin, const Grid& g) {
  Section hy = top.sub("hydraulics");
  p.topology = hy.text("topology", "chamber");
  if (p.topology != "chamber" && p.topology != "direct" && p.topology != "explicit") {
    hy.fail_key("topology", "\"" + p.topology + R"(" is not "chamber", "direct" or "explicit")");
  }
  const std::string reservoir = hy.text("reservoir", "edge_valves");
  if (reservoir != "edge_valves" && reservoir != "all_valves" && reservoir != "none") {
    hy.fail_key("reservoir", "\"" + reservoir + R"(" is not "edge_valves", "all_valves" or "none")");
  }
  generate_links(p, g, reservoir, hy);
  if (const toml::array* links = hy.array_of_tables("link")) {
    std::size_t i = 0;
    for (const toml::node& n : *links) {
      Section ls(n.as_table(), "hydraulics.link " + std::to_string(i++), origin);
      HydraulicLink k;
      k.a = parse_node(ls, "from", ls.text("from"), g);
      k.b = parse_node(ls, "to", ls.text("to"), g);
      const std::string valve = ls.text("valve");
      if (valve != "none") {
        const auto [r, c] = parse_rc(ls, "valve", valve);
        const int v = g.valve_at(r, c);
        if (v < 0) {
          ls.fail_key("valve", "\"" + valve + "\" is not a valve cell of the grid");
        }
        k.valve = v;
      }
      ls.finish();
      p.links.push_back(k);
    }
  }
  hy.finish();
  validate_graph(p, g);
}

// [sensors]
void parse_sensors(Section& top, DeviceProfile& p, const std::string& origin, const Grid& g) {
  Section se = top.sub("sensors");
  const std::string generate = se.text("generate", "none");
  if (generate != "none") {
    if (generate != "under_valves" && generate != "per_fluid_cell") {
      se.fail_key("generate", "\"" + generate + R"(" is not "under_valves", "per_fluid_cell" or "none")");
    }
    SensorSpec proto;
    proto.quantity = parse_quantity(se, "quantity", se.text("quantity"));
    if (se.text("unit") != unit_of(proto.quantity)) {
      se.fail_key("unit", std::string("must be \"") + unit_of(proto.quantity) + "\" for " +
                              to_string(proto.quantity));
    }
    proto.resolution = se.positive("resolution");
    proto.noise_std = se.non_negative("noise_std");
    const bool valves = generate == "under_valves";
    const std::vector<GridCell>& places = valves ? g.layout.valves() : g.layout.fluid_cells();
    for (std::size_t i = 0; i < places.size(); ++i) {
      SensorSpec s = proto;
      s.place = valves ? PlaceKind::valve : PlaceKind::fluid_cell;
      s.row = places[i].row;
      s.col = places[i].col;
      s.index = i;
      p.sensors.push_back(s);
    }
  }
  if (const toml::array* list = se.array_of_tables("sensor")) {
    std::size_t i = 0;
    for (const toml::node& n : *list) {
      Section ss(n.as_table(), "sensors.sensor " + std::to_string(i++), origin);
      SensorSpec s;
      s.quantity = parse_quantity(ss, "quantity", ss.text("quantity"));
      if (ss.text("unit") != unit_of(s.quantity)) {
        ss.fail_key("unit",
                    std::string("must be \"") + unit_of(s.quantity) + "\" for " + to_string(s.quantity));
      }
      const std::string place = ss.text("place");
      const NodeRef node = parse_node(ss, "place", place, g);
      if (node.kind == NodeKind::reservoir) {
        s.place = PlaceKind::reservoir;
      } else {
        s.place = node.kind == NodeKind::fluid_cell ? PlaceKind::fluid_cell : PlaceKind::valve;
        s.index = node.index;
        const GridCell gc = node.kind == NodeKind::fluid_cell ? g.layout.fluid_cells()[node.index]
                                                              : g.layout.valves()[node.index];
        s.row = gc.row;
        s.col = gc.col;
      }
      s.resolution = ss.positive("resolution");
      s.noise_std = ss.non_negative("noise_std");
      ss.finish();
      p.sensors.push_back(s);
    }
  }
  se.finish();
  if (p.sensors.empty()) {
    fail(origin,
         R"([sensors]: the profile declares no sensor (generate = "under_valves" or [[sensors.sensor]]))");
  }
}

// [design]
void parse_design(Section& top, DeviceProfile& p, const Grid& g) {
  Section de = top.sub("design");
  p.design.force_range_N = de.positive("force_range_N", 2.0);
  p.design.indentation_m = de.positive("indentation_m", 5e-3);
  const int mid_r = p.rows / 2;
  const int mid_c = (mid_r + p.cols / 2) % 2 == 0 ? p.cols / 2 : (p.cols / 2 > 0 ? p.cols / 2 - 1 : 1);
  const std::string cell = de.text("cell", std::to_string(mid_r) + "," + std::to_string(mid_c));
  const auto [dr, dc] = parse_rc(de, "cell", cell);
  if (g.fluid_at(dr, dc) < 0) {
    de.fail_key("cell", "\"" + cell + "\" is not a fluid cell of the grid");
  }
  p.design.row = dr;
  p.design.col = dc;
  de.finish();
}

// [interface]
void parse_interface(Section& top, DeviceProfile& p) {
  Section in = top.sub("interface");
  const std::string bus = in.text("bus", "hid-fs");
  bool known = bus == "none";
  if (known) {
    p.bus.reset();
  }
  for (const auto kind : {protocol::BusKind::hid_full_speed, protocol::BusKind::hid_high_speed,
                          protocol::BusKind::can_classic, protocol::BusKind::can_fd}) {
    if (bus == protocol::to_string(kind)) {
      p.bus = kind;
      known = true;
    }
  }
  if (!known) {
    in.fail_key("bus", "\"" + bus + R"(" is not "hid-fs", "hid-hs", "can", "canfd" or "none")");
  }
  in.finish();
}

}  // namespace

DeviceProfile parse_profile(std::string_view toml_text, const std::string& origin) {
  toml::table root;
  try {
    root = toml::parse(toml_text, origin);
  } catch (const toml::parse_error& e) {
    std::ostringstream s;
    s << origin << ":" << e.source().begin.line << ":" << e.source().begin.column
      << ": TOML syntax: " << e.description();
    throw InvalidArgument(s.str());
  }
  DeviceProfile p;
  p.origin = origin;
  Section top(&root, "", origin);

  parse_identity(top, p, origin);
  parse_grid(top, p);
  const Grid g(p.rows, p.cols);
  parse_fluid(top, p, origin);
  parse_valve(top, p, origin);
  parse_magnetic(top, p, origin);
  parse_coil(top, p, origin);
  parse_membrane(top, p, origin);
  parse_contact(top, p);
  parse_reservoir(top, p);
  parse_hydraulics(top, p, origin, g);
  parse_sensors(top, p, origin, g);
  parse_design(top, p, g);
  parse_interface(top, p);
  top.finish();
  return p;
}

namespace {
// The directory this library was loaded from (dladdr on one of its own functions), so that an
// install finds its profiles wherever its prefix was moved; "" if the loader cannot say.
std::string driver_library_dir() {
  Dl_info info{};
  // NOLINTNEXTLINE(cppcoreguidelines-pro-type-reinterpret-cast): dladdr takes an address
  if (::dladdr(reinterpret_cast<const void*>(&driver_library_dir), &info) == 0 || info.dli_fname == nullptr) {
    return {};
  }
  std::error_code ec;
  const std::filesystem::path lib = std::filesystem::canonical(info.dli_fname, ec);
  return ec ? std::string() : lib.parent_path().string();
}
}  // namespace

std::vector<std::string> profile_search_path() {
  std::vector<std::string> dirs;
  if (const char* env = std::getenv("MRSKIN_PROFILE_PATH"); env != nullptr && *env != '\0') {
    std::string s(env);
    std::size_t start = 0;
    while (start <= s.size()) {
      const std::size_t colon = s.find(':', start);
      const std::string d = s.substr(start, colon == std::string::npos ? std::string::npos : colon - start);
      if (!d.empty()) {
        dirs.push_back(d);
      }
      if (colon == std::string::npos) {
        break;
      }
      start = colon + 1;
    }
  }
  if (const std::string libdir = driver_library_dir(); !libdir.empty()) {
    dirs.push_back(libdir + "/" + MRSKIN_PROFILES_FROM_LIBDIR);
    dirs.push_back(libdir + "/mrskin-profiles");
  }
  return dirs;
}

namespace {
bool readable(const std::string& path) {
  const std::ifstream f(path);
  return f.good();
}
}  // namespace

std::string find_profile(const std::string& name) {
  const bool is_path = name.find('/') != std::string::npos || name.ends_with(".toml");
  if (is_path) {
    if (!readable(name)) {
      throw InvalidArgument("profile file " + name + " cannot be read (check the path and its permissions)");
    }
    return name;
  }
  std::string looked;
  for (const std::string& d : profile_search_path()) {
    std::string candidate = d;
    candidate += "/";
    candidate += name;
    candidate += ".toml";
    if (readable(candidate)) {
      return candidate;
    }
    looked += looked.empty() ? "" : ", ";
    looked += d;
  }
  throw InvalidArgument(
      "profile \"" + name + "\" not found in " + (looked.empty() ? "(no directory)" : looked) +
      "; give a file path or set MRSKIN_PROFILE_PATH to the directory holding " + name + ".toml");
}

DeviceProfile load_profile(const std::string& path_or_name) {
  const std::string path = find_profile(path_or_name);
  std::ifstream in(path);
  std::ostringstream text;
  text << in.rdbuf();
  if (!in.good() && !in.eof()) {
    throw InvalidArgument("profile file " + path + " could not be read");
  }
  return parse_profile(text.str(), path);
}

DeviceProfile default_profile() { return load_profile(kDefaultProfileName); }

namespace {

bool is_path(std::string_view name) noexcept {
  return name.find('/') != std::string_view::npos || name.ends_with(".toml");
}

}  // namespace

std::vector<std::string> available_profile_names() {
  std::set<std::string> names;
  for (const std::string& dir : model::profile_search_path()) {
    std::error_code ec;
    for (const auto& entry : std::filesystem::directory_iterator(dir, ec)) {
      if (entry.path().extension() == ".toml") {
        names.insert(entry.path().stem().string());
      }
    }
  }
  return {names.begin(), names.end()};
}

LoadedProfile load_profile_with_text(std::string_view name_or_path) {
  const std::string name = name_or_path.empty() || name_or_path == "default"
                               ? std::string(model::kDefaultProfileName)
                               : std::string(name_or_path);
  std::string path;
  if (is_path(name)) {
    path = model::find_profile(name);  // InvalidArgument when unreadable
  } else {
    std::string looked;
    for (const std::string& dir : model::profile_search_path()) {
      const std::string candidate = fmt::format("{}/{}.toml", dir, name);
      if (std::ifstream(candidate).good()) {
        path = candidate;
        break;
      }
      looked += looked.empty() ? dir : ", " + dir;
    }
    if (path.empty()) {
      const std::vector<std::string> names = available_profile_names();
      std::string list;
      for (const std::string& n : names) {
        list += list.empty() ? n : ", " + n;
      }
      throw ProfileNotFound(
          fmt::format("device profile \"{}\" not found; searched {}; available: {}. Use one of those names "
                      "(mock://NAME), a file path (mock:///path/to/profile.toml), or add its directory to "
                      "MRSKIN_PROFILE_PATH",
                      name, looked.empty() ? std::string("no directory") : looked,
                      list.empty() ? std::string("none") : list));
    }
  }
  std::ifstream in(path);
  std::ostringstream text;
  text << in.rdbuf();
  if (!in.good() && !in.eof()) {
    throw InvalidArgument("profile file " + path + " could not be read; check its permissions");
  }
  LoadedProfile loaded;
  loaded.text = text.str();
  loaded.profile = model::parse_profile(loaded.text, path);
  loaded.path = path;
  return loaded;
}

}  // namespace mrskin::model
