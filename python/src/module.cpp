// The Python module mrskin: the device model, the device and the bridge (docs/python.md).
#include <pybind11/pybind11.h>

#include <string>

#include "bindings.hpp"
#include "mrskin/driver/version.hpp"
#include "mrskin/sim/open_mock.hpp"

namespace py = pybind11;

PYBIND11_MODULE(mrskin, m) {
  m.doc() =
      "mrskin: the MR skin tactile display from Python (docs/python.md).\n\n"
      "  mrskin.model   the device model: valve flow (exact, fast), field, fluid, membrane, cell\n"
      "                 force and the renderable envelope; profiles (load, inspect, list)\n"
      "  mrskin.device  open_device(uri): identity, telemetry, enable/disable/estop, valve\n"
      "                 currents, calibration\n"
      "  mrskin.bridge  a scene or a recorded stream on the simulated clock (statistics as a dict),\n"
      "                 or in real time with a Python callback at a decimated rate\n\n"
      "SI units, the unit in every name (force_N, current_A). Setup errors raise the classes\n"
      "below, mirroring the C++ ones; every blocking call releases the GIL.";
  m.attr("__version__") = std::string(mrskin::library_version());
  m.attr("protocol_version") =
      py::make_tuple(mrskin::protocol_version_major(), mrskin::protocol_version_minor());
  mrskin::sim::register_mock_scheme();  // mock:// (the simulated unit)

  mrskin::python::bind_errors(m);
  // `import mrskin.model` works as well as `mrskin.model`.
  const py::dict modules = py::module_::import("sys").attr("modules");
  py::module_ model = m.def_submodule("model", "The device model's laws and profiles (docs/model.md).");
  mrskin::python::bind_model(model);
  modules["mrskin.model"] = model;
  py::module_ device =
      m.def_submodule("device", "One unit by URI (docs/api.md): mock://, hid://, usb://, can://.");
  mrskin::python::bind_device(device);
  modules["mrskin.device"] = device;
  m.attr("open_device") = device.attr("open_device");
  py::module_ bridge =
      m.def_submodule("bridge", "The bridge: scenes and recorded streams, simulated or in real time.");
  mrskin::python::bind_bridge(bridge);
  modules["mrskin.bridge"] = bridge;
}
