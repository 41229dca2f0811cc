// Python exception classes mirroring mrskin's typed setup errors (driver/.../errors.hpp), plus
// ModelError (a law's Status) and ResultError (a device call's ResultCode).
#include <Python.h>

#include <exception>
#include <string>

#include "bindings.hpp"

namespace mrskin::python {

namespace {

// The classes, created once at import and kept for the interpreter's life.
struct ExceptionTypes {
  py::handle error;
  py::handle invalid_argument;
  py::handle profile_not_found;
  py::handle device_not_found;
  py::handle permission_denied;
  py::handle protocol_mismatch;
  py::handle device_busy;
  py::handle timeout;
  py::handle model_error;
  py::handle result_error;
};

ExceptionTypes& types() {
  static ExceptionTypes t;
  return t;
}

py::handle make_type(py::module_& m, const char* name, const py::tuple& bases, const char* doc) {
  const std::string qualified = std::string("mrskin.") + name;
  PyObject* type = PyErr_NewExceptionWithDoc(qualified.c_str(), doc, bases.ptr(), nullptr);
  if (type == nullptr) {
    throw py::error_already_set();
  }
  m.add_object(name, py::handle(type));  // the module keeps a reference; so does types()
  return {type};
}

void raise(py::handle type, const char* what) { PyErr_SetString(type.ptr(), what); }

void raise_with(py::handle type, const char* what, const char* attr, const char* value) {
  const py::object exc = py::reinterpret_borrow<py::object>(type)(what);
  exc.attr(attr) = value;
  PyErr_SetObject(type.ptr(), exc.ptr());
}

void translate(const std::exception_ptr& p) {
  const ExceptionTypes& t = types();
  try {
    if (p) {
      std::rethrow_exception(p);
    }
  } catch (const ModelFailure& e) {
    raise_with(t.model_error, e.what(), "status", status_name(e.status()));
  } catch (const ResultFailure& e) {
    raise_with(t.result_error, e.what(), "code", result_code_name(e.code()));
  } catch (const ProfileNotFound& e) {
    raise(t.profile_not_found, e.what());
  } catch (const InvalidArgument& e) {
    raise(t.invalid_argument, e.what());
  } catch (const DeviceNotFound& e) {
    raise(t.device_not_found, e.what());
  } catch (const PermissionDenied& e) {
    raise(t.permission_denied, e.what());
  } catch (const ProtocolMismatch& e) {
    raise(t.protocol_mismatch, e.what());
  } catch (const DeviceBusy& e) {
    raise(t.device_busy, e.what());
  } catch (const Timeout& e) {
    raise(t.timeout, e.what());
  } catch (const Error& e) {
    raise(t.error, e.what());
  }
}

}  // namespace

const char* status_name(model::Status s) noexcept {
  switch (s) {
    case model::Status::ok:
      return "ok";
    case model::Status::not_finite:
      return "not_finite";
    case model::Status::negative:
      return "negative";
    case model::Status::out_of_range:
      return "out_of_range";
    case model::Status::degenerate:
      return "degenerate";
    case model::Status::out_of_regime:
      return "out_of_regime";
    case model::Status::no_convergence:
      return "no_convergence";
    case model::Status::overflow:
      return "overflow";
  }
  return "unknown";
}

const char* result_code_name(ResultCode c) noexcept {
  switch (c) {
    case ResultCode::ok:
      return "ok";
    case ResultCode::would_block:
      return "would_block";
    case ResultCode::not_open:
      return "not_open";
    case ResultCode::invalid_value:
      return "invalid_value";
    case ResultCode::device_fault:
      return "device_fault";
    case ResultCode::disconnected:
      return "disconnected";
    case ResultCode::stale:
      return "stale";
  }
  return "unknown";
}

void check_result(ResultCode rc, const char* call) {
  if (rc != ResultCode::ok) {
    throw ResultFailure(std::string(call) + ": " + to_string(rc), rc);
  }
}

void check_signals() {
  const py::gil_scoped_acquire gil;
  if (PyErr_CheckSignals() != 0) {
    throw py::error_already_set();
  }
}

void bind_errors(py::module_& m) {
  ExceptionTypes& t = types();
  const py::handle runtime(PyExc_RuntimeError);
  t.error = make_type(m, "Error", py::make_tuple(runtime),
                      "Base of every mrskin error (C++ mrskin::Error). The message says what to do.");
  t.invalid_argument = make_type(m, "InvalidArgument", py::make_tuple(t.error, py::handle(PyExc_ValueError)),
                                 "A URI, option, profile value or input that cannot be used "
                                 "(mrskin::InvalidArgument).");
  t.profile_not_found = make_type(m, "ProfileNotFound", py::make_tuple(t.invalid_argument),
                                  "A profile name in none of the profile directories; the message lists "
                                  "the search path and the names there (mrskin::ProfileNotFound).");
  t.device_not_found = make_type(m, "DeviceNotFound", py::make_tuple(t.error),
                                 "No device answers at the given address (mrskin::DeviceNotFound).");
  t.permission_denied =
      make_type(m, "PermissionDenied", py::make_tuple(t.error, py::handle(PyExc_PermissionError)),
                "The OS refused access: udev rule, group, capability (mrskin::PermissionDenied).");
  t.protocol_mismatch = make_type(m, "ProtocolMismatch", py::make_tuple(t.error),
                                  "The device speaks another protocol version; the message names both.");
  t.device_busy = make_type(m, "DeviceBusy", py::make_tuple(t.error),
                            "Another process or session owns the device (mrskin::DeviceBusy).");
  t.timeout = make_type(m, "Timeout", py::make_tuple(t.error, py::handle(PyExc_TimeoutError)),
                        "The device did not answer in time during setup (mrskin::Timeout).");
  t.model_error = make_type(m, "ModelError", py::make_tuple(t.invalid_argument),
                            "A model law refused its inputs; .status is the C++ mrskin::model::Status "
                            "name ('not_finite' for NaN or Inf, 'negative', 'out_of_range', ...).");
  t.result_error = make_type(m, "ResultError", py::make_tuple(t.error),
                             "A device call returned a ResultCode other than ok; .code is its name "
                             "('invalid_value' for NaN, Inf or out of range: nothing was sent).");
  // pybind11's translator type takes the pointer by value.
  py::register_exception_translator(
      [](std::exception_ptr p) { translate(p); });  // NOLINT(performance-unnecessary-value-param)
}

}  // namespace mrskin::python
