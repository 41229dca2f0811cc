// A finger on a fluid cell: the contact patch, the cell's own free membrane, and the force.
//
// Contact patch (axisymmetric, finger modelled as a flat pad of radius c on a cell of
// equivalent radius a; c is capped at 0.9 a so that a free rim remains). Linear membrane theory
// with pre-tension T0 gives two exact modes (derivation in docs/model.md):
//   indentation mode  u1 = -d ln(a/r) / ln(a/c)  (d: pad depth), displacing A_eff d with
//                     A_eff = pi (a^2 - c^2) / (2 ln(a/c))          (effective piston area)
//   bulge mode        u2 = s psi(r) / N2, psi = (a^2 - r^2) - (a^2 - c^2) ln(a/r) / ln(a/c),
//                     N2 = integral of psi dA, holding a volume s in the free annulus.
// The two are orthogonal in the tension energy. The cell's energy is
//   U(d, s) = U_pad(d) + U_bulge(s),
//   U_pad'(d)   = F_m(d): the point-load law of membrane.hpp (bending + pre-tension + stretching)
//   U_bulge'(s) = p_b(s) = k1 s + k3 s^3, k1 = 4 T0 / N2 + 16 pi D (a^2 - c^2) / N2^2,
//                 k3 = kappa E' t J4 / (2 N2^4), J4 = integral of psi'^4 dA, E' = E / (1 - nu^2),
//                 kappa = 3 (1 - nu^2) / (16 K^3) (so that c -> 0 reproduces Hencky's law).
// With V_out the volume sent through the valves, s = A_eff d - V_out; the fluid pressure is
// p = p_b(s) and the force on the finger F = F_m(d) + A_eff (p + p0). Work balance holds by
// construction: F dd = dU + (p + p0) dV_out.
//
// Quasi-static cell law (one pressed cell; neighbours and the reservoir at p0):
//   loading (v >= 0):  Q = A_eff v,  p = min(p_b(A_eff d), dp_valves(Q, tau_y))
//                      - below the valves' pressure the cell's own membrane takes the volume
//                        ("bulge"), above it the valves flow and hold p at dp_valves;
//                      - v = 0 gives the breakaway (holding) pressure: the yield threshold.
//   unloading (v < 0): the cell refills through its valves: p = -dp_valves(|Q|, tau_y); the
//                      finger is followed only by what the membrane and p0 give, F >= 0.
// dp_valves comes from the profile's hydraulic graph: each of the cell's links is a branch,
// a branch ending in a valve chamber continues through the chamber's other links in parallel
// (a chamber between two passages in series doubles the yield threshold).
#pragma once

#include <cstdint>

#include "mrskin/driver/export.hpp"
#include "mrskin/driver/model/common.hpp"
#include "mrskin/driver/model/membrane.hpp"

namespace mrskin::model {

struct ContactPatch {
  double cell_radius_m = 0.0;           // a
  double contact_radius_m = 0.0;        // c (finger pad radius, capped at 0.9 a)
  double contact_area_m2 = 0.0;         // pi c^2
  double effective_area_m2 = 0.0;       // A_eff
  double log_ratio = 0.0;               // ln(a / c)
  double bulge_normalisation_m4 = 0.0;  // N2
  double bulge_linear_Pa_per_m3 = 0.0;  // k1
  double bulge_cubic_Pa_per_m9 = 0.0;   // k3
  MembraneParams membrane;
};

// Builds the patch (quadrature at setup; no allocation). degenerate for radii <= 0 or
// a finger smaller than 1 % of the cell.
MRSKIN_DRIVER_API Result<ContactPatch> contact_patch(const MembraneParams& m, double cell_radius_m,
                                                     double finger_radius_m) noexcept;

// Membrane force on the pad at depth d (no fluid pressure), N.
MRSKIN_DRIVER_API Result<double> pad_membrane_force_N(const ContactPatch& p, double indentation_m) noexcept;
// Pressure of the free annulus holding a bulge volume s, Pa, and its inverse.
MRSKIN_DRIVER_API double bulge_pressure_Pa(const ContactPatch& p, double bulge_volume_m3) noexcept;
MRSKIN_DRIVER_API Result<double> bulge_volume_m3(const ContactPatch& p, double pressure_Pa) noexcept;
// Elastic energy stored in the cell's membrane, J.
MRSKIN_DRIVER_API Result<double> stored_energy_J(const ContactPatch& p, double indentation_m,
                                                 double bulge_volume_m3) noexcept;

enum class CellMode : unsigned char {
  bulging,    // loading, valves below their threshold: the cell's own membrane takes the volume
  flowing,    // loading, valves flowing at the imposed rate
  holding,    // zero rate, valves at their yield threshold (the breakaway force)
  refilling,  // unloading, fluid returning through the valves
  released,   // unloading faster than the membrane and p0 can follow: no contact force
};
MRSKIN_DRIVER_API const char* to_string(CellMode m) noexcept;

struct CellLoad {
  double force_N = 0.0;              // contact force on the finger
  double pressure_Pa = 0.0;          // cell fluid pressure, gauge, relative to p0
  double valve_flow_m3_per_s = 0.0;  // leaving the cell through its valves (< 0: refilling)
  double bulge_volume_m3 = 0.0;      // held by the cell's own free membrane
  double membrane_force_N = 0.0;     // F_m(d)
  double effective_area_m2 = 0.0;
  CellMode mode = CellMode::bulging;
};

struct CellEnvelope {
  double force_min_N = 0.0;  // valves at their lowest resistance (loading: minimum current)
  double force_max_N = 0.0;  // valves at their highest allowed current (loading)
  CellLoad at_min;
  CellLoad at_max;
};

}  // namespace mrskin::model
