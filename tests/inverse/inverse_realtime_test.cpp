// CellInverse::solve allocates nothing and throws nothing after construction, whatever it is
// asked: warm tracking, cold restarts, role changes (new components), stale targets, errors.
#include <gtest/gtest.h>

#include <cstdint>
#include <limits>
#include <vector>

#include "counting_new.hpp"
#include "inverse_cases.hpp"
#include "mrskin/driver/model/inverse.hpp"

namespace {

using namespace mrskin::model;

TEST(InverseRealtime, SolveAllocatesNothing) {
  const DeviceModel m = mrskin::test::default_model();
  CellInverse inv(m);
  const std::size_t n = m.layout().fluid_cell_count();
  mrskin::test::CaseGenerator g(n, 11);
  // Inputs prepared before counting.
  std::vector<mrskin::test::InverseCase> cases;
  for (int k = 0; k < 400; ++k) {
    cases.push_back(g.next(k % 50 == 0 ? n : 3));
  }
  mrskin::test::InverseCase press = cases[0];
  for (std::size_t i = 0; i < n; ++i) {
    press.states[i] = {};
    press.targets[i] = {900.0, 1.2, 5.0, 0.0, 0.0, 2.5, 1e9};
  }
  const std::size_t a = m.fluid_cell_index(1, 1).value;
  const std::size_t b = m.fluid_cell_index(2, 2).value;
  mrskin::test::InverseCase bad = cases[1];
  bad.states[0].indentation_m = std::numeric_limits<double>::quiet_NaN();
  ASSERT_EQ(inv.solve(cases[0].targets, cases[0].states, cases[0].now_s), Status::ok);  // warm the caches

  const std::uint64_t before = mrskin::test::allocation_count();
  int failures = 0;
  for (const auto& c : cases) {  // cold, random roles and components
    failures += inv.solve(c.targets, c.states, c.now_s) != Status::ok ? 1 : 0;
    failures += inv.solve(bad.targets, bad.states, bad.now_s) != Status::not_finite ? 1 : 0;
  }
  for (int k = 0; k < 2000; ++k) {  // tracking a press between two cells, then a hold
    const double time = 1e-3 * k;
    const double d = time < 1.0 ? 0.5e-3 + 4.5e-3 * time : 5e-3;
    press.states[a] = {d, time < 1.0 ? 4.5e-3 : 0.0};
    press.states[b] = {0.7 * d, time < 1.0 ? 3e-3 : 0.0};
    failures += inv.solve(press.targets, press.states, time) != Status::ok ? 1 : 0;
  }
  inv.invalidate();
  failures += inv.solve(press.targets, press.states, 2.0) != Status::ok ? 1 : 0;
  EXPECT_EQ(mrskin::test::allocation_count(), before);
  EXPECT_EQ(failures, 0);
  static_assert(noexcept(inv.solve(press.targets, press.states, 0.0)));
  static_assert(noexcept(inv.currents_A()));
  static_assert(noexcept(inv.report()));
}

}  // namespace
