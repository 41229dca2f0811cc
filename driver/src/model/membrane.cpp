#include "mrskin/driver/model/membrane.hpp"

#include <cmath>
#include <initializer_list>

namespace mrskin::model {

namespace {

// Root of a x^3 + b x = p (a, b >= 0, a + b > 0, p >= 0): increasing, so one root, found by
// Newton from an upper bound (convex: descends monotonically).
Result<double> cubic_root(double a, double b, double p) noexcept {
  if (p == 0.0) {
    return {0.0};
  }
  double x = b > 0.0 ? p / b : std::cbrt(p / a);
  if (a > 0.0) {
    x = std::fmin(x, std::cbrt(p / a));
  }
  // Both candidates are upper bounds of the root; start from the smaller one.
  if (!std::isfinite(x)) {
    return failure<double>(Status::overflow);
  }
  for (int i = 0; i < 200; ++i) {
    const double f = a * x * x * x + b * x - p;
    const double df = 3.0 * a * x * x + b;
    const double next = x - f / df;
    if (!std::isfinite(f) || !std::isfinite(next)) {
      return failure<double>(Status::overflow);  // |p| near DBL_MAX: the cube does not fit
    }
    if (!(next < x) || x - next <= 4.5e-16 * x) {
      return {next > 0.0 && next < x ? next : x};
    }
    x = next;
  }
  return failure<double>(Status::no_convergence);
}
}  // namespace

const char* to_string(DeflectionRegime r) noexcept {
  switch (r) {
    case DeflectionRegime::bending:
      return "bending";
    case DeflectionRegime::transition:
      return "transition";
    case DeflectionRegime::membrane:
      return "membrane";
  }
  return "unknown";
}

DeflectionRegime deflection_regime(const MembraneParams& m, double deflection_m) noexcept {
  const double ratio = std::fabs(deflection_m) / m.thickness_m;
  if (ratio < 0.3) {
    return DeflectionRegime::bending;
  }
  return ratio > 3.0 ? DeflectionRegime::membrane : DeflectionRegime::transition;
}

double bending_stiffness_N_m(const MembraneParams& m) noexcept {
  const double t = m.thickness_m;
  return m.youngs_modulus_Pa * t * t * t / (12.0 * (1.0 - m.poisson_ratio * m.poisson_ratio));
}

double point_load_q(double poisson_ratio) noexcept {
  return 1.05 - 0.15 * poisson_ratio - 0.16 * poisson_ratio * poisson_ratio;
}

namespace {
struct DiskCoeffs {
  double linear;  // Pa per m
  double cubic;   // Pa per m^3
};
DiskCoeffs disk_coeffs(const MembraneParams& m, double a) noexcept {
  const double a2 = a * a;
  const double a4 = a2 * a2;
  const double k3 = m.hencky_K * m.hencky_K * m.hencky_K;
  return {64.0 * bending_stiffness_N_m(m) / a4 + 4.0 * m.pretension_N_per_m / a2,
          m.youngs_modulus_Pa * m.thickness_m / (k3 * a4)};
}
DiskCoeffs strip_coeffs(const MembraneParams& m, double l) noexcept {
  const double l2 = l * l;
  const double l4 = l2 * l2;
  return {
      384.0 * bending_stiffness_N_m(m) / (5.0 * l4) + 8.0 * m.pretension_N_per_m / l2,
      64.0 / 3.0 * m.youngs_modulus_Pa * m.thickness_m / ((1.0 - m.poisson_ratio * m.poisson_ratio) * l4)};
}
Status check_len(double len, double defl) noexcept {
  if (!std::isfinite(len) || !std::isfinite(defl)) {
    return Status::not_finite;
  }
  if (!(len > 0.0)) {
    return Status::degenerate;
  }
  return Status::ok;
}
}  // namespace

Result<double> disk_pressure_Pa(const MembraneParams& m, double radius_m,
                                double centre_deflection_m) noexcept {
  const double w0 = centre_deflection_m;
  if (const Status s = check_len(radius_m, w0); s != Status::ok) {
    return failure<double>(s);
  }
  const DiskCoeffs c = disk_coeffs(m, radius_m);
  const double p = c.linear * w0 + c.cubic * w0 * w0 * w0;
  return std::isfinite(p) ? Result<double>{p} : failure<double>(Status::overflow);
}

Result<double> disk_deflection_m(const MembraneParams& m, double radius_m, double pressure_Pa) noexcept {
  if (const Status s = check_len(radius_m, pressure_Pa); s != Status::ok) {
    return failure<double>(s);
  }
  const DiskCoeffs c = disk_coeffs(m, radius_m);
  const Result<double> w = cubic_root(c.cubic, c.linear, std::fabs(pressure_Pa));
  return {std::copysign(w.value, pressure_Pa), w.status};
}

Result<LoadSplit> point_load_force_N(const MembraneParams& m, double radius_m, double contact_radius_m,
                                     double centre_deflection_m) noexcept {
  const double d = centre_deflection_m;
  if (!std::isfinite(radius_m) || !std::isfinite(contact_radius_m) || !std::isfinite(d)) {
    return failure<LoadSplit>(Status::not_finite);
  }
  if (!(contact_radius_m > 0.0 && contact_radius_m < radius_m)) {
    return failure<LoadSplit>(Status::degenerate);
  }
  const double a2 = radius_m * radius_m;
  const double q = point_load_q(m.poisson_ratio);
  LoadSplit out;
  out.bending = 16.0 * kPi * bending_stiffness_N_m(m) * d / a2;
  out.pretension = 2.0 * kPi * m.pretension_N_per_m * d / std::log(radius_m / contact_radius_m);
  out.stretching = m.youngs_modulus_Pa * m.thickness_m / a2 * d * d * d / (q * q * q);
  out.total = out.bending + out.pretension + out.stretching;
  if (!std::isfinite(out.total)) {
    return failure<LoadSplit>(Status::overflow);
  }
  return {out};
}

Result<double> strip_pressure_Pa(const MembraneParams& m, double span_m,
                                 double centre_deflection_m) noexcept {
  const double w0 = centre_deflection_m;
  if (const Status s = check_len(span_m, w0); s != Status::ok) {
    return failure<double>(s);
  }
  const DiskCoeffs c = strip_coeffs(m, span_m);
  const double p = c.linear * w0 + c.cubic * w0 * w0 * w0;
  return std::isfinite(p) ? Result<double>{p} : failure<double>(Status::overflow);
}

Result<double> strip_deflection_m(const MembraneParams& m, double span_m, double pressure_Pa) noexcept {
  if (const Status s = check_len(span_m, pressure_Pa); s != Status::ok) {
    return failure<double>(s);
  }
  const DiskCoeffs c = strip_coeffs(m, span_m);
  const Result<double> w = cubic_root(c.cubic, c.linear, std::fabs(pressure_Pa));
  return {std::copysign(w.value, pressure_Pa), w.status};
}

Result<double> paper_eq6_deflection_m(double pressure_Pa, double area_m2, double length_m,
                                      double youngs_modulus_Pa, double second_moment_m4, double x_m,
                                      double thickness_m) noexcept {
  for (const double v :
       {pressure_Pa, area_m2, length_m, youngs_modulus_Pa, second_moment_m4, x_m, thickness_m}) {
    if (!std::isfinite(v)) {
      return failure<double>(Status::not_finite);
    }
  }
  if (!(length_m > 0.0 && youngs_modulus_Pa > 0.0 && second_moment_m4 > 0.0 && thickness_m > 0.0)) {
    return failure<double>(Status::degenerate);
  }
  if (x_m < 0.0 || x_m > length_m) {
    return failure<double>(Status::out_of_range);
  }
  const double k =
      pressure_Pa * area_m2 * length_m * length_m * length_m / (24.0 * youngs_modulus_Pa * second_moment_m4);
  const double u = x_m / length_m;
  const double d = k * (u * u * u * u - 2.0 * u * u * u + u);
  if (!std::isfinite(d)) {
    return failure<double>(Status::overflow);
  }
  const double mid = k * (5.0 / 16.0);
  return {d, std::fabs(mid) > 0.3 * thickness_m ? Status::out_of_regime : Status::ok};
}

const char* check_membrane(const MembraneParams& m) noexcept {
  auto pos = [](double x) { return std::isfinite(x) && x > 0.0; };
  if (!pos(m.thickness_m)) {
    return "thickness_m: must be > 0";
  }
  if (!pos(m.youngs_modulus_Pa)) {
    return "youngs_modulus_Pa: must be > 0";
  }
  if (!(std::isfinite(m.poisson_ratio) && m.poisson_ratio >= 0.0 && m.poisson_ratio <= 0.5)) {
    return "poisson_ratio: must be in [0, 0.5]";
  }
  if (!(std::isfinite(m.pretension_N_per_m) && m.pretension_N_per_m >= 0.0)) {
    return "pretension_N_per_m: must be >= 0";
  }
  if (!(pos(m.hencky_K) && m.hencky_K < 2.0)) {
    return "hencky_K: must be in (0, 2) (Hencky: about 0.65)";
  }
  return "";
}

}  // namespace mrskin::model
