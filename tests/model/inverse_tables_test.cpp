// The inverse's branch-law tables are built by bisection. Their tolerances (1e-17 and 1e-16 of
// the bracket) lie below the spacing of doubles, so the loops used to reach adjacent doubles
// after about 53 halvings and then spend the rest of their 400 iterations on a midpoint equal to
// an end (opening fingertip-16x16 took 1.59G instructions, 0.35G without them). They now stop
// there. This checks that the answer is the one the 400 iterations gave, to the bit.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <cstring>

#include "inverse_impl.hpp"

namespace {

using mrskin::model::inverse_detail::BranchShape;
using mrskin::model::inverse_detail::shape_of;

// BranchShape::r_of_phi as it was: 400 halvings whatever the bracket.
double r_of_phi_all_iterations(const BranchShape& b, double target) {
  double lo = std::sqrt(std::max(0.0, (target - b.a) / b.g));
  double hi = std::sqrt(std::max(0.0, (target - b.s) / b.g)) * 1.0000001 + 1e-300;
  for (int i = 0; i < 400 && hi - lo > 1e-17 * hi; ++i) {
    const double mid = 0.5 * (lo + hi);
    (b.phi(mid * mid) < target ? lo : hi) = mid;
  }
  const double w = 0.5 * (lo + hi);
  return w * w;
}

std::uint64_t bits(double x) {
  std::uint64_t u = 0;
  std::memcpy(&u, &x, sizeof u);
  return u;
}

TEST(ModelInverseTables, BisectionStoppingAtAdjacentDoublesGivesTheSameBits) {
  int checked = 0;
  for (const int m : {0, 1, 2, 3, 4, 6}) {
    const BranchShape b = shape_of(m);
    // Targets from just above the threshold multiplier to far up the large-flow line.
    for (int k = 0; k < 400; ++k) {
      const double target = b.s * (1.0 + 1e-9) + std::pow(10.0, -6.0 + 0.025 * k);
      const double now = b.r_of_phi(target);
      const double before = r_of_phi_all_iterations(b, target);
      ASSERT_EQ(bits(now), bits(before)) << "m " << m << " target " << target;
      ++checked;
    }
  }
  EXPECT_EQ(checked, 2400);
}

}  // namespace
