// Membrane laws: each term exact in its limit, the paper's Eq. 6 as the small-deflection
// limit of the strip law, and the regime check.
#include "mrskin/driver/model/membrane.hpp"

#include <gtest/gtest.h>

#include <cmath>

namespace {

using namespace mrskin::model;

MembraneParams paper_skin() {
  MembraneParams m;
  m.thickness_m = 0.121e-3;
  m.youngs_modulus_Pa = 1e6;
  m.poisson_ratio = 0.5;
  m.pretension_N_per_m = 0.0;
  return m;
}

TEST(ModelMembrane, SmallDeflectionStripIsThePapersEq6) {
  // Strip of span l, no pre-tension, nu = 0 (so the plate strip's D is the beam's E I per width).
  MembraneParams m = paper_skin();
  m.poisson_ratio = 0.0;
  const double l = 0.030;
  const double b = 0.030;  // the beam's width (Eq. 6's A = b l, I = b t^3 / 12)
  const double t = m.thickness_m;
  const double p = 1e-7;  // Pa: deflection << t (stretching adds 3.3 (w/t)^2)
  const double w = strip_deflection_m(m, l, p).value;
  const Result<double> eq6 =
      paper_eq6_deflection_m(p, b * l, l, m.youngs_modulus_Pa, b * t * t * t / 12.0, 0.5 * l, t);
  ASSERT_TRUE(eq6.ok());
  EXPECT_LT(w / t, 1e-4);
  EXPECT_NEAR(w / eq6.value, 1.0, 1e-6);
  // Eq. 6's whole shape: D(x) vanishes at both supports and is symmetric.
  EXPECT_EQ(paper_eq6_deflection_m(p, b * l, l, 1e6, 1.0, 0.0, t).value, 0.0);
  EXPECT_NEAR(paper_eq6_deflection_m(p, b * l, l, 1e6, 1.0, l, t).value, 0.0, 1e-30);
  EXPECT_NEAR(paper_eq6_deflection_m(p, b * l, l, 1e6, 1.0, 0.25 * l, t).value,
              paper_eq6_deflection_m(p, b * l, l, 1e6, 1.0, 0.75 * l, t).value, 1e-25);
  // With nu != 0 the limit is Eq. 6 with E replaced by the plate modulus E / (1 - nu^2).
  MembraneParams m2 = paper_skin();
  const double w2 = strip_deflection_m(m2, l, p).value;
  const double eq6_plate =
      paper_eq6_deflection_m(p, b * l, l, m2.youngs_modulus_Pa / (1 - 0.25), b * t * t * t / 12.0, 0.5 * l, t)
          .value;
  EXPECT_NEAR(w2 / eq6_plate, 1.0, 1e-6);
}

TEST(ModelMembrane, Eq6AtThePapersNumbersPredictsMetresAndIsFlagged) {
  // 2 N over a 30 mm cell, the 0.121 mm sheet of E = 1 MPa: Eq. 6 predicts ~160 m of deflection.
  const double l = 0.030;
  const double t = 0.121e-3;
  const double p = 2.0 / (l * l);
  const Result<double> eq6 = paper_eq6_deflection_m(p, l * l, l, 1e6, l * t * t * t / 12.0, 0.5 * l, t);
  EXPECT_EQ(eq6.status, Status::out_of_regime);
  EXPECT_GT(eq6.value, 100.0);
  // The corrected law: a few millimetres.
  const double w = disk_deflection_m(paper_skin(), l / std::sqrt(kPi), p).value;
  EXPECT_GT(w, 1e-3);
  EXPECT_LT(w, 10e-3);
  EXPECT_EQ(deflection_regime(paper_skin(), w), DeflectionRegime::membrane);
  EXPECT_EQ(deflection_regime(paper_skin(), 0.01e-3), DeflectionRegime::bending);
  EXPECT_EQ(deflection_regime(paper_skin(), 0.2e-3), DeflectionRegime::transition);
}

TEST(ModelMembrane, DiskLimits) {
  const MembraneParams m = paper_skin();
  const double a = 0.017;
  // Small deflection: clamped plate, w0 = p a^4 / (64 D).
  const double p_small = 1e-6;  // w/t ~ 5e-5: stretching adds 0.5 (w/t)^2
  EXPECT_NEAR(
      disk_deflection_m(m, a, p_small).value / (p_small * std::pow(a, 4) / (64 * bending_stiffness_N_m(m))),
      1.0, 1e-6);
  // Large deflection: Hencky, w0 = K a (p a / (E t))^(1/3).
  const double p_big = 2000.0;
  const double hencky = m.hencky_K * a * std::cbrt(p_big * a / (m.youngs_modulus_Pa * m.thickness_m));
  EXPECT_NEAR(disk_deflection_m(m, a, p_big).value / hencky, 1.0, 0.01);
  // Pre-tension alone (a soap film): w0 = p a^2 / (4 T0).
  MembraneParams film = m;
  film.pretension_N_per_m = 50.0;
  film.youngs_modulus_Pa = 1e-3;  // no stretching or bending to speak of
  EXPECT_NEAR(disk_deflection_m(film, a, 10.0).value / (10.0 * a * a / 200.0), 1.0, 1e-6);
  // Round trip and monotonicity.
  double prev = -1.0;
  for (double w = 1e-7; w < 10e-3; w *= 1.5) {
    const double p = disk_pressure_Pa(m, a, w).value;
    EXPECT_GT(p, prev);
    prev = p;
    EXPECT_NEAR(disk_deflection_m(m, a, p).value / w, 1.0, 1e-12);
  }
}

TEST(ModelMembrane, PointLoadLaw) {
  MembraneParams m = paper_skin();
  const double a = 0.017;
  const double c = 0.006;
  // Stretching term: F = (E t / a^2) d^3 / q(nu)^3, q(0.5) = 0.935.
  EXPECT_NEAR(point_load_q(0.5), 1.05 - 0.075 - 0.04, 1e-15);
  const LoadSplit big = point_load_force_N(m, a, c, 5e-3).value;
  EXPECT_NEAR(big.stretching, 1e6 * 0.121e-3 / (a * a) * 125e-9 / std::pow(0.935, 3), 1e-12);
  EXPECT_LT(big.bending, 0.01 * big.total);  // at d / t = 41 bending is a fraction of a percent
  // Pre-tension adds the linear term 2 pi T0 d / ln(a / c).
  m.pretension_N_per_m = 5.0;
  const LoadSplit pre = point_load_force_N(m, a, c, 1e-3).value;
  EXPECT_NEAR(pre.pretension, 2 * kPi * 5.0 * 1e-3 / std::log(a / c), 1e-15);
  EXPECT_EQ(point_load_force_N(m, a, a, 1e-3).status, Status::degenerate);
  double prev = -1.0;
  for (double d = 0.0; d < 10e-3; d += 0.1e-3) {
    const double f = point_load_force_N(m, a, c, d).value.total;
    EXPECT_GT(f, prev);
    prev = f;
  }
}

TEST(ModelMembrane, StripLawLimitsAndInverse) {
  MembraneParams m = paper_skin();
  m.pretension_N_per_m = 5.0;
  const double l = 0.03;
  // Pre-tensioned string: w0 = p l^2 / (8 T0) when bending and stretching are negligible.
  MembraneParams film = m;
  film.youngs_modulus_Pa = 1e-3;
  EXPECT_NEAR(strip_deflection_m(film, l, 1.0).value / (l * l / 40.0), 1.0, 1e-6);
  for (double p = 1e-3; p < 1e5; p *= 3.0) {
    EXPECT_NEAR(strip_pressure_Pa(m, l, strip_deflection_m(m, l, p).value).value / p, 1.0, 1e-12);
  }
}

TEST(ModelMembrane, BadInputsAreExplicitErrors) {
  const MembraneParams m = paper_skin();
  EXPECT_EQ(disk_pressure_Pa(m, 0.0, 1e-3).status, Status::degenerate);
  EXPECT_EQ(disk_pressure_Pa(m, 0.01, std::nan("")).status, Status::not_finite);
  EXPECT_EQ(paper_eq6_deflection_m(1.0, 1.0, 1.0, 1.0, 1.0, 2.0, 1.0).status, Status::out_of_range);
  EXPECT_EQ(paper_eq6_deflection_m(1.0, 1.0, 1.0, 0.0, 1.0, 0.5, 1.0).status, Status::degenerate);
  MembraneParams bad = m;
  bad.poisson_ratio = 0.7;
  EXPECT_NE(std::string(check_membrane(bad)), "");
  EXPECT_STREQ(check_membrane(m), "");
}

}  // namespace
