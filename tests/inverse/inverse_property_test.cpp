// Properties of CellInverse::solve (rapidcheck), and 10^6 randomised cases inside the operating
// envelope, every one succeeding. Seed fixed so runs repeat; RC_PARAMS overrides, e.g.
//   RC_PARAMS="seed=7 max_success=20000" build/release/tests/inverse/mrskin_inverse_property_test
#include <gtest/gtest.h>
#include <rapidcheck.h>
#include <rapidcheck/gtest.h>

#include <chrono>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <vector>

#include "inverse_cases.hpp"
#include "mrskin/driver/model/inverse.hpp"

namespace {

using namespace mrskin::model;

const bool kSeedSet = [] {
  setenv("RC_PARAMS", "seed=20240601 max_success=300", 0);
  return true;
}();

const DeviceModel& model() {
  static const DeviceModel m = mrskin::test::default_model();
  return m;
}

CellInverse& shared_inverse() {
  static CellInverse inv(model());
  return inv;
}

// The outputs every successful solve must satisfy.
void check_outputs(const CellInverse& inv, const DeviceModel& m) {
  const double imax = m.profile().coil.max_current_A;
  for (const double i : inv.currents_A()) {
    RC_ASSERT(i >= 0.0);
    RC_ASSERT(i <= imax);
  }
  for (const CellSolution& c : inv.cells()) {
    RC_ASSERT(std::isfinite(c.residual_N));
    RC_ASSERT(std::isfinite(c.target_force_N));
    if (c.role == CellRole::holding || c.role == CellRole::loading) {
      RC_ASSERT(c.force_min_N <= c.force_max_N);
      RC_ASSERT(c.target_force_N >= c.force_min_N);
      RC_ASSERT(c.target_force_N <= c.force_max_N);
    }
  }
  RC_ASSERT(std::isfinite(inv.report().residual_norm_N));
}

// Random inputs inside the operating envelope always succeed.
RC_GTEST_PROP(InverseProperty, OperatingEnvelopeAlwaysSucceeds, (unsigned seed)) {
  CellInverse& inv = shared_inverse();
  mrskin::test::CaseGenerator g(inv.fluid_cell_count(), seed);
  const mrskin::test::InverseCase c = g.next(inv.fluid_cell_count());
  RC_ASSERT(inv.solve(c.targets, c.states, c.now_s) == Status::ok);
  check_outputs(inv, model());
}

// Any double in any field: either success or an explicit error that changes nothing.
RC_GTEST_PROP(InverseProperty, AnyInputIsSolvedOrRefusedExplicitly, ()) {
  CellInverse& inv = shared_inverse();
  const std::size_t n = inv.fluid_cell_count();
  mrskin::test::CaseGenerator g(n, *rc::gen::arbitrary<unsigned>());
  mrskin::test::InverseCase c = g.next(3);
  const auto cell = *rc::gen::inRange<std::size_t>(0, n);
  const auto field = *rc::gen::inRange(0, 9);
  const double x = *rc::gen::oneOf(
      rc::gen::arbitrary<double>(),
      rc::gen::element(std::numeric_limits<double>::quiet_NaN(), std::numeric_limits<double>::infinity(),
                       -0.0, 0.0, std::numeric_limits<double>::denorm_min(),
                       -std::numeric_limits<double>::max(), 1e300, -1e-300));
  double* fields[] = {&c.targets[cell].stiffness_N_per_m, &c.targets[cell].exponent,
                      &c.targets[cell].damping_N_s_per_m, &c.targets[cell].hc_damping_N_s_per_m2,
                      &c.targets[cell].surface_offset_m,  &c.targets[cell].force_ceiling_N,
                      &c.targets[cell].valid_until_s,     &c.states[cell].indentation_m,
                      &c.states[cell].rate_m_per_s};
  *fields[field] = x;
  const std::vector<double> before(inv.currents_A().begin(), inv.currents_A().end());
  const Status s = inv.solve(c.targets, c.states, c.now_s);
  if (s == Status::ok) {
    check_outputs(inv, model());
  } else {
    RC_ASSERT(s == Status::not_finite || s == Status::negative || s == Status::out_of_range ||
              s == Status::overflow);
    RC_ASSERT(inv.report().error_cell == cell);
    RC_ASSERT(std::vector<double>(inv.currents_A().begin(), inv.currents_A().end()) == before);
  }
}

// 10^6 cases of the operating envelope (fixed seed): streams of ticks in which a press evolves
// (the warm path) interleaved with fresh random inputs on up to all 13 cells (the cold path).
TEST(InverseStress, MillionRandomCasesAllSucceed) {
  const DeviceModel& m = model();
  CellInverse inv(m);
  const std::size_t n = m.layout().fluid_cell_count();
  mrskin::test::CaseGenerator g(n, 20240601);
#if defined(NDEBUG) && !defined(MRSKIN_SANITIZED)
  constexpr long kCases = 1000000;
#else
  constexpr long kCases = 100000;  // Debug or sanitizers in CI: the same cases, fewer of them
#endif
  long failures = 0;
  long not_converged = 0;
  double worst_residual = 0.0;
  const auto t0 = std::chrono::steady_clock::now();
  mrskin::test::InverseCase c = g.next(3);
  for (long k = 0; k < kCases; ++k) {
    if (k % 64 == 0) {
      c = g.next(k % 640 == 0 ? n : 3);  // a new scene (cold)
    } else {
      for (std::size_t i = 0; i < n; ++i) {  // the scene evolves for a tick (warm)
        CellState& s = c.states[i];
        if (s.indentation_m > 0.0) {
          s.indentation_m = std::clamp(s.indentation_m + 1e-3 * s.rate_m_per_s, 1e-4, 8e-3);
        }
      }
      c.now_s += 1e-3;
    }
    const Status st = inv.solve(c.targets, c.states, c.now_s);
    if (st != Status::ok) {
      if (++failures <= 5) {
        ADD_FAILURE() << "case " << k << ": " << to_string(st) << " at cell " << inv.report().error_cell;
      }
      continue;
    }
    not_converged += inv.report().converged ? 0 : 1;
    worst_residual = std::max(worst_residual, inv.report().max_residual_N);
    for (const double i : inv.currents_A()) {
      if (!(i >= 0.0 && i <= m.profile().coil.max_current_A)) {
        ++failures;
      }
    }
  }
  const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  std::printf(
      "%ld cases: %ld failures, %ld components short of the tolerance (conflicting targets), "
      "largest fast-model residual %.3g N, %.1f s\n",
      kCases, failures, not_converged, worst_residual, s);
  EXPECT_EQ(failures, 0);
}

}  // namespace
