#include "model_command.hpp"

#include <array>
#include <charconv>
#include <cmath>
#include <memory>
#include <optional>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/model/device_model.hpp"

namespace mrskin::ctl {

namespace {

using namespace mrskin::model;

// Thrown inside a callback for a bad argument: exit code 2.
struct BadArgument : std::runtime_error {
  using std::runtime_error::runtime_error;
};
// A law that returned an error status: exit code 1.
struct LawFailure : std::runtime_error {
  using std::runtime_error::runtime_error;
};

std::string num(double v) {
  std::array<char, 40> buf{};
  const auto r = std::to_chars(buf.data(), buf.data() + buf.size(), v, std::chars_format::general, 9);
  return {buf.data(), r.ptr};
}

std::string quoted(const std::string& s) {
  std::string o = "\"";
  for (const char c : s) {
    if (c == '"' || c == '\\') {
      o += '\\';
    }
    o += c;
  }
  return o + "\"";
}

// A flat JSON object built in insertion order.
class Json {
 public:
  Json& add(const std::string& key, double v) { return raw(key, num(v)); }
  Json& add(const std::string& key, const std::string& v) { return raw(key, quoted(v)); }
  Json& add(const std::string& key, const char* v) { return raw(key, quoted(v)); }
  Json& add(const std::string& key, bool v) { return raw(key, v ? "true" : "false"); }
  Json& add(const std::string& key, int v) { return raw(key, std::to_string(v)); }
  Json& add(const std::string& key, std::size_t v) { return raw(key, std::to_string(v)); }
  Json& add(const std::string& key, const Json& v) { return raw(key, v.str()); }
  Json& raw(const std::string& key, const std::string& v) {
    items_.emplace_back(key, v);
    return *this;
  }
  [[nodiscard]] std::string str() const {
    std::string s = "{";
    for (std::size_t i = 0; i < items_.size(); ++i) {
      s += (i == 0 ? "" : ", ") + quoted(items_[i].first) + ": " + items_[i].second;
    }
    return s + "}";
  }

