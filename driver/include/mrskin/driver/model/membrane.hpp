// The skin: a thin elastomer sheet (thickness t, modulus E, Poisson ratio nu) clamped over a
// fluid cell and pre-tensioned to T0 (N/m). Its deflection under a press is a stretching
// problem, not the beam problem of the paper's Eq. 6.
//
// Each law below is the sum of three stiffnesses, each exact in its own limit:
//   bending    (plate, w << t):            D = E t^3 / (12 (1 - nu^2))
//   pre-tension (linear membrane):         T0
//   stretching (large deflection, w >> t): E t, cubic in w
// Circular sheet of radius a (a square cell of side s uses a = s / sqrt(pi), same area):
//   uniform pressure p, centre deflection w0:
//     p = 64 D w0 / a^4 + 4 T0 w0 / a^2 + E t w0^3 / (K^3 a^4)
//     (clamped plate, Timoshenko & Woinowsky-Krieger s. 62; tensioned membrane; Hencky's
//      membrane w0 = K a (p a / (E t))^(1/3), K ~ 0.65)
//   central load F through a contact of radius c (the finger), centre deflection d:
//     F = 16 pi D d / a^2 + 2 pi T0 d / ln(a / c) + (E t / a^2) d^3 / q(nu)^3,
//     q(nu) = 1.05 - 0.15 nu - 0.16 nu^2   (Schwerin's point-loaded membrane, as fitted by
//      Komaragiri, Begley & Simmonds, J. Appl. Mech. 72 (2005) 203)
// Strip of span l between simple supports (the geometry of the paper's Eq. 6), per unit area:
//     p = 384 D w0 / (5 l^4) + 8 T0 w0 / l^2 + (64/3) E t w0^3 / ((1 - nu^2) l^4)
// whose small-deflection, untensioned limit is exactly Eq. 6 at mid-span with E I -> D.
//
// Regime: w/t < 0.3 bending dominates and Eq. 6 (bending alone) is valid; w/t > 3 the sheet
// is a membrane (bending < 1 % of the load at the paper's numbers); in between the additive
// form is an interpolation (within ~20 % of the von Karman plate solution).
#pragma once

#include "mrskin/driver/export.hpp"
#include "mrskin/driver/model/common.hpp"

namespace mrskin::model {

struct MembraneParams {
  double thickness_m = 0.121e-3;
  double youngs_modulus_Pa = 1.0e6;
  double poisson_ratio = 0.5;
  double pretension_N_per_m = 5.0;
  double hencky_K = 0.65;
};

enum class DeflectionRegime : unsigned char { bending, transition, membrane };
MRSKIN_DRIVER_API const char* to_string(DeflectionRegime r) noexcept;
MRSKIN_DRIVER_API DeflectionRegime deflection_regime(const MembraneParams& m, double deflection_m) noexcept;

// Plate bending stiffness D = E t^3 / (12 (1 - nu^2)), N m.
MRSKIN_DRIVER_API double bending_stiffness_N_m(const MembraneParams& m) noexcept;
// q(nu) of the point-load law.
MRSKIN_DRIVER_API double point_load_q(double poisson_ratio) noexcept;

// Uniform pressure on a clamped circular sheet.
MRSKIN_DRIVER_API Result<double> disk_pressure_Pa(const MembraneParams& m, double radius_m,
                                                  double centre_deflection_m) noexcept;
MRSKIN_DRIVER_API Result<double> disk_deflection_m(const MembraneParams& m, double radius_m,
                                                   double pressure_Pa) noexcept;

struct LoadSplit {
  double total = 0.0;
  double bending = 0.0;
  double pretension = 0.0;
  double stretching = 0.0;
};
// Central load through a contact of radius c < a on a clamped circular sheet, N.
MRSKIN_DRIVER_API Result<LoadSplit> point_load_force_N(const MembraneParams& m, double radius_m,
                                                       double contact_radius_m,
                                                       double centre_deflection_m) noexcept;
// Strip of span l, pressure for a mid-span deflection, Pa.
MRSKIN_DRIVER_API Result<double> strip_pressure_Pa(const MembraneParams& m, double span_m,
                                                   double centre_deflection_m) noexcept;
MRSKIN_DRIVER_API Result<double> strip_deflection_m(const MembraneParams& m, double span_m,
                                                    double pressure_Pa) noexcept;

// The paper's Eq. 6 verbatim: deflection of a simply supported beam of length l under a
// total load p A, at x:  D(x) = p A l^3 / (24 E I) ((x/l)^4 - 2 (x/l)^3 + x/l).
// Status::out_of_regime (value still given) when the mid-span deflection exceeds 0.3 t.
MRSKIN_DRIVER_API Result<double> paper_eq6_deflection_m(double pressure_Pa, double area_m2, double length_m,
                                                        double youngs_modulus_Pa, double second_moment_m4,
                                                        double x_m, double thickness_m) noexcept;

// Empty string when the parameters make sense, otherwise "field: reason".
MRSKIN_DRIVER_API const char* check_membrane(const MembraneParams& m) noexcept;

}  // namespace mrskin::model
