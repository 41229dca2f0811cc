#include "mrskin/driver/model/fluid.hpp"

#include <cmath>

namespace mrskin::model {

double saturated_yield_stress_Pa(const FluidParams& f) noexcept {
  return f.carrier_factor * f.yield_coefficient_Pa * std::pow(f.volume_fraction, f.yield_exponent);
}

Result<double> yield_stress_Pa(const FluidParams& f, double field_A_per_m) noexcept {
  if (!std::isfinite(field_A_per_m)) {
    return failure<double>(Status::not_finite);
  }
  return {saturated_yield_stress_Pa(f) * std::tanh(f.yield_field_scale_m_per_A * std::fabs(field_A_per_m))};
}

double yield_stress_slope_Pa_per_A_per_m(const FluidParams& f, double field_A_per_m) noexcept {
  const double t = std::tanh(f.yield_field_scale_m_per_A * std::fabs(field_A_per_m));
  return saturated_yield_stress_Pa(f) * f.yield_field_scale_m_per_A * (1.0 - t * t);
}

Result<double> fluid_flux_density_T(const FluidParams& f, double field_A_per_m) noexcept {
  if (!std::isfinite(field_A_per_m)) {
    return failure<double>(Status::not_finite);
  }
  const double a = f.saturation_coefficient_T * std::pow(f.volume_fraction, f.saturation_exponent);
  const double h = std::fabs(field_A_per_m);
  // -expm1 keeps the low-field slope exact (1 - exp(-x) cancels for small x).
  const double b = a * -std::expm1(-f.saturation_rate_per_T * kMu0_H_per_m * h) + kMu0_H_per_m * h;
  return {std::copysign(b, field_A_per_m)};
}

double fluid_permeability_H_per_m(const FluidParams& f, double field_A_per_m) noexcept {
  const double a = f.saturation_coefficient_T * std::pow(f.volume_fraction, f.saturation_exponent);
  const double k = f.saturation_rate_per_T * kMu0_H_per_m;
  return a * k * std::exp(-k * std::fabs(field_A_per_m)) + kMu0_H_per_m;
}

Result<double> fluid_field_for_flux_density_A_per_m(const FluidParams& f, double flux_density_T) noexcept {
  if (!std::isfinite(flux_density_T)) {
    return failure<double>(Status::not_finite);
  }
  const double b = std::fabs(flux_density_T);
  if (b == 0.0) {
    return {0.0};
  }
  // B(H) is increasing and concave: bracket [b / mu_initial, b / mu0] and run safeguarded Newton.
  double lo = b / fluid_permeability_H_per_m(f, 0.0);
  double hi = b / kMu0_H_per_m;
  double h = lo;
  for (int i = 0; i < 100; ++i) {
    const double r = fluid_flux_density_T(f, h).value - b;
    if (r < 0.0) {
      lo = h;
    } else {
      hi = h;
    }
    double next = h - r / fluid_permeability_H_per_m(f, h);
    const bool converged = r == 0.0 || std::fabs(next - h) <= 4e-16 * h;
    if (!converged && !(next > lo && next < hi)) {
      next = 0.5 * (lo + hi);
    }
    if (converged || hi - lo <= 4e-16 * hi) {
      return {std::copysign(next, flux_density_T)};
    }
    h = next;
  }
  return failure<double>(Status::no_convergence);
}

Result<double> field_for_yield_stress_A_per_m(const FluidParams& f, double yield_stress_Pa) noexcept {
  if (!std::isfinite(yield_stress_Pa)) {
    return failure<double>(Status::not_finite);
  }
  if (yield_stress_Pa < 0.0) {
    return failure<double>(Status::negative);
  }
  const double ratio = yield_stress_Pa / saturated_yield_stress_Pa(f);
  if (ratio >= 1.0) {
    return failure<double>(Status::out_of_range);
  }
  return {std::atanh(ratio) / f.yield_field_scale_m_per_A};
}

const char* check_fluid(const FluidParams& f) noexcept {
  auto pos = [](double x) { return std::isfinite(x) && x > 0.0; };
  if (!(pos(f.volume_fraction) && f.volume_fraction <= 0.6)) {
    return "volume_fraction: must be in (0, 0.6]";
  }
  if (!pos(f.carrier_factor)) {
    return "carrier_factor: must be > 0 (1.0 hydrocarbon, 1.16 water, 0.95 silicone oil)";
  }
  if (!pos(f.viscosity_Pa_s)) {
    return "viscosity_Pa_s: must be > 0";
  }
  if (!pos(f.density_kg_per_m3)) {
    return "density_kg_per_m3: must be > 0";
  }
  if (!pos(f.yield_coefficient_Pa) || !pos(f.yield_exponent) || !pos(f.yield_field_scale_m_per_A)) {
    return "yield fit coefficients: must all be > 0";
  }
  if (!pos(f.saturation_coefficient_T) || !pos(f.saturation_exponent) || !pos(f.saturation_rate_per_T)) {
    return "flux density fit coefficients: must all be > 0";
  }
  return "";
}

}  // namespace mrskin::model
