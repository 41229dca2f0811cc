// mrskin.device: one unit by URI. A service thread polls the session every millisecond (its
// heartbeat keeps the unit enabled); Python's calls take the session's mutex with the GIL released.
#include "mrskin/driver/device.hpp"

#include <pybind11/numpy.h>
#include <pybind11/stl.h>

#include <algorithm>
#include <cctype>
#include <chrono>
#include <condition_variable>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "bindings.hpp"
#include "mrskin/driver/model/calibration.hpp"
#include "mrskin/sim/fingertip.hpp"
#include "mrskin/sim/open_mock.hpp"

namespace mrskin::python {

namespace {

using Array = py::array_t<double, py::array::forcecast>;
using namespace std::chrono_literals;

py::array_t<double> to_array(const std::vector<double>& v) {
  return py::array_t<double>(static_cast<py::ssize_t>(v.size()), v.data());
}

class Device {
 public:
  Device(const std::string& uri, double time_scale) {
    OpenOptions options;
    options.session.time_scale = time_scale;
    dev_ = open_device(uri, clock_, options);
    mock_ = sim::mock_of(dev_);
    sensors_.assign(dev_.session->info().sensors, 0.0);
    service_ = std::thread([this] { serve(); });
  }
  Device(const Device&) = delete;
  Device& operator=(const Device&) = delete;
  Device(Device&&) = delete;
  Device& operator=(Device&&) = delete;
  ~Device() { close(); }

  void close() noexcept {
    {
      const std::lock_guard<std::mutex> lock(mutex_);
      stop_ = true;
    }
    if (service_.joinable()) {
      service_.join();
    }
    if (mock_) {
      mock_->stop();
    }
    dev_.session.reset();
    mock_.reset();
    dev_ = {};
  }

  [[nodiscard]] DeviceSession& session() const {
    if (!dev_.session) {
      throw Error("the device is closed: open it again with mrskin.open_device(uri)");
    }
    return *dev_.session;
  }

  [[nodiscard]] py::dict info() const {
    const DeviceInfo& i = session().info();
    py::dict d;
    d["protocol_version"] = py::make_tuple(i.protocol_major, i.protocol_minor);
    d["firmware"] = i.firmware;
    d["serial"] = i.serial;
    d["rows"] = i.rows;
    d["cols"] = i.cols;
    d["fluid_cells"] = i.fluid_cells;
    d["valves"] = i.valves;
    d["sensors"] = i.sensors;
    d["current_lsb_A"] = i.current_lsb_A;
    d["max_current_A"] = i.max_current_A;
    d["sensor_lsb"] = i.sensor_lsb;
    d["sensor_quantity"] = i.sensor_quantity;
    d["sensor_unit"] = i.sensor_unit;
    d["sensor_deadband_counts"] = i.sensor_deadband_counts;  // protocol 1.2: readings up to this stale
    d["heartbeat_timeout_s"] = i.heartbeat_timeout_s;
    d["telemetry_rate_hz"] = i.telemetry_rate_hz;
    return d;
  }

  // A state request, then a wait (GIL released, Ctrl-C honoured) until the status confirms it.
  void request(ResultCode (DeviceSession::*call)() noexcept, DeviceState want, const char* name,
               double timeout_s) {
    {
      const py::gil_scoped_release release;
      std::unique_lock<std::mutex> lock(mutex_);
      check_result((session().*call)(), name);
      const auto deadline = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
      while (session().state() != want) {
        if (std::chrono::steady_clock::now() >= deadline) {
          throw Timeout(std::string(name) + ": the device did not confirm within " +
                        std::to_string(timeout_s) + " s (state " + to_string(session().state()) +
                        "); check the link, or raise timeout_s");
        }
        changed_.wait_for(lock, 20ms);
        lock.unlock();
        check_signals();
        lock.lock();
      }
    }
  }

  void set_valve_currents(const Array& currents) {
    const py::buffer_info b = currents.request();
    const std::size_t valves = session().info().valves;
    if (b.ndim != 1 || static_cast<std::size_t>(b.shape[0]) != valves) {
      throw InvalidArgument("current_A: one current per valve (" + std::to_string(valves) + " on this unit)");
    }
    const std::span<const double> span(static_cast<const double*>(b.ptr), valves);
    const py::gil_scoped_release release;
    const std::lock_guard<std::mutex> lock(mutex_);
    check_result(session().send_valve_currents(span), "set_valve_currents");
  }

  py::tuple sensors() {
    std::vector<double> copy;
    std::uint32_t at_us = 0;
    {
      const py::gil_scoped_release release;
      const std::lock_guard<std::mutex> lock(mutex_);
      copy = sensors_;
      at_us = sensor_time_us_;
    }
    return py::make_tuple(at_us, to_array(copy));
  }