 private:
  std::vector<std::pair<std::string, std::string>> items_;
};

double finite_arg(const char* name, double v) {
  if (!std::isfinite(v)) {
    throw BadArgument(std::string(name) + " must be a finite number (got " + num(v) + ")");
  }
  return v;
}

template <class T>
T checked(const Result<T>& r, const std::string& what) {
  if (!r.ok()) {
    throw LawFailure(what + ": " + to_string(r.status));
  }
  return r.value;
}

struct Options {
  std::string profile;
  // valve
  std::optional<double> dp;
  std::optional<double> q;
  std::optional<double> tau_y;
  std::optional<double> gap;
  std::optional<double> width;
  std::optional<double> length;
  std::optional<double> viscosity;
  std::optional<double> density;
  std::string method = "exact";
  // fluid / coil / membrane / cell
  std::optional<double> h;
  std::optional<double> current;
  std::optional<double> from_current;
  std::optional<double> deflection;
  std::string cell;
  std::optional<double> displacement;
  std::optional<double> velocity;
};

// "[row, col]", appended piece by piece: g++ 12 at -O3 warns falsely (-Wrestrict, GCC bug 105329)
// on "[" + std::to_string(row) + ...
std::string cell_json(int row, int col) {
  std::string out = "[";
  out += std::to_string(row);
  out += ", ";
  out += std::to_string(col);
  out += ']';
  return out;
}

DeviceProfile load(const Options& o) {
  return o.profile.empty() ? default_profile() : load_profile(o.profile);
}

ValveMethod parse_method(const std::string& m) {
  if (m == "exact") {
    return ValveMethod::exact;
  }
  if (m == "wereley-pang") {
    return ValveMethod::wereley_pang;
  }
  if (m == "fast") {
    return ValveMethod::fast;
  }
  throw BadArgument("--method must be exact, wereley-pang, fast or paper-eq3 (got \"" + m + "\")");
}

std::string run_valve(const Options& o) {
  if (o.dp.has_value() == o.q.has_value()) {
    throw BadArgument(
        "model valve needs exactly one of --dp PA (gives the flow) or --q M3_S (gives the pressure)");
  }
  if (!o.tau_y) {
    throw BadArgument("model valve needs --tau-y PA");
  }
  const double tau = finite_arg("--tau-y", *o.tau_y);
  if (tau < 0.0) {
    throw BadArgument("--tau-y must be >= 0 Pa (got " + num(tau) + ")");
  }
  const bool paper = o.method == "paper-eq3";
  const ValveMethod method = paper ? ValveMethod::exact : parse_method(o.method);
  if (paper && !o.dp) {
    throw BadArgument("--method paper-eq3 (the paper's Eq. 3 as printed) gives a flow: use it with --dp");
  }
  const bool need_profile = !(o.gap && o.width && o.length && o.viscosity);
  std::optional<DeviceProfile> prof;
  if (need_profile) {
    prof = load(o);
  }
  ValveGeometry g = prof ? prof->valve : ValveGeometry{};
  double mu = prof ? prof->fluid.viscosity_Pa_s : 0.0;
  double rho = prof ? prof->fluid.density_kg_per_m3 : FluidParams{}.density_kg_per_m3;
  if (o.gap) {
    g.gap_m = finite_arg("--gap", *o.gap);
  }
  if (o.width) {
    g.shape = ValveGeometry::Shape::slot;
    g.width_m = finite_arg("--width", *o.width);
  }
  if (o.length) {
    g.length_m = finite_arg("--length", *o.length);
  }
  if (o.viscosity) {
    mu = finite_arg("--viscosity", *o.viscosity);
  }
  if (o.density) {
    rho = finite_arg("--density", *o.density);
  }
  std::unique_ptr<ValveLaw> law;
  try {
    law = std::make_unique<ValveLaw>(g, mu, rho);
  } catch (const InvalidArgument& e) {
    throw BadArgument(e.what());
  }
  double q = 0.0;
  double dp = 0.0;
  if (paper) {
    dp = finite_arg("--dp", *o.dp);
    const double d = g.shape == ValveGeometry::Shape::annulus ? g.mean_diameter_m : g.width_m / kPi;
    const Result<double> eq3 = paper_eq3_flow_m3_per_s(dp, tau, g.gap_m, g.length_m, d, mu);
    if (eq3.status != Status::out_of_regime) {
      throw LawFailure(std::string("paper Eq. 3: ") + to_string(eq3.status));
    }
    Json j;
    j.add("law", "valve").add("method", "paper-eq3").add("given", "dp_pa").add("dp_pa", dp);
    j.add("q_m3_s", eq3.value).add("valid", false);
    j.add("q_exact_m3_s", checked(law->flow_m3_per_s(dp, tau), "valve flow"));
    j.add("tau_y_pa", tau).add("gap_m", g.gap_m).add("length_m", g.length_m).add("mean_diameter_m", d);
    j.add("viscosity_pa_s", mu);
    j.add("note", "Eq. 3 as printed: one term has units Pa^3/m beside Pa^3; not a usable law");
    j.add("profile", prof ? prof->origin : std::string("(command line)"));
    return j.str();
  }
  if (o.dp) {
    dp = finite_arg("--dp", *o.dp);
    q = checked(law->flow_m3_per_s(dp, tau, method), "valve flow");
  } else {
    q = finite_arg("--q", *o.q);
    dp = checked(law->pressure_Pa(q, tau, method), "valve pressure");
  }
  const double re = law->reynolds_number(q);
  Json j;
  j.add("law", "valve").add("method", to_string(method)).add("given", o.dp ? "dp_pa" : "q_m3_s");
  j.add("dp_pa", dp).add("q_m3_s", q).add("tau_y_pa", tau).add("dp_y_pa", law->yield_pressure_Pa(tau));
  j.add("newtonian_dp_pa", law->newtonian_pressure_Pa(std::fabs(q)));
  j.add("zeta", std::fabs(dp) > 0.0 ? std::fmin(1.0, law->yield_pressure_Pa(tau) / std::fabs(dp)) : 1.0);
  j.add("reynolds", re)
      .add("turbulent", re > kCriticalReynolds)
      .add("turbulent_dp_pa", law->turbulent_pressure_Pa(q));
  j.add("shape", g.shape == ValveGeometry::Shape::slot ? "slot" : "annulus");
  j.add("gap_m", g.gap_m).add("width_m", g.width_m).add("length_m", g.length_m);
  j.add("viscosity_pa_s", mu).add("density_kg_m3", rho);
  j.add("profile", prof ? prof->origin : std::string("(command line)"));
  return j.str();
}

std::string run_fluid(const Options& o) {
  if (!o.h) {
    throw BadArgument("model fluid needs --h A_M");
  }
  const double h = finite_arg("--h", *o.h);
  const DeviceProfile p = load(o);
  Json j;
  j.add("law", "fluid").add("h_a_m", h);
  j.add("tau_y_pa", checked(yield_stress_Pa(p.fluid, h), "yield stress"));
  j.add("b_t", checked(fluid_flux_density_T(p.fluid, h), "flux density"));
  j.add("mu_r", fluid_permeability_H_per_m(p.fluid, h) / kMu0_H_per_m);
  j.add("tau_y_saturated_pa", saturated_yield_stress_Pa(p.fluid));
  j.add("volume_fraction", p.fluid.volume_fraction).add("carrier_factor", p.fluid.carrier_factor);
  j.add("viscosity_pa_s", p.fluid.viscosity_Pa_s).add("density_kg_m3", p.fluid.density_kg_per_m3);
  j.add("profile", p.origin);
  return j.str();
}

std::string run_coil(const Options& o) {
  if (!o.current) {
    throw BadArgument("model coil needs --current A");
  }
  const double i = finite_arg("--current", *o.current);
  const DeviceProfile p = load(o);
  if (i < 0.0 || i > p.coil.max_current_A) {
    throw BadArgument("--current " + num(i) + " A is outside the profile's range 0.." +
                      num(p.coil.max_current_A) + " A (max_current_A)");
  }
  const GapField g = checked(gap_field(p.magnetic, p.fluid, i), "magnetic circuit");
  Json j;
  j.add("law", "coil").add("current_a", i).add("h_a_m", g.field_A_per_m).add("b_t", g.flux_density_T);
  j.add("tau_y_pa", g.yield_stress_Pa).add("steel_h_a_m", g.steel_field_A_per_m);
  j.add("steel_b_t", g.steel_flux_density_T)
      .add("steel_polarization_fraction", g.steel_polarization_fraction);
  j.add("mmf_a", p.magnetic.turns * i).add("turns", p.magnetic.turns);
  j.add("inductance_h", p.coil.inductance_H);
  j.add("inductance_zero_field_estimate_h", zero_field_inductance_H(p.magnetic, p.fluid));
  j.add("current_loop_time_constant_s", current_loop_time_constant_s(p.coil));
  j.add("coil_time_constant_s", coil_time_constant_s(p.coil));
  j.add("open_loop_time_constant_s", open_loop_time_constant_s(p.coil));
  j.add("max_current_a", p.coil.max_current_A).add("current_resolution_a", p.coil.current_resolution_A);
  if (o.from_current) {
    // Hysteresis branch: demagnetised start, drive to --from, then to --current.
    const double from = finite_arg("--from", *o.from_current);
    if (from < 0.0 || from > p.coil.max_current_A) {
      throw BadArgument("--from " + num(from) + " A is outside the profile's range 0.." +
                        num(p.coil.max_current_A) + " A (max_current_A)");
    }
    HysteresisState state;
    checked(gap_field_hysteretic(p.magnetic, p.fluid, from, state), "magnetic circuit (hysteretic)");
    const GapField hy =
        checked(gap_field_hysteretic(p.magnetic, p.fluid, i, state), "magnetic circuit (hysteretic)");
    Json hj;
    hj.add("from_current_a", from).add("coercivity_a_m", p.magnetic.steel.coercivity_A_per_m);
    hj.add("h_a_m", hy.field_A_per_m).add("b_t", hy.flux_density_T).add("tau_y_pa", hy.yield_stress_Pa);
    j.add("hysteresis", hj);
  }
  j.add("profile", p.origin);
  return j.str();
}

std::string run_membrane(const Options& o) {
  if (!o.deflection) {
    throw BadArgument("model membrane needs --deflection M");
  }
  const double d = finite_arg("--deflection", *o.deflection);
  const DeviceProfile p = load(o);
  if (d < 0.0 || d >= p.cell_depth_m) {
    throw BadArgument("--deflection " + num(d) + " m is outside 0.." + num(p.cell_depth_m) +
                      " m (cell_depth_m)");
  }
  const DeviceModel model(p);
  const ContactPatch& c = model.contact();
  const LoadSplit f =
      checked(point_load_force_N(p.membrane, c.cell_radius_m, c.contact_radius_m, d), "membrane point load");
  const double pressure =
      checked(disk_pressure_Pa(p.membrane, c.cell_radius_m, d), "membrane uniform pressure");
  // The paper's Eq. 6 for the same cell under the same pressure: a beam as long and wide as
  // the cell, I = w t^3 / 12, at mid-span.
  const double w = p.cell_pitch_m;
  const double t = p.membrane.thickness_m;
  const Result<double> eq6 = paper_eq6_deflection_m(pressure, w * w, w, p.membrane.youngs_modulus_Pa,
                                                    w * t * t * t / 12.0, 0.5 * w, t);
  Json j;
  j.add("law", "membrane").add("deflection_m", d).add("deflection_to_thickness", d / t);
  j.add("regime", to_string(deflection_regime(p.membrane, d)));
  j.add("force_n", f.total).add("force_bending_n", f.bending).add("force_pretension_n", f.pretension);
  j.add("force_stretching_n", f.stretching).add("contact_radius_m", c.contact_radius_m);
  j.add("cell_radius_m", c.cell_radius_m).add("uniform_pressure_pa", pressure);
  j.add("eq6_deflection_m", eq6.value).add("eq6_valid", eq6.status == Status::ok);
  j.add("eq6_over_law", d > 0.0 ? eq6.value / d : 1.0);
  j.add("profile", p.origin);
  return j.str();
}

std::pair<int, int> parse_cell(const std::string& s) {
  std::istringstream in(s);
  int r = 0;
  int c = 0;
  char comma = 0;
  if (!(in >> r >> comma >> c) || comma != ',' || !(in >> std::ws).eof()) {
    throw BadArgument("--cell must be ROW,COL (got \"" + s + "\")");
  }
  return {r, c};
}

std::string run_cell(const Options& o) {
  if (o.cell.empty() || !o.displacement || !o.velocity || !o.current) {
    throw BadArgument("model cell needs --cell ROW,COL --displacement M --velocity M_S --current A");
  }
  const auto [row, col] = parse_cell(o.cell);
  const double d = finite_arg("--displacement", *o.displacement);
  const double v = finite_arg("--velocity", *o.velocity);
  const double i = finite_arg("--current", *o.current);
  const DeviceProfile p = load(o);
  const DeviceModel model(p);
  const Result<std::size_t> cell = model.fluid_cell_index(row, col);
  if (!cell.ok()) {
    throw BadArgument("--cell " + o.cell + " is not a fluid cell of the " + std::to_string(p.rows) + " x " +
                      std::to_string(p.cols) + " grid (fluid cells have row + col even)");
  }
  if (d < 0.0 || d >= p.cell_depth_m) {
    throw BadArgument("--displacement " + num(d) + " m is outside 0.." + num(p.cell_depth_m) +
                      " m (cell_depth_m)");
  }
  if (i < 0.0 || i > p.coil.max_current_A) {
    throw BadArgument("--current " + num(i) + " A is outside the profile's range 0.." +
                      num(p.coil.max_current_A) + " A (max_current_A)");
  }
  const CellLoad l = checked(model.cell_force_uniform(cell.value, d, v, i), "cell force");
  const CellEnvelope e = checked(model.envelope(cell.value, d, v), "envelope");
  Json env;
  env.add("force_min_n", e.force_min_N).add("force_max_n", e.force_max_N);
  env.add("mode_at_min", to_string(e.at_min.mode)).add("mode_at_max", to_string(e.at_max.mode));
  env.add("current_at_max_a", v >= 0.0 ? p.coil.max_current_A : 0.0);
  Json j;
  j.add("law", "cell").raw("cell", cell_json(row, col));
  j.add("cell_index", cell.value).add("displacement_m", d).add("velocity_m_s", v).add("current_a", i);
  j.add("tau_y_pa", checked(model.yield_stress_at_current_Pa(i), "yield curve"));
  j.add("force_n", l.force_N).add("pressure_pa", l.pressure_Pa).add("valve_flow_m3_s", l.valve_flow_m3_per_s);
  j.add("bulge_volume_m3", l.bulge_volume_m3).add("membrane_force_n", l.membrane_force_N);
  j.add("effective_area_m2", l.effective_area_m2).add("contact_area_m2", model.contact().contact_area_m2);
  j.add("mode", to_string(l.mode)).add("branches", model.branch_count(cell.value));
  j.add("envelope", env);
  j.add("profile", p.origin);
  return j.str();
}

std::string run_profile(const Options& o) {
  const DeviceProfile p = load(o);
  const DeviceModel model(p);
  std::size_t reservoir_links = 0;
  for (const HydraulicLink& k : p.links) {
    reservoir_links += (k.a.kind == NodeKind::reservoir || k.b.kind == NodeKind::reservoir) ? 1 : 0;
  }
  Json j;
  j.add("name", p.name).add("profile", p.origin).add("rows", p.rows).add("cols", p.cols);
  j.add("fluid_cells", model.layout().fluid_cell_count()).add("valves", model.layout().valve_count());
  j.add("sensors", p.sensors.size()).add("links", p.links.size()).add("reservoir_links", reservoir_links);
  j.add("topology", p.topology).add("cell_pitch_m", p.cell_pitch_m).add("cell_radius_m", p.cell_radius_m());
  j.add("effective_area_m2", model.contact().effective_area_m2);
  j.add("contact_area_m2", model.contact().contact_area_m2);
  j.add("turns", p.magnetic.turns).add("max_current_a", p.coil.max_current_A);
  j.add("current_resolution_a", p.coil.current_resolution_A);
  j.add("tau_y_at_max_current_pa",
        checked(model.yield_stress_at_current_Pa(p.coil.max_current_A), "yield curve"));
  j.add("yield_table_max_error_pa", model.yield_table_max_error_Pa());
  j.add("coil_time_constant_s", coil_time_constant_s(p.coil));
  j.add("reynolds_at_1e-6_m3_s", model.valve_law().reynolds_number(1e-6));
  const Result<std::size_t> cell = model.fluid_cell_index(p.design.row, p.design.col);
  const double d = p.design.indentation_m;
  const CellEnvelope hold = checked(model.envelope(cell.value, d, 0.0), "design envelope");
  Json design;
  design.raw("cell", cell_json(p.design.row, p.design.col));
  design.add("indentation_m", d).add("velocity_m_s", 0.0).add("force_range_n", p.design.force_range_N);
  design.add("force_min_n", hold.force_min_N).add("force_max_n", hold.force_max_N);
  const Result<double> i_full = model.current_for_force_A(cell.value, d, 0.0, p.design.force_range_N);
  if (i_full.ok()) {
    design.add("current_for_force_range_a", i_full.value);
    design.add("fraction_of_current_range", i_full.value / p.coil.max_current_A);
    // Force change per current count at the design point (linearised over one count).
    const double f0 =
        checked(model.cell_force_uniform(cell.value, d, 0.0, i_full.value), "design force").force_N;
    const double i1 = std::fmax(0.0, i_full.value - p.coil.current_resolution_A);
    const double f1 = checked(model.cell_force_uniform(cell.value, d, 0.0, i1), "design force").force_N;
    design.add("force_per_count_n", f0 - f1);
    design.add("force_per_count_fraction_of_range", (f0 - f1) / p.design.force_range_N);
  } else {
    design.add("current_for_force_range_a", "unreachable");
  }
  j.add("design", design);
  return j.str();
}

}  // namespace

CliCommand add_model_command(CliCommand app, int& exit_code, std::FILE* out, std::FILE* err) {
  auto opts = std::make_shared<Options>();
  CliCommand model =
      app.subcommand("model", "evaluate the device model's laws for a profile (JSON, SI units)");
  model.option("--profile", opts->profile,
               "device profile: a .toml file, or a name looked up in $MRSKIN_PROFILE_PATH and the shipped "
               "profiles (default: mr-skin-5x5)");
  model.require_subcommand(1);

  auto wrap = [&exit_code, out, err](std::string (*fn)(const Options&), const std::shared_ptr<Options>& o) {
    return [&exit_code, out, err, fn, o] {
      auto fail = [&](const std::exception& e, int code) {
        std::fputs(("error: " + std::string(e.what()) + "\n").c_str(), err);
        exit_code = code;
      };
      try {
        std::fputs((fn(*o) + "\n").c_str(), out);
        exit_code = 0;
      } catch (const BadArgument& e) {
        fail(e, 2);
      } catch (const InvalidArgument& e) {
        fail(e, 2);
      } catch (const LawFailure& e) {
        fail(e, 1);
      } catch (const std::exception& e) {
        fail(e, 1);
      }
    };
  };

  CliCommand valve = model.subcommand("valve", "Bingham valve: --dp gives the flow, --q gives the pressure");
  valve.option("--dp", opts->dp, "pressure drop, Pa");
  valve.option("--q", opts->q, "flow, m^3/s");
  valve.option("--tau-y", opts->tau_y, "yield stress, Pa").required();
  valve.option("--gap", opts->gap, "gap h, m (default: profile)");
  valve.option("--width", opts->width, "slot width w, m (default: profile)");
  valve.option("--length", opts->length, "length L, m (default: profile)");
  valve.option("--viscosity", opts->viscosity, "viscosity, Pa s (default: profile)");
  valve.option("--density", opts->density, "density, kg/m^3 (default: profile; only for Re)");
  valve
      .option("--method", opts->method,
              "exact | wereley-pang | fast (| paper-eq3: the paper's Eq. 3 as "
              "printed, with --dp, for comparison)")
      .show_default();
  valve.callback(wrap(run_valve, opts));

  CliCommand fluid = model.subcommand("fluid", "MR fluid: yield stress and B at a field H");
  fluid.option("--h", opts->h, "field, A/m").required();
  fluid.callback(wrap(run_fluid, opts));

  CliCommand coil =
      model.subcommand("coil", "magnetic circuit: H and B in the gap, and the yield stress there");
  coil.option("--current", opts->current, "coil current, A").required();
  coil.option("--from", opts->from_current,
              "also evaluate on the hysteresis branch reached from this current, A "
              "(the steel's coercivity_A_per_m)");
  coil.callback(wrap(run_coil, opts));

  CliCommand membrane =
      model.subcommand("membrane", "membrane force at a centre deflection (and Eq. 6 beside it)");
  membrane.option("--deflection", opts->deflection, "centre deflection, m").required();
  membrane.callback(wrap(run_membrane, opts));

  CliCommand cell = model.subcommand("cell",
                                     "force on a fluid cell with all its valves at one current, and "
                                     "its renderable envelope");
  cell.option("--cell", opts->cell, "ROW,COL of a fluid cell").required();
  cell.option("--displacement", opts->displacement, "indentation, m").required();
  cell.option("--velocity", opts->velocity, "indentation rate, m/s (< 0: unloading)").required();
  cell.option("--current", opts->current, "current on every valve, A").required();
  cell.callback(wrap(run_cell, opts));

  CliCommand profile = model.subcommand("profile", "summary of the profile and its design check");
  profile.callback(wrap(run_profile, opts));
  return model;
}

}  // namespace mrskin::ctl
