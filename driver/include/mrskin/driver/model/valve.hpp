// MR valve: Bingham-plastic flow through a slot (gap h, width w, length L) or an annulus
// (mean diameter d: w = pi d, valid for h << d).
//
// Exact law (pressure-driven Bingham flow between parallel plates; e.g. Wereley & Pang, Smart
// Mater. Struct. 7 (1998) 732; Bird, Armstrong & Hassager, Dynamics of Polymeric Liquids):
//   yield threshold   dp_y = 2 tau_y L / h            (no flow while |dp| <= dp_y)
//   flow              Q = (w h^3 dp / (12 mu L)) (1 - zeta)^2 (1 + zeta / 2),   zeta = dp_y / |dp| < 1
// evaluated in this factored form (the expanded 1 - 1.5 zeta + 0.5 zeta^3 cancels as zeta -> 1).
//
// Inverse (flow imposed, find dp): with r = dp_N / dp_y (dp_N = 12 mu Q L / (w h^3), the Newtonian
// drop) the law is the cubic 0.5 zeta^3 - (1.5 + r) zeta + 1 = 0 with one root in (0, 1). As r -> 0
// that root merges with the double root at zeta = 1 (dp - dp_y ~ sqrt(Q)). The exact solver writes
// it as 0.5 e^2 (3 - e) = r (1 - e), e = 1 - zeta (no cancellation) for r < 1, and as
// zeta = (1 + 0.5 zeta^3) / (1.5 + r) for r >= 1, each solved by Newton inside a bracket.
// Limits: tau_y -> 0 gives dp = dp_N exactly; Q -> 0 gives dp -> dp_y.
//
// Wereley-Pang approximation (Wereley & Pang 1998):
//   dp = 12 mu Q L / (w h^3) + c tau_y L / h,  c = 2.07 + 12 Q mu / (12 Q mu + 0.4 w h^2 tau_y)
// Fast path: dp = dp_N + dp_y c(r), c(r) = 1/zeta - r in [1, 1.5], tabulated once (at compile
// time) over r in [2^-40, 2^40] with 16 linear segments per octave, looked up from the bits of r.
//
// Reynolds number Re = rho V D_h / mu, V = |Q| / (w h), D_h = 2 w h / (w + h). Only when a flow
// puts Re above 2300 is a turbulent term added (the paper's Eq. 1 structure p = p_lam + p_turb):
//   dp_turb = (f_Blasius(Re) - 96 / Re) (L / D_h) rho V^2 / 2,  f_Blasius = 0.316 Re^-0.25
// i.e. the excess of turbulent over laminar friction. At the MR skin's flows Re ~ 2.
#pragma once

#include "mrskin/driver/export.hpp"
#include "mrskin/driver/model/common.hpp"

namespace mrskin::model {

struct ValveGeometry {
  enum class Shape : unsigned char { slot, annulus };
  Shape shape = Shape::slot;
  double gap_m = 0.5e-3;
  double width_m = 30e-3;        // slot width; for an annulus pi * mean_diameter_m
  double length_m = 24.01e-3;    // magnetised length along the flow
  double mean_diameter_m = 0.0;  // annulus only
};

MRSKIN_DRIVER_API ValveGeometry slot_geometry(double gap_m, double width_m, double length_m) noexcept;
MRSKIN_DRIVER_API ValveGeometry annulus_geometry(double gap_m, double mean_diameter_m,
                                                 double length_m) noexcept;
// Empty string when the geometry makes sense, otherwise "field: reason".
MRSKIN_DRIVER_API const char* check_valve_geometry(const ValveGeometry& g) noexcept;

enum class ValveMethod : unsigned char { exact, wereley_pang, fast };
MRSKIN_DRIVER_API const char* to_string(ValveMethod m) noexcept;

// Flow and its derivative dQ/d(dp) (the valve's incremental conductance, m^3/(s Pa)).
struct FlowPoint {
  double flow_m3_per_s = 0.0;
  double conductance_m3_per_s_Pa = 0.0;
};

class MRSKIN_DRIVER_API ValveLaw {
 public:
  // Throws mrskin::InvalidArgument naming the bad field.
  ValveLaw(const ValveGeometry& g, double viscosity_Pa_s, double density_kg_per_m3);

  [[nodiscard]] const ValveGeometry& geometry() const noexcept { return geometry_; }
  [[nodiscard]] double viscosity_Pa_s() const noexcept { return viscosity_; }
  [[nodiscard]] double density_kg_per_m3() const noexcept { return density_; }

