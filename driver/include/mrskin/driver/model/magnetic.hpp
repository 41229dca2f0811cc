// The valve's magnetic circuit: coil MMF N*I driving flux through the fluid gap, an optional
// non-magnetic spacer and a steel (soft-magnetic) return path that saturates.
//
//   N I = H_fluid * g + (B_gap / mu0) * g_spacer + H_steel * l_steel,   B_gap * A_pole = B_steel * A_steel
//
// With a linear core this is B_gap = mu0 N I / (g / mu_r,fluid + g_spacer + l_s A_p / (mu_r,s A_s)).
// It replaces the paper's Eq. 2 (B = mu0 n I, an air-core solenoid's field, which says nothing
// about a gapped circuit). Sources: any magnetic-circuit text (e.g. Hughes, "Electric Motors and
// Drives", ch. 1); the fluid's B(H) is Carlson's fit (fluid.hpp).
//
// Steel: anhysteretic curve B = mu0 H + J_s tanh(mu0 (mu_i - 1) H / J_s) (initial relative
// permeability mu_i, saturation polarisation J_s: low-carbon steel J_s ~ 1.6-2.1 T with the knee
// near 1.4-1.6 T; 80 % Ni-Fe ~ 0.75 T). Optional hysteresis: a play operator of half-width H_c
// (the coercivity) on the steel field, B = B_an(p), p = clamp(p_prev, H - H_c, H + H_c), i.e. a
// single Preisach hysteron. With H_c = 0 the circuit is anhysteretic and stateless.
#pragma once

#include "mrskin/driver/export.hpp"
#include "mrskin/driver/model/common.hpp"
#include "mrskin/driver/model/fluid.hpp"

namespace mrskin::model {

struct SteelParams {
  double saturation_polarization_T = 0.75;
  double initial_relative_permeability = 20000.0;
  double coercivity_A_per_m = 0.0;  // 0: no hysteresis
};

struct MagneticCircuitParams {
  int turns = 100;
  double fluid_gap_m = 0.5e-3;   // field path across the fluid (the valve gap)
  double spacer_gap_m = 0.0;     // non-magnetic spacer in series with the fluid gap
  double pole_area_m2 = 7.2e-4;  // flux cross-section in the gap
  double steel_path_length_m = 0.06;
  double steel_area_m2 = 1.0e-4;
  SteelParams steel;
};

// Operating point of the circuit at one current.
struct GapField {
  double field_A_per_m = 0.0;                // H in the fluid gap
  double flux_density_T = 0.0;               // B in the fluid gap
  double steel_field_A_per_m = 0.0;          // H in the steel path
  double steel_flux_density_T = 0.0;         // B in the steel path
  double steel_polarization_fraction = 0.0;  // J / J_s of the steel, 0..1 (near 1: saturated)
  double yield_stress_Pa = 0.0;              // fluid yield stress at the gap field
};

// Play-operator state for the optional hysteresis (the steel's "played" field, A/m).
struct HysteresisState {
  double play_A_per_m = 0.0;
};

// Steel anhysteretic curve and its slope.
MRSKIN_DRIVER_API double steel_flux_density_T(const SteelParams& s, double field_A_per_m) noexcept;
MRSKIN_DRIVER_API double steel_permeability_H_per_m(const SteelParams& s, double field_A_per_m) noexcept;

// Anhysteretic operating point at a coil current (any sign), A.
MRSKIN_DRIVER_API Result<GapField> gap_field(const MagneticCircuitParams& m, const FluidParams& f,
                                             double current_A) noexcept;
// With hysteresis: updates `state` (the play) to the new operating point.
MRSKIN_DRIVER_API Result<GapField> gap_field_hysteretic(const MagneticCircuitParams& m, const FluidParams& f,
                                                        double current_A, HysteresisState& state) noexcept;

// Small-signal reluctance at zero field, 1/H (A-turn per Wb), and the inductance N^2 / R it gives.
MRSKIN_DRIVER_API double zero_field_reluctance_per_H(const MagneticCircuitParams& m,
                                                     const FluidParams& f) noexcept;
MRSKIN_DRIVER_API double zero_field_inductance_H(const MagneticCircuitParams& m,
                                                 const FluidParams& f) noexcept;

// Empty string when the parameters make sense, otherwise "field: reason".
MRSKIN_DRIVER_API const char* check_magnetic(const MagneticCircuitParams& m) noexcept;

}  // namespace mrskin::model
