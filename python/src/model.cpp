// mrskin.model: the device model's laws (driver/include/mrskin/driver/model/*.hpp) and profiles.
// Scalar laws take floats or NumPy arrays (broadcast, float64); a Status other than ok raises
// mrskin.ModelError (out_of_regime returns the value, as in C++).
#include <pybind11/numpy.h>
#include <pybind11/stl.h>

#include <initializer_list>
#include <string>
#include <string_view>
#include <vector>

#include "bindings.hpp"
#include "mrskin/driver/model/cell.hpp"
#include "mrskin/driver/model/device_model.hpp"
#include "mrskin/driver/model/fluid.hpp"
#include "mrskin/driver/model/magnetic.hpp"
#include "mrskin/driver/model/membrane.hpp"
#include "mrskin/driver/model/profile.hpp"
#include "mrskin/driver/model/valve.hpp"

namespace mrskin::python {

namespace {

using Array = py::array_t<double, py::array::forcecast>;
using model::DeviceModel;
using model::ValveLaw;

// "Name(a=1.0, b=2.0)" from the attributes named.
template <class Class>
void add_repr(Class& cls, std::initializer_list<const char*> fields) {
  const std::vector<std::string> names(fields.begin(), fields.end());
  cls.def("__repr__", [names](const py::object& self) {
    std::string out = py::str(py::type::of(self).attr("__name__"));
    out += "(";
    for (std::size_t i = 0; i < names.size(); ++i) {
      out += (i == 0 ? "" : ", ") + names[i] + "=" + std::string(py::repr(self.attr(names[i].c_str())));
    }
    return out + ")";
  });
}

model::ValveMethod valve_method(std::string_view name) {
  if (name == "exact") {
    return model::ValveMethod::exact;
  }
  if (name == "fast") {
    return model::ValveMethod::fast;
  }
  if (name == "wereley_pang") {
    return model::ValveMethod::wereley_pang;
  }
  throw InvalidArgument("method '" + std::string(name) + "': use 'exact', 'fast' or 'wereley_pang'");
}

void bind_parameters(py::module_& m) {
  py::class_<model::FluidParams> fluid(m, "FluidParams", "MR fluid: Carlson's fits (docs/model.md, 1).");
  fluid.def(py::init<>())
      .def_readwrite("volume_fraction", &model::FluidParams::volume_fraction)
      .def_readwrite("carrier_factor", &model::FluidParams::carrier_factor)
      .def_readwrite("viscosity_Pa_s", &model::FluidParams::viscosity_Pa_s)
      .def_readwrite("density_kg_per_m3", &model::FluidParams::density_kg_per_m3);
  add_repr(fluid, {"volume_fraction", "carrier_factor", "viscosity_Pa_s", "density_kg_per_m3"});

  py::class_<model::ValveGeometry> valve(m, "ValveGeometry",
                                         "A slot (gap, width, length) or an annulus (width = pi d).");
  valve
      .def(py::init([](double gap, double width, double length) {
             return model::slot_geometry(gap, width, length);
           }),
           py::arg("gap_m") = 0.5e-3, py::arg("width_m") = 30e-3, py::arg("length_m") = 24.01e-3)
      .def_static(
          "annulus",
          [](double gap, double d, double length) { return model::annulus_geometry(gap, d, length); },
          py::arg("gap_m"), py::arg("mean_diameter_m"), py::arg("length_m"),
          "An annulus of mean diameter d (valid for gap << d).")
      .def_readwrite("gap_m", &model::ValveGeometry::gap_m)
      .def_readwrite("width_m", &model::ValveGeometry::width_m)
      .def_readwrite("length_m", &model::ValveGeometry::length_m)
      .def_readonly("mean_diameter_m", &model::ValveGeometry::mean_diameter_m);
  add_repr(valve, {"gap_m", "width_m", "length_m", "mean_diameter_m"});

  py::class_<model::MembraneParams> membrane(m, "MembraneParams", "The elastomer skin (docs/model.md, 5).");
  membrane.def(py::init<>())
      .def_readwrite("thickness_m", &model::MembraneParams::thickness_m)
      .def_readwrite("youngs_modulus_Pa", &model::MembraneParams::youngs_modulus_Pa)
      .def_readwrite("poisson_ratio", &model::MembraneParams::poisson_ratio)
      .def_readwrite("pretension_N_per_m", &model::MembraneParams::pretension_N_per_m)
      .def_readwrite("hencky_K", &model::MembraneParams::hencky_K);
  add_repr(membrane, {"thickness_m", "youngs_modulus_Pa", "poisson_ratio", "pretension_N_per_m"});

  py::class_<model::MagneticCircuitParams> magnetic(m, "MagneticCircuitParams",
                                                    "The valve's magnetic circuit (docs/model.md, 2).");
  magnetic.def(py::init<>())
      .def_readwrite("turns", &model::MagneticCircuitParams::turns)
      .def_readwrite("fluid_gap_m", &model::MagneticCircuitParams::fluid_gap_m)
      .def_readwrite("spacer_gap_m", &model::MagneticCircuitParams::spacer_gap_m)
      .def_readwrite("pole_area_m2", &model::MagneticCircuitParams::pole_area_m2)
      .def_readwrite("steel_path_length_m", &model::MagneticCircuitParams::steel_path_length_m)
      .def_readwrite("steel_area_m2", &model::MagneticCircuitParams::steel_area_m2);
  add_repr(magnetic, {"turns", "fluid_gap_m", "spacer_gap_m", "pole_area_m2"});

  py::class_<model::CoilParams> coil(m, "CoilParams", "The valve coil and its current-mode driver.");
  coil.def(py::init<>())
      .def_readwrite("resistance_ohm", &model::CoilParams::resistance_ohm)
      .def_readwrite("inductance_H", &model::CoilParams::inductance_H)
      .def_readwrite("max_current_A", &model::CoilParams::max_current_A)
      .def_readwrite("current_resolution_A", &model::CoilParams::current_resolution_A);
  add_repr(coil, {"resistance_ohm", "inductance_H", "max_current_A", "current_resolution_A"});
}

void bind_results(py::module_& m) {
  py::class_<model::GapField> gap(m, "GapField", "The magnetic circuit's operating point at one current.");
  gap.def_readonly("field_A_per_m", &model::GapField::field_A_per_m)
      .def_readonly("flux_density_T", &model::GapField::flux_density_T)
      .def_readonly("steel_flux_density_T", &model::GapField::steel_flux_density_T)
      .def_readonly("steel_polarization_fraction", &model::GapField::steel_polarization_fraction)
      .def_readonly("yield_stress_Pa", &model::GapField::yield_stress_Pa);
  add_repr(gap, {"field_A_per_m", "flux_density_T", "yield_stress_Pa"});

  py::class_<model::CellLoad> load(m, "CellLoad", "A fluid cell under a finger (docs/model.md, 8).");
  load.def_readonly("force_N", &model::CellLoad::force_N)
      .def_readonly("pressure_Pa", &model::CellLoad::pressure_Pa)
      .def_readonly("valve_flow_m3_per_s", &model::CellLoad::valve_flow_m3_per_s)
      .def_readonly("bulge_volume_m3", &model::CellLoad::bulge_volume_m3)
      .def_readonly("membrane_force_N", &model::CellLoad::membrane_force_N)
      .def_readonly("effective_area_m2", &model::CellLoad::effective_area_m2)
      .def_property_readonly("mode", [](const model::CellLoad& l) { return model::to_string(l.mode); });
  add_repr(load, {"force_N", "pressure_Pa", "valve_flow_m3_per_s", "mode"});

  py::class_<model::CellEnvelope> env(m, "CellEnvelope",
                                      "The renderable force range of a cell at one indentation and rate.");
  env.def_readonly("force_min_N", &model::CellEnvelope::force_min_N)
      .def_readonly("force_max_N", &model::CellEnvelope::force_max_N)
      .def_readonly("at_min", &model::CellEnvelope::at_min)
      .def_readonly("at_max", &model::CellEnvelope::at_max);
  add_repr(env, {"force_min_N", "force_max_N"});
}

void bind_profile(py::module_& m) {
  py::class_<model::DeviceProfile> p(m, "Profile",
                                     "A device profile: every parameter of one MR skin (docs/model.md, 9).");
  p.def_readonly("name", &model::DeviceProfile::name)
      .def_readonly("description", &model::DeviceProfile::description)
      .def_readonly("origin", &model::DeviceProfile::origin)
      .def_readonly("rows", &model::DeviceProfile::rows)
      .def_readonly("cols", &model::DeviceProfile::cols)
      .def_readonly("cell_pitch_m", &model::DeviceProfile::cell_pitch_m)
      .def_readonly("cell_depth_m", &model::DeviceProfile::cell_depth_m)
      .def_readonly("fluid", &model::DeviceProfile::fluid)
      .def_readonly("valve", &model::DeviceProfile::valve)
      .def_readonly("magnetic", &model::DeviceProfile::magnetic)
      .def_readonly("core_material", &model::DeviceProfile::core_material)
      .def_readonly("coil", &model::DeviceProfile::coil)
      .def_readonly("membrane", &model::DeviceProfile::membrane)
      .def_readonly("finger_radius_m", &model::DeviceProfile::finger_radius_m)
      .def_readonly("topology", &model::DeviceProfile::topology)
      .def_property_readonly("sensor_count", [](const model::DeviceProfile& d) { return d.sensors.size(); })
      .def_property_readonly("cell_radius_m", &model::DeviceProfile::cell_radius_m);
  add_repr(p, {"name", "rows", "cols", "cell_pitch_m", "origin"});

  m.def(
      "load_profile",
      [](const std::string& name_or_path) { return model::load_profile_with_text(name_or_path).profile; },
      py::arg("name_or_path") = "",
      "A profile by name (searched in profile_search_path()) or by file path; '' or 'default' is\n"
      "mr-skin-5x5. Raises ProfileNotFound (listing where it looked) or InvalidArgument.");
  m.def(
      "profile_text",
      [](const std::string& name_or_path) { return model::load_profile_with_text(name_or_path).text; },
      py::arg("name_or_path") = "", "The TOML text of a profile, as load_profile reads it.");
  m.def("available_profiles", &model::available_profile_names,
        "The profile names in the search path, sorted.");
  m.def("profile_search_path", &model::profile_search_path,
        "Where profile names are looked up, in order ($MRSKIN_PROFILE_PATH first).");
}

void bind_valve(py::module_& m) {
  py::class_<ValveLaw> law(m, "ValveLaw",
                           "Bingham flow through an MR valve (docs/model.md, 4): exact, Wereley-Pang, fast.");
  law.def(py::init<const model::ValveGeometry&, double, double>(), py::arg("geometry"),
          py::arg("viscosity_Pa_s"), py::arg("density_kg_per_m3"))
      .def_property_readonly("geometry", &ValveLaw::geometry)
      .def_property_readonly("viscosity_Pa_s", &ValveLaw::viscosity_Pa_s)
      .def_property_readonly("density_kg_per_m3", &ValveLaw::density_kg_per_m3)
      .def(
          "yield_pressure_Pa",
          [](const ValveLaw& l, const Array& tau) {
            return py::vectorize([&l](double t) { return l.yield_pressure_Pa(t); })(tau);
          },
          py::arg("yield_stress_Pa"), "dp_y = 2 tau_y L / h, Pa.")
      .def(
          "flow_m3_per_s",
          [](const ValveLaw& l, const Array& dp, const Array& tau, std::string_view method) {
            const model::ValveMethod vm = valve_method(method);
            return py::vectorize([&l, vm](double p, double t) {
              return value_or_throw(l.flow_m3_per_s(p, t, vm), "ValveLaw.flow_m3_per_s");
            })(dp, tau);
          },
          py::arg("dp_Pa"), py::arg("yield_stress_Pa"), py::arg("method") = "exact",
          "Pressure drop to flow, m^3/s (0 while |dp| <= dp_y). method: 'exact', 'fast' or\n"
          "'wereley_pang' (the approximations inverted by bisection). Floats or arrays.")
      .def(
          "pressure_Pa",
          [](const ValveLaw& l, const Array& q, const Array& tau, std::string_view method) {
            const model::ValveMethod vm = valve_method(method);
            return py::vectorize([&l, vm](double f, double t) {
              return value_or_throw(l.pressure_Pa(f, t, vm), "ValveLaw.pressure_Pa");
            })(q, tau);
          },
          py::arg("flow_m3_per_s"), py::arg("yield_stress_Pa"), py::arg("method") = "exact",
          "Flow to pressure drop, Pa (odd in Q; Q = 0 gives dp_y). method: 'exact' (safeguarded\n"
          "Newton), 'fast' (the loop's tabulated law) or 'wereley_pang'. Floats or arrays.")
      .def(
          "reynolds_number",
          [](const ValveLaw& l, const Array& q) {
            return py::vectorize([&l](double f) { return l.reynolds_number(f); })(q);
          },
          py::arg("flow_m3_per_s"), "Re = rho V D_h / mu.");
}

void bind_laws(py::module_& m) {
  m.def(
      "yield_stress_Pa",
      [](const model::FluidParams& f, const Array& h) {
        return py::vectorize(
            [&f](double x) { return value_or_throw(model::yield_stress_Pa(f, x), "yield_stress_Pa"); })(h);
      },
      py::arg("fluid"), py::arg("field_A_per_m"), "Carlson's tau_y(H), Pa (even in H).");
  m.def(
      "fluid_flux_density_T",
      [](const model::FluidParams& f, const Array& h) {
        return py::vectorize([&f](double x) {
          return value_or_throw(model::fluid_flux_density_T(f, x), "fluid_flux_density_T");
        })(h);
      },
      py::arg("fluid"), py::arg("field_A_per_m"), "Carlson's B(H) in the fluid, T (odd in H).");
  m.def("saturated_yield_stress_Pa", &model::saturated_yield_stress_Pa, py::arg("fluid"),
        "C * 271700 * phi^1.5239, Pa.");
  m.def(
      "gap_field",
      [](const model::MagneticCircuitParams& mc, const model::FluidParams& f, double current_A) {
        return value_or_throw(model::gap_field(mc, f, current_A), "gap_field");
      },
      py::arg("magnetic"), py::arg("fluid"), py::arg("current_A"),
      "The circuit's operating point (anhysteretic) at a coil current.");
  m.def("bending_stiffness_N_m", &model::bending_stiffness_N_m, py::arg("membrane"),
        "D = E t^3 / (12 (1 - nu^2)), N m.");
  m.def(
      "point_load_force_N",
      [](const model::MembraneParams& mp, double radius_m, double contact_radius_m, const Array& d) {
        return py::vectorize([&mp, radius_m, contact_radius_m](double x) {
          return value_or_throw(model::point_load_force_N(mp, radius_m, contact_radius_m, x),
                                "point_load_force_N")
              .total;
        })(d);
      },
      py::arg("membrane"), py::arg("radius_m"), py::arg("contact_radius_m"), py::arg("centre_deflection_m"),
      "Central load through a contact of radius c on a clamped circular sheet, N.");
  m.def(
      "disk_pressure_Pa",
      [](const model::MembraneParams& mp, double radius_m, const Array& w) {
        return py::vectorize([&mp, radius_m](double x) {
          return value_or_throw(model::disk_pressure_Pa(mp, radius_m, x), "disk_pressure_Pa");
        })(w);
      },
      py::arg("membrane"), py::arg("radius_m"), py::arg("centre_deflection_m"),
      "Uniform pressure on a clamped circular sheet for a centre deflection, Pa.");
}

std::vector<double> currents_of(const DeviceModel& dm, const Array& a) {
  const py::buffer_info b = a.request();
  if (b.ndim != 1 || static_cast<std::size_t>(b.shape[0]) != dm.layout().valve_count()) {
    throw InvalidArgument("valve_current_A: one current per valve (" +
                          std::to_string(dm.layout().valve_count()) + " for this profile)");
  }
  const auto* p = static_cast<const double*>(b.ptr);
  return {p, p + b.shape[0]};
}

void bind_device_model(py::module_& m) {
  py::class_<DeviceModel> dm(m, "DeviceModel", "The laws of one profile, assembled (device_model.hpp).");
  dm.def(py::init<model::DeviceProfile>(), py::arg("profile"))
      .def_property_readonly("profile", &DeviceModel::profile)
      .def_property_readonly("valve_law", &DeviceModel::valve_law,
                             py::return_value_policy::reference_internal)
      .def_property_readonly("fluid_cell_count",
                             [](const DeviceModel& d) { return d.layout().fluid_cell_count(); })
      .def_property_readonly("valve_count", [](const DeviceModel& d) { return d.layout().valve_count(); })
      .def(
          "fluid_cell_index",
          [](const DeviceModel& d, int row, int col) {
            return value_or_throw(d.fluid_cell_index(row, col), "fluid_cell_index");
          },
          py::arg("row"), py::arg("col"), "The fluid cell at (row, col) (row + col even).")
      .def(
          "gap_field",
          [](const DeviceModel& d, double i) { return value_or_throw(d.gap_field(i), "gap_field"); },
          py::arg("current_A"), "The exact magnetic circuit at a coil current.")
      .def(
          "yield_stress_at_current_Pa",
          [](const DeviceModel& d, const Array& i) {
            return py::vectorize([&d](double x) {
              return value_or_throw(d.yield_stress_at_current_Pa(x), "yield_stress_at_current_Pa");
            })(i);
          },
          py::arg("current_A"), "The tabulated tau_y(I), Pa, for I in [0, max_current_A].")
      .def(
          "cell_force",
          [](const DeviceModel& d, std::size_t cell, double depth, double rate, const Array& currents) {
            const std::vector<double> i = currents_of(d, currents);
            return value_or_throw(d.cell_force(cell, depth, rate, i), "cell_force");
          },
          py::arg("cell"), py::arg("indentation_m"), py::arg("velocity_m_per_s"), py::arg("valve_current_A"),
          "The quasi-static load on a fluid cell with one current per valve (A).")
      .def(
          "cell_force_uniform",
          [](const DeviceModel& d, std::size_t cell, double depth, double rate, double current) {
            return value_or_throw(d.cell_force_uniform(cell, depth, rate, current), "cell_force_uniform");
          },
          py::arg("cell"), py::arg("indentation_m"), py::arg("velocity_m_per_s"), py::arg("current_A"),
          "The same with every valve at one current.")
      .def(
          "envelope",
          [](const DeviceModel& d, std::size_t cell, double depth, double rate) {
            return value_or_throw(d.envelope(cell, depth, rate), "envelope");
          },
          py::arg("cell"), py::arg("indentation_m"), py::arg("velocity_m_per_s") = 0.0,
          "F_min (valves open) and F_max (valves at max_current_A) at (d, v).")
      .def(
          "current_for_force_A",
          [](const DeviceModel& d, std::size_t cell, double depth, double rate, double force) {
            return value_or_throw(d.current_for_force_A(cell, depth, rate, force), "current_for_force_A");
          },
          py::arg("cell"), py::arg("indentation_m"), py::arg("velocity_m_per_s"), py::arg("force_N"),
          "The uniform current rendering a force while loading; ModelError out_of_range outside\n"
          "the envelope.");
}

}  // namespace

void bind_model(py::module_& m) {
  bind_parameters(m);
  bind_results(m);
  bind_profile(m);
  bind_valve(m);
  bind_laws(m);
  bind_device_model(m);
}

}  // namespace mrskin::python
