// Every law returns a finite value or an explicit error for any input, and never refuses a
// valid one (rapidcheck). Seed fixed so runs repeat; RC_PARAMS overrides, e.g.
//   RC_PARAMS="seed=7 max_success=20000" build/release/tests/model/mrskin_model_property_test
#include <gtest/gtest.h>
#include <rapidcheck.h>
#include <rapidcheck/gtest.h>

#include <cmath>
#include <cstdlib>
#include <limits>
#include <string>

#include "mrskin/driver/model/device_model.hpp"

namespace {

using namespace mrskin::model;

const bool kSeedSet = [] {
  setenv("RC_PARAMS", "seed=20240601 max_success=300", 0);
  return true;
}();

// Any double: specials, signed zeros, subnormals, huge and tiny magnitudes, ordinary values.
rc::Gen<double> any_double() {
  const double inf = std::numeric_limits<double>::infinity();
  return rc::gen::oneOf(
      rc::gen::element(std::nan(""), inf, -inf, 0.0, -0.0, std::numeric_limits<double>::denorm_min(),
                       std::numeric_limits<double>::max(), std::numeric_limits<double>::lowest(), 1e-300,
                       -1e-300),
      rc::gen::arbitrary<double>(),
      rc::gen::map(rc::gen::pair(rc::gen::inRange(-320, 309), rc::gen::inRange(-1000, 1000)),
                   [](auto p) { return static_cast<double>(p.second) / 100.0 * std::pow(10.0, p.first); }));
}

// Log-uniform in [lo, hi].
rc::Gen<double> log_uniform(double lo, double hi) {
  return rc::gen::map(rc::gen::inRange(0, 1000001),
                      [lo, hi](int k) { return lo * std::pow(hi / lo, static_cast<double>(k) / 1e6); });
}
rc::Gen<double> uniform(double lo, double hi) {
  return rc::gen::map(rc::gen::inRange(0, 1000001), [lo, hi](int k) { return lo + (hi - lo) * k / 1e6; });
}

template <class T>
void finite_or_error(const Result<T>& r, double v) {
  if (r.ok()) {
    RC_ASSERT(std::isfinite(v));
  } else {
    RC_ASSERT(r.status != Status::ok);
  }
}

const ValveLaw& valve() {
  static const ValveLaw v(slot_geometry(0.5e-3, 30e-3, 24.01e-3), 0.112, 3050.0);
  return v;
}

const DeviceModel& model() {
  static const DeviceModel m(load_profile(std::string(MRSKIN_TEST_PROFILE_DIR) + "/mr-skin-5x5.toml"));
  return m;
}

RC_GTEST_PROP(ModelProperty, ValveLawsAreFiniteOrExplicitErrors, ()) {
  const double a = *any_double();
  const double tau = *any_double();
  for (const ValveMethod m : {ValveMethod::exact, ValveMethod::fast, ValveMethod::wereley_pang}) {
    const Result<double> p = valve().pressure_Pa(a, tau, m);
    finite_or_error(p, p.value);
    // Valid and representable (the turbulent term grows like Q^2): never refused.
    if (std::isfinite(a) && std::isfinite(tau) && tau >= 0.0 && std::fabs(a) < 1e100 && tau < 1e200) {
      RC_ASSERT(p.ok());
    }
  }
  const Result<FlowPoint> f = valve().flow_point(a, tau);
  finite_or_error(f, f.value.flow_m3_per_s);
  if (std::isfinite(a) && std::isfinite(tau) && tau >= 0.0) {
    // Valid: computed, unless the flow itself is not representable (|dp| near DBL_MAX).
    RC_ASSERT(f.ok() || (f.status == Status::overflow && std::fabs(a) > 1e200));
  }
}

RC_GTEST_PROP(ModelProperty, ValveRoundTripInsideTheEnvelope, ()) {
  const double q = *log_uniform(1e-12, 1e-3);
  const double tau = *rc::gen::oneOf(uniform(0.0, 60e3), log_uniform(1e-9, 60e3));
  const Result<double> p = valve().pressure_exact_Pa(q, tau);
  RC_ASSERT(p.ok());
  const Result<double> back = valve().flow_m3_per_s(p.value, tau);
  RC_ASSERT(back.ok());
  RC_ASSERT(std::fabs(back.value - q) <= 1e-9 * q);
  const Result<double> pf = valve().pressure_fast_Pa(q, tau);
  RC_ASSERT(pf.ok());
  if (q >= 1e-9 && q <= 1e-4 && tau <= 50e3) {
    RC_ASSERT(std::fabs(pf.value - p.value) <= 0.005 * p.value);
  }
}

RC_GTEST_PROP(ModelProperty, FluidAndCircuitAreFiniteOrExplicitErrors, ()) {
  const FluidParams f;
  const double h = *any_double();
  const Result<double> t = yield_stress_Pa(f, h);
  finite_or_error(t, t.value);
  const Result<double> b = fluid_flux_density_T(f, h);
  finite_or_error(b, b.value);
  if (std::isfinite(h)) {
    RC_ASSERT(t.ok() && b.ok());
    RC_ASSERT(t.value >= 0.0 && t.value <= saturated_yield_stress_Pa(f));
  }
  const double i = *rc::gen::oneOf(any_double(), uniform(-5.0, 5.0));
  const Result<GapField> g = model().gap_field(i);
  finite_or_error(g, g.value.field_A_per_m);
  if (std::isfinite(i) && std::fabs(i) < 1e6) {
    RC_ASSERT(g.ok());
  }
}

RC_GTEST_PROP(ModelProperty, MembraneLawsAreFiniteOrExplicitErrors, ()) {
  const MembraneParams m;
  const double x = *any_double();
  const double a = *rc::gen::oneOf(any_double(), log_uniform(1e-4, 1.0));
  const Result<double> p = disk_pressure_Pa(m, a, x);
  finite_or_error(p, p.value);
  const Result<double> w = disk_deflection_m(m, a, x);
  finite_or_error(w, w.value);
  const Result<LoadSplit> f = point_load_force_N(m, a, 0.3 * a, x);
  finite_or_error(f, f.value.total);
  if (std::isfinite(x) && std::isfinite(a) && a > 0.0 && std::fabs(x) < 1e50 && a < 1e50 && a > 1e-50) {
    RC_ASSERT(w.ok());
    RC_ASSERT(f.ok());
  }
}

RC_GTEST_PROP(ModelProperty, CellForceIsFiniteOrExplicitErrorForAnyInput, ()) {
  const DeviceModel& m = model();
  const auto cell = static_cast<std::size_t>(*rc::gen::inRange(0, 16));
  const double d = *rc::gen::oneOf(any_double(), uniform(-1e-3, 0.045));
  const double v = *rc::gen::oneOf(any_double(), uniform(-0.05, 0.05));
  const double i = *rc::gen::oneOf(any_double(), uniform(-0.01, 0.11));
  const Result<CellLoad> l = m.cell_force_uniform(cell, d, v, i);
  finite_or_error(l, l.value.force_N);
  if (l.ok()) {
    RC_ASSERT(l.value.force_N >= 0.0);
  }
  const bool valid = cell < 13 && std::isfinite(d) && d < m.profile().cell_depth_m && std::isfinite(v) &&
                     std::fabs(v) < 1e3 && std::isfinite(i) && i >= 0.0 &&
                     i <= m.profile().coil.max_current_A;
  if (valid) {
    RC_ASSERT(l.ok());
  }
}

RC_GTEST_PROP(ModelProperty, EnvelopeContainsEveryCurrentInsideTheOperatingRange, ()) {
  const DeviceModel& m = model();
  const auto cell = static_cast<std::size_t>(*rc::gen::inRange(0, 13));
  const double d = *uniform(0.0, 8e-3);
  const double v = *uniform(-20e-3, 20e-3);
  const double i = *uniform(0.0, m.profile().coil.max_current_A);
  const Result<CellEnvelope> e = m.envelope(cell, d, v);
  RC_ASSERT(e.ok());
  const Result<CellLoad> l = m.cell_force_uniform(cell, d, v, i);
  RC_ASSERT(l.ok());
  RC_ASSERT(l.value.force_N >= e.value.force_min_N - 1e-12);
  RC_ASSERT(l.value.force_N <= e.value.force_max_N + 1e-12);
}

}  // namespace