  py::tuple wait_telemetry(double timeout_s) {
    {
      const py::gil_scoped_release release;
      std::unique_lock<std::mutex> lock(mutex_);
      const std::uint64_t seen = telemetry_;
      const auto deadline = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
      while (telemetry_ == seen) {
        if (std::chrono::steady_clock::now() >= deadline) {
          throw Timeout("wait_telemetry: no telemetry within " + std::to_string(timeout_s) +
                        " s; check the link (mrskinctl monitor) or raise timeout_s");
        }
        changed_.wait_for(lock, 20ms);
        lock.unlock();
        check_signals();
        lock.lock();
      }
    }
    return sensors();
  }

  template <class Get>
  auto locked(Get get) {
    const py::gil_scoped_release release;
    const std::lock_guard<std::mutex> lock(mutex_);
    return get(session());
  }

  [[nodiscard]] bool is_mock() const noexcept { return mock_ != nullptr; }

  sim::MockDevice& mock() {
    if (!mock_) {
      throw InvalidArgument("this is not a simulated unit: only mock:// has a finger and a truth");
    }
    return *mock_;
  }

 private:
  void serve() noexcept {
    std::unique_lock<std::mutex> lock(mutex_);
    while (!stop_) {
      (void)dev_.session->poll(clock_.now());
      const std::uint64_t n = dev_.session->counters().telemetry;
      if (n != telemetry_) {
        const std::span<const double> s = dev_.session->sensors();
        std::copy(s.begin(), s.end(), sensors_.begin());
        sensor_time_us_ = dev_.session->sensor_device_time_us();
        telemetry_ = n;
      }
      changed_.notify_all();
      lock.unlock();
      std::this_thread::sleep_for(1ms);
      lock.lock();
    }
  }

