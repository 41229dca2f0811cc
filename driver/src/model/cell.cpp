#include "mrskin/driver/model/cell.hpp"

#include <array>
#include <cmath>

namespace mrskin::model {

namespace {

// 4-point Gauss-Legendre on [-1, 1].
constexpr std::array<double, 4> kGaussX = {-0.8611363115940526, -0.3399810435848563, 0.3399810435848563,
                                           0.8611363115940526};
constexpr std::array<double, 4> kGaussW = {0.3478548451374538, 0.6521451548625461, 0.6521451548625461,
                                           0.3478548451374538};

// Integrals over the free annulus c < r < a, in t = ln r (composite Gauss, 64 panels x 4 nodes):
// N2 = int psi dA, J4 = int psi'^4 dA, with psi(r) = (a^2 - r^2) - (a^2 - c^2) ln(a/r) / L.
struct AnnulusIntegrals {
  double n2 = 0.0;
  double j4 = 0.0;
};
AnnulusIntegrals annulus_integrals(double a, double c) noexcept {
  const double big_l = std::log(a / c);
  const double k = (a * a - c * c) / big_l;
  const double t0 = std::log(c);
  const double t1 = std::log(a);
  constexpr int kPanels = 64;
  const double hp = (t1 - t0) / kPanels;
  AnnulusIntegrals out;
  for (int i = 0; i < kPanels; ++i) {
    const double mid = t0 + (static_cast<double>(i) + 0.5) * hp;
    for (std::size_t j = 0; j < kGaussX.size(); ++j) {
      const double r = std::exp(mid + 0.5 * hp * kGaussX[j]);
      const double w = 0.5 * hp * kGaussW[j] * 2.0 * kPi * r * r;  // dA = 2 pi r dr = 2 pi r^2 dt
      const double psi = (a - r) * (a + r) - k * std::log(a / r);
      const double dpsi = -2.0 * r + k / r;
      out.n2 += w * psi;
      out.j4 += w * dpsi * dpsi * dpsi * dpsi;
    }
  }
  return out;
}

}  // namespace

const char* to_string(CellMode m) noexcept {
  switch (m) {
    case CellMode::bulging:
      return "bulging";
    case CellMode::flowing:
      return "flowing";
    case CellMode::holding:
      return "holding";
    case CellMode::refilling:
      return "refilling";
    case CellMode::released:
      return "released";
  }
  return "unknown";
}

Result<ContactPatch> contact_patch(const MembraneParams& m, double cell_radius_m,
                                   double finger_radius_m) noexcept {
  if (!std::isfinite(cell_radius_m) || !std::isfinite(finger_radius_m)) {
    return failure<ContactPatch>(Status::not_finite);
  }
  if (!(cell_radius_m > 0.0) || !(finger_radius_m >= 0.01 * cell_radius_m)) {
    return failure<ContactPatch>(Status::degenerate);
  }
  ContactPatch p;
  p.membrane = m;
  p.cell_radius_m = cell_radius_m;
  p.contact_radius_m = std::fmin(finger_radius_m, 0.9 * cell_radius_m);
  const double a = cell_radius_m;
  const double c = p.contact_radius_m;
  p.contact_area_m2 = kPi * c * c;
  p.log_ratio = std::log(a / c);
  p.effective_area_m2 = kPi * (a - c) * (a + c) / (2.0 * p.log_ratio);
  const AnnulusIntegrals in = annulus_integrals(a, c);
  p.bulge_normalisation_m4 = in.n2;
  const double n2 = in.n2;
  const double nu = m.poisson_ratio;
  const double e_prime = m.youngs_modulus_Pa / (1.0 - nu * nu);
  const double kappa = 3.0 * (1.0 - nu * nu) / (16.0 * m.hencky_K * m.hencky_K * m.hencky_K);
  p.bulge_linear_Pa_per_m3 =
      4.0 * m.pretension_N_per_m / n2 + 16.0 * kPi * bending_stiffness_N_m(m) * (a - c) * (a + c) / (n2 * n2);
  p.bulge_cubic_Pa_per_m9 = kappa * e_prime * m.thickness_m * in.j4 / (2.0 * n2 * n2 * n2 * n2);
  if (!std::isfinite(p.bulge_linear_Pa_per_m3) || !std::isfinite(p.bulge_cubic_Pa_per_m9) || !(n2 > 0.0)) {
    return failure<ContactPatch>(Status::degenerate);
  }
  return {p};
}

Result<double> pad_membrane_force_N(const ContactPatch& p, double indentation_m) noexcept {
  const Result<LoadSplit> f =
      point_load_force_N(p.membrane, p.cell_radius_m, p.contact_radius_m, indentation_m);
  return {f.value.total, f.status};
}

double bulge_pressure_Pa(const ContactPatch& p, double bulge_volume_m3) noexcept {
  const double s = bulge_volume_m3;
  return p.bulge_linear_Pa_per_m3 * s + p.bulge_cubic_Pa_per_m9 * s * s * s;
}

Result<double> bulge_volume_m3(const ContactPatch& p, double pressure_Pa) noexcept {
  if (!std::isfinite(pressure_Pa)) {
    return failure<double>(Status::not_finite);
  }
  const double target = std::fabs(pressure_Pa);
  if (target == 0.0) {
    return {0.0};
  }
  const double k1 = p.bulge_linear_Pa_per_m3;
  const double k3 = p.bulge_cubic_Pa_per_m9;
  // Increasing convex in s >= 0: Newton from an upper bound descends monotonically.
  double s = k1 > 0.0 ? target / k1 : std::cbrt(target / k3);
  if (k3 > 0.0) {
    s = std::fmin(s, std::cbrt(target / k3));
  }
  for (int i = 0; i < 200; ++i) {
    const double f = k1 * s + k3 * s * s * s - target;
    const double next = s - f / (k1 + 3.0 * k3 * s * s);
    if (!std::isfinite(f) || !std::isfinite(next)) {
      return failure<double>(Status::overflow);
    }
    if (!(next < s) || s - next <= 4.5e-16 * s) {
      return {std::copysign(next > 0.0 && next < s ? next : s, pressure_Pa)};
    }
    s = next;
  }
  return failure<double>(Status::no_convergence);
}

Result<double> stored_energy_J(const ContactPatch& p, double indentation_m, double bulge_volume_m3) noexcept {
  const double s = bulge_volume_m3;
  if (!std::isfinite(indentation_m) || !std::isfinite(s)) {
    return failure<double>(Status::not_finite);
  }
  const MembraneParams& m = p.membrane;
  const double a2 = p.cell_radius_m * p.cell_radius_m;
  const double q = point_load_q(m.poisson_ratio);
  const double d = indentation_m;
  const double k_lin =
      16.0 * kPi * bending_stiffness_N_m(m) / a2 + 2.0 * kPi * m.pretension_N_per_m / p.log_ratio;
  const double k_cub = m.youngs_modulus_Pa * m.thickness_m / (a2 * q * q * q);
  const double u = 0.5 * k_lin * d * d + 0.25 * k_cub * d * d * d * d +
                   0.5 * p.bulge_linear_Pa_per_m3 * s * s + 0.25 * p.bulge_cubic_Pa_per_m9 * s * s * s * s;
  return std::isfinite(u) ? Result<double>{u} : failure<double>(Status::overflow);
}

}  // namespace mrskin::model
