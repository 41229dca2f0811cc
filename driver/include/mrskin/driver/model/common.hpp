// Shared vocabulary of the device model (mrskin::model): status codes, results and constants.
//
// Every law is a pure function of SI inputs. A law that can fail returns a Result whose
// status says why; none of the laws meant for the real-time path (valve laws, fluid, coil,
// membrane, cell force, envelope) throws or allocates. Only profile loading throws
// (mrskin::InvalidArgument, at setup).
#pragma once

namespace mrskin::model {

enum class Status : unsigned char {
  ok = 0,
  not_finite,      // an input is NaN or infinite
  negative,        // an input that must be >= 0 (yield stress, deflection, radius...) is negative
  out_of_range,    // an input outside the law's domain (a current above the coil's limit, a cell index...)
  degenerate,      // a geometry or parameter that makes the law meaningless (zero gap, zero viscosity)
  out_of_regime,   // value computed, but the law is outside the regime it is valid in (paper's Eq. 6)
  no_convergence,  // a safeguarded solve hit its iteration cap (never seen in tests; reported, not hidden)
  overflow,        // the result is not representable as a finite double
};

constexpr const char* to_string(Status s) noexcept {
  switch (s) {
    case Status::ok:
      return "ok";
    case Status::not_finite:
      return "input is NaN or infinite";
    case Status::negative:
      return "input must not be negative";
    case Status::out_of_range:
      return "input outside the law's domain";
    case Status::degenerate:
      return "degenerate geometry or parameters";
    case Status::out_of_regime:
      return "law used outside its regime";
    case Status::no_convergence:
      return "solver did not converge";
    case Status::overflow:
      return "result overflows";
  }
  return "unknown";
}

// A value and the status it was computed with. `value` is meaningful when ok(), and also for
// Status::out_of_regime (computed, but not trustworthy); otherwise it is 0.
template <class T>
struct Result {
  T value{};
  Status status = Status::ok;
  [[nodiscard]] constexpr bool ok() const noexcept { return status == Status::ok; }
};

template <class T>
constexpr Result<T> failure(Status s) noexcept {
  return Result<T>{T{}, s};
}

// Vacuum permeability, H/m (CODATA 2018).
inline constexpr double kMu0_H_per_m = 1.25663706212e-6;
inline constexpr double kPi = 3.14159265358979323846;
// Reynolds number above which the valve law adds a turbulent term.
inline constexpr double kCriticalReynolds = 2300.0;

}  // namespace mrskin::model