  MonotonicClock clock_;
  OpenedDevice dev_;
  std::shared_ptr<sim::MockDevice> mock_;
  std::mutex mutex_;
  std::condition_variable changed_;
  std::vector<double> sensors_;
  std::uint32_t sensor_time_us_ = 0;
  std::uint64_t telemetry_ = 0;
  bool stop_ = false;
  std::thread service_;
};

py::dict counters_of(const SessionCounters& c) {
  const std::pair<const char*, std::uint64_t> counts[] = {
      {"sent", c.sent},
      {"received", c.received},
      {"telemetry", c.telemetry},
      {"crc_errors", c.crc_errors},
      {"decode_errors", c.decode_errors},
      {"sequence_gaps", c.sequence_gaps},
      {"invalid_commands", c.invalid_commands},
      {"telemetry_timeouts", c.telemetry_timeouts},
      {"disconnects", c.disconnects},
      {"reconnects", c.reconnects},
      {"faults", c.faults},
  };
  py::dict d;
  for (const auto& [name, count] : counts) {
    d[name] = count;
  }
  return d;
}

void bind_calibration(py::module_& m) {
  py::class_<model::Calibration> c(m, "Calibration",
                                   "A unit's calibration: measured / nominal ratios (calibration.hpp).");
  c.def_readonly("version", &model::Calibration::version)
      .def_readonly("serial", &model::Calibration::serial)
      .def_readonly("profile", &model::Calibration::profile)
      .def_readonly("viscosity_scale", &model::Calibration::viscosity_scale)
      .def_readonly("yield_scale", &model::Calibration::yield_scale)
      .def_readonly("membrane_modulus_scale", &model::Calibration::membrane_modulus_scale)
      .def_readonly("membrane_pretension_scale", &model::Calibration::membrane_pretension_scale)
      .def_readonly("reservoir_compliance_scale", &model::Calibration::reservoir_compliance_scale)
      .def_readonly("turns_scale", &model::Calibration::turns_scale)
      .def_readonly("gap_scale", &model::Calibration::gap_scale)
      .def_property_readonly("valve_yield_gain",
                             [](const model::Calibration& k) { return to_array(k.valve_yield_gain); })
      .def_property_readonly("sensor_offset",
                             [](const model::Calibration& k) { return to_array(k.sensor_offset); })
      .def_readonly("sensor_offset_unit", &model::Calibration::sensor_offset_unit);
}

void bind_commands(py::class_<Device>& d) {
  d.def(
       "enable",
       [](Device& self, double timeout_s) {
         self.request(&DeviceSession::request_enable, DeviceState::enabled, "enable", timeout_s);
       },
       py::arg("timeout_s") = 1.0, "Enables the unit (re-seeding its commands) and waits for its status.")
      .def(
          "disable",
          [](Device& self, double timeout_s) {
            self.request(&DeviceSession::request_disable, DeviceState::disabled, "disable", timeout_s);
          },
          py::arg("timeout_s") = 1.0, "Disables the unit (valves released) and waits for its status.")
      .def(
          "estop",
          [](Device& self, double timeout_s) {
            self.request(&DeviceSession::request_estop, DeviceState::fault, "estop", timeout_s);
          },
          py::arg("timeout_s") = 1.0, "Emergency stop: the unit latches FAULT until enable().")
      .def("set_valve_currents", &Device::set_valve_currents, py::arg("current_A"),
           "One coil current per valve, A (the unit must be enabled). NaN, Inf or out of range:\n"
           "ResultError with code 'invalid_value', nothing sent.");
}

}  // namespace

void bind_device(py::module_& m) {
  bind_calibration(m);
  py::class_<Device> d(m, "Device", "An open unit. Use as a context manager, or call close().");
  d.def_property_readonly("info", &Device::info, "Identity and limits, SI units (DeviceInfo).")
      .def_property_readonly("is_mock", &Device::is_mock, "True for mock:// (a simulated unit).")
      .def_property_readonly(
          "state",
          [](Device& self) {
            std::string name = to_string(self.locked([](DeviceSession& s) { return s.state(); }));
            std::transform(name.begin(), name.end(), name.begin(),
                           [](unsigned char c) { return std::tolower(c); });
            return name;
          },
          "'disabled', 'enabled', 'paused' or 'fault'.")
      .def_property_readonly(
          "profile", [](Device& self) { return self.locked([](DeviceSession& s) { return *s.profile(); }); },
          "The profile read from the unit's configuration memory (mrskin.model.Profile).")
      .def_property_readonly(
          "calibration_text",
          [](Device& self) { return self.locked([](DeviceSession& s) { return s.info().calibration; }); },
          "The calibration text stored on the unit.")
      .def(
          "calibration",
          [](Device& self) {
            return self.locked([](DeviceSession& s) {
              const DeviceInfo& i = s.info();
              return model::parse_calibration(i.calibration, "device calibration", i.valves, i.sensors);
            });
          },
          "The stored calibration, parsed (mrskin.device.Calibration).")
      .def("sensors", &Device::sensors,
           "(device_time_us, readings): the latest telemetry, in info['sensor_unit'].")
      .def("wait_telemetry", &Device::wait_telemetry, py::arg("timeout_s") = 1.0,
           "Blocks (GIL released) for the next telemetry packet; returns it like sensors().")
      .def(
          "commanded_currents_A",
          [](Device& self) {
            return to_array(self.locked([](DeviceSession& s) {
              const std::span<const double> c = s.commanded_currents();
              return std::vector<double>(c.begin(), c.end());
            }));
          },
          "The currents as last sent (or re-seeded), A.")
      .def(
          "counters",
          [](Device& self) {
            return counters_of(self.locked([](DeviceSession& s) { return s.counters(); }));
          },
          "The session's counters (sent, received, telemetry, errors...).");
  bind_commands(d);
  d.def(
       "press_finger",
       [](Device& self, double row, double col, double depth_m) {
         sim::MockDevice& mock = self.mock();
         std::vector<double> depth(mock.layout().fluid_cell_count());
         sim::press_fingertip(mock.layout(), row, col, depth_m, depth);
         mock.set_finger_indentation(depth);
       },
       py::arg("row"), py::arg("col"), py::arg("depth_m"),
       "mock:// only: the simulated fingertip pressed depth_m deep centred at (row, col), cells.")
      .def(
          "true_force_N",
          [](Device& self) {
            sim::MockDevice& mock = self.mock();
            std::vector<double> f(mock.layout().fluid_cell_count());
            mock.true_contact_forces(f);
            return to_array(f);
          },
          "mock:// only: the plant's true contact force per fluid cell, N (no hardware knows it).")
      .def("close", &Device::close, "Stops the service thread and closes the session (idempotent).")
      .def("__enter__", [](Device& self) -> Device& { return self; })
      .def("__exit__", [](Device& self, const py::args&) { self.close(); });

  m.def(
      "open_device",
      [](const std::string& uri, double time_scale) {
        const py::gil_scoped_release release;
        return std::make_unique<Device>(uri, time_scale);
      },
      py::arg("uri") = "mock://", py::arg("time_scale") = 1.0,
      "Opens a unit: mock://PROFILE[?seed=N&...], hid://VID:PID, usb://VID:PID, can://IFACE?node=N\n"
      "(docs/api.md). Raises InvalidArgument (bad URI), ProfileNotFound, DeviceNotFound,\n"
      "PermissionDenied, ProtocolMismatch, DeviceBusy or Timeout; each message says what to do.");
}

}  // namespace mrskin::python
