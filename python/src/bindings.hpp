// The pieces of the Python module mrskin (docs/python.md), one function per submodule.
#pragma once

#include <pybind11/pybind11.h>

#include <stdexcept>
#include <string>

#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/model/common.hpp"

namespace mrskin::python {

namespace py = pybind11;

// A law's Status other than ok (and out_of_regime, whose value is returned): raised as
// mrskin.ModelError with .status, a subclass of mrskin.InvalidArgument.
class ModelFailure : public InvalidArgument {
 public:
  ModelFailure(const std::string& what, model::Status status) : InvalidArgument(what), status_(status) {}
  [[nodiscard]] model::Status status() const noexcept { return status_; }

 private:
  model::Status status_;
};

// A device call's ResultCode other than ok: raised as mrskin.ResultError with .code.
class ResultFailure : public Error {
 public:
  ResultFailure(const std::string& what, ResultCode code) : Error(what), code_(code) {}
  [[nodiscard]] ResultCode code() const noexcept { return code_; }

 private:
  ResultCode code_;
};

// The status's name as in C++ ("not_finite").
const char* status_name(model::Status s) noexcept;
const char* result_code_name(ResultCode c) noexcept;

// The value of a law's result, or ModelFailure naming the law (out_of_regime: the value).
template <class T>
T value_or_throw(const model::Result<T>& r, const char* law) {
  if (r.ok() || r.status == model::Status::out_of_regime) {
    return r.value;
  }
  throw ModelFailure(std::string(law) + ": " + model::to_string(r.status), r.status);
}
// Nothing, or ResultFailure naming the call.
void check_result(ResultCode rc, const char* call);

// Called without the GIL: takes it, runs Python's signal handlers (Ctrl-C raises
// KeyboardInterrupt there) and throws py::error_already_set if one raised.
void check_signals();

void bind_errors(py::module_& m);
void bind_model(py::module_& m);
void bind_device(py::module_& m);
void bind_bridge(py::module_& m);

}  // namespace mrskin::python