  // dp_y = 2 tau_y L / h, Pa (tau_y >= 0 assumed).
  [[nodiscard]] double yield_pressure_Pa(double yield_stress_Pa) const noexcept {
    return yield_k_ * yield_stress_Pa;
  }
  // dp_N = 12 mu Q L / (w h^3), Pa.
  [[nodiscard]] double newtonian_pressure_Pa(double flow_m3_per_s) const noexcept {
    return newton_k_ * flow_m3_per_s;
  }
  [[nodiscard]] double reynolds_number(double flow_m3_per_s) const noexcept;
  // 0 unless Re > 2300.
  [[nodiscard]] double turbulent_pressure_Pa(double flow_m3_per_s) const noexcept;
  // The flow at which Re reaches 2300, m^3/s.
  [[nodiscard]] double critical_flow_m3_per_s() const noexcept { return critical_flow_; }
  // Q / dp of a passage without yield below the critical flow, w h^3 / (12 mu L), m^3/(s Pa):
  // flow_point's conductance there, the same bits.
  [[nodiscard]] double newtonian_conductance_m3_per_s_Pa() const noexcept { return flow_k_; }

  // Pressure to flow, exact (explicit factored form; with a safeguarded solve only if Re > 2300).
  [[nodiscard]] Result<double> flow_m3_per_s(double dp_Pa, double yield_stress_Pa) const noexcept;
  [[nodiscard]] Result<FlowPoint> flow_point(double dp_Pa, double yield_stress_Pa) const noexcept;
  // Pressure to flow under any method: exact is explicit; the approximations are inverted
  // by a bracketed bisection on their monotone pressure(Q) (a diagnostic, not a loop path).
  [[nodiscard]] Result<double> flow_m3_per_s(double dp_Pa, double yield_stress_Pa,
                                             ValveMethod method) const noexcept;

  // Flow to pressure (odd in Q; Q = +-0 gives +-dp_y, the breakaway threshold).
  [[nodiscard]] Result<double> pressure_Pa(double flow_m3_per_s, double yield_stress_Pa,
                                           ValveMethod method) const noexcept;
  [[nodiscard]] Result<double> pressure_exact_Pa(double flow_m3_per_s, double yield_stress_Pa) const noexcept;
  [[nodiscard]] Result<double> pressure_wereley_pang_Pa(double flow_m3_per_s,
                                                        double yield_stress_Pa) const noexcept;
  [[nodiscard]] Result<double> pressure_fast_Pa(double flow_m3_per_s, double yield_stress_Pa) const noexcept;

 private:
  ValveGeometry geometry_;
  double viscosity_;
  double density_;
  double newton_k_;  // 12 mu L / (w h^3)
  double yield_k_;   // 2 L / h
  double flow_k_;    // w h^3 / (12 mu L)
  double hydraulic_diameter_m_;
  double reynolds_k_;     // Re per unit |Q|
  double critical_flow_;  // |Q| at Re = 2300
  double wp_k_;           // 0.4 w h^2
};

// The paper's Eq. 3 exactly as printed, for comparison only (status always out_of_regime):
//   Q = (pi d / (24 m)) (l / dp)^2 [20 tau^3 - (12 dp / l) tau^2 + 15 h^2 (dp / l)^2 tau + 2 h^3 (dp / l)^3]
// Its second term has units Pa^3/m beside Pa^3, and the h^2 term's sign and the coefficients
// differ from the exact law, which in the same variables reads
//   Q = (pi d / (24 mu)) (l / dp)^2 [8 tau^3 - 6 h^2 (dp / l)^2 tau + 2 h^3 (dp / l)^3].
// At the device's numbers it predicts negative flow.
MRSKIN_DRIVER_API Result<double> paper_eq3_flow_m3_per_s(double dp_Pa, double yield_stress_Pa, double gap_m,
                                                         double length_m, double mean_diameter_m,
                                                         double viscosity_Pa_s) noexcept;

// Dimensionless inverse shared by all geometries: for r = dp_N / dp_y > 0, the exact
// x = dp / dp_y = 1 / zeta >= 1 (safeguarded Newton), and the fast path's c(r) = x - r.
MRSKIN_DRIVER_API Result<double> bingham_pressure_ratio(double r) noexcept;
MRSKIN_DRIVER_API double bingham_excess_fast(double r) noexcept;

}  // namespace mrskin::model
