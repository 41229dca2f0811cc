// MR fluid: Carlson's fits for yield stress and flux density against field, plus the
// Newtonian (plastic) viscosity and density that the valve law uses.
//
// Source: J. D. Carlson, "MR fluids and devices in the real world", Int. J. Mod. Phys. B 19
// (2005) 1463-1470, fits for MRF-132DG-class fluids:
//   tau_y(H) = C * 271700 * phi^1.5239 * tanh(6.33e-6 * H)          [Pa, H in A/m]
//   B(H)     = 1.91 * phi^1.133 * (1 - exp(-10.97 * mu0 * H)) + mu0 * H   [T]
// C = 1.0 for a hydrocarbon carrier, 1.16 for water, 0.95 for silicone oil.
#pragma once

#include "mrskin/driver/export.hpp"
#include "mrskin/driver/model/common.hpp"

namespace mrskin::model {

struct FluidParams {
  double volume_fraction = 0.32;      // phi, iron particles by volume (0, 0.6]
  double carrier_factor = 1.0;        // Carlson's C (hydrocarbon 1.0, water 1.16, silicone 0.95)
  double viscosity_Pa_s = 0.112;      // plastic (off-state) viscosity, MRF-132DG at 40 C
  double density_kg_per_m3 = 3050.0;  // MRF-132DG: 2.95-3.15 g/cm^3
  // Fit coefficients (defaults are Carlson's; a calibration may refit them).
  double yield_coefficient_Pa = 271700.0;
  double yield_exponent = 1.5239;
  double yield_field_scale_m_per_A = 6.33e-6;
  double saturation_coefficient_T = 1.91;
  double saturation_exponent = 1.133;
  double saturation_rate_per_T = 10.97;
};

// Yield stress at field magnitude |H|, Pa (even in H).
MRSKIN_DRIVER_API Result<double> yield_stress_Pa(const FluidParams& f, double field_A_per_m) noexcept;
// Flux density in the fluid at field H, T (odd in H).
MRSKIN_DRIVER_API Result<double> fluid_flux_density_T(const FluidParams& f, double field_A_per_m) noexcept;
// d tau_y / dH at H, Pa per (A/m), and dB/dH, H/m.
MRSKIN_DRIVER_API double yield_stress_slope_Pa_per_A_per_m(const FluidParams& f,
                                                           double field_A_per_m) noexcept;
MRSKIN_DRIVER_API double fluid_permeability_H_per_m(const FluidParams& f, double field_A_per_m) noexcept;
// The field that gives a flux density B in the fluid (inverse of the B(H) fit), A/m.
MRSKIN_DRIVER_API Result<double> fluid_field_for_flux_density_A_per_m(const FluidParams& f,
                                                                      double flux_density_T) noexcept;
// The field that gives a yield stress (inverse of the tau_y fit), A/m; out_of_range at or above
// the saturated yield stress.
MRSKIN_DRIVER_API Result<double> field_for_yield_stress_A_per_m(const FluidParams& f,
                                                                double yield_stress_Pa) noexcept;
// The saturated yield stress C * 271700 * phi^1.5239, Pa.
MRSKIN_DRIVER_API double saturated_yield_stress_Pa(const FluidParams& f) noexcept;

// Empty string when the parameters make sense, otherwise "field: reason".
MRSKIN_DRIVER_API const char* check_fluid(const FluidParams& f) noexcept;

}  // namespace mrskin::model
