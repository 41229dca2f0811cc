#include "mrskin/driver/model/magnetic.hpp"

#include <algorithm>
#include <cmath>

namespace mrskin::model {

double steel_flux_density_T(const SteelParams& s, double field_A_per_m) noexcept {
  const double k = kMu0_H_per_m * (s.initial_relative_permeability - 1.0) / s.saturation_polarization_T;
  return kMu0_H_per_m * field_A_per_m + s.saturation_polarization_T * std::tanh(k * field_A_per_m);
}

double steel_permeability_H_per_m(const SteelParams& s, double field_A_per_m) noexcept {
  const double k = kMu0_H_per_m * (s.initial_relative_permeability - 1.0) / s.saturation_polarization_T;
  const double t = std::tanh(k * field_A_per_m);
  return kMu0_H_per_m + kMu0_H_per_m * (s.initial_relative_permeability - 1.0) * (1.0 - t * t);
}

namespace {

struct Solved {
  GapField field;
  double play = 0.0;
  Status status = Status::ok;
};

// Solves the circuit for the steel field H_s: R(H_s) = H_s l_s + H_f(B) g + B g_sp / mu0 - N I = 0,
// B = B_an(p(H_s)) A_s / A_p. R is strictly increasing (slope >= l_s), so a bracketed Newton
// (bisection whenever Newton leaves the bracket) always converges.
Solved solve(const MagneticCircuitParams& m, const FluidParams& f, double current_A,
             double play_prev) noexcept {
  Solved out;
  const double hc = m.steel.coercivity_A_per_m;
  const double mmf = static_cast<double>(m.turns) * current_A;
  const double ls = m.steel_path_length_m;
  const double area_ratio = m.steel_area_m2 / m.pole_area_m2;

  struct Eval {
    double r, dr, p, bs, bf, hf;
    Status st;
  };
  auto eval = [&](double hs) -> Eval {
    // The play follows the field only when the field has pushed it to an edge of its band.
    const double p = hc == 0.0 ? hs : std::clamp(play_prev, hs - hc, hs + hc);
    const bool moving = hc == 0.0 || p != play_prev;
    const double bs = steel_flux_density_T(m.steel, p);
    const double bf = bs * area_ratio;
    const Result<double> hf = fluid_field_for_flux_density_A_per_m(f, bf);
    const double r = hs * ls + hf.value * m.fluid_gap_m + bf / kMu0_H_per_m * m.spacer_gap_m - mmf;
    const double dfdb =
        m.fluid_gap_m / fluid_permeability_H_per_m(f, hf.value) + m.spacer_gap_m / kMu0_H_per_m;
    const double dr = ls + (moving ? dfdb * area_ratio * steel_permeability_H_per_m(m.steel, p) : 0.0);
    return {r, dr, p, bs, bf, hf.value, hf.status};
  };

  double lo = std::min(mmf / ls, 0.0) - hc;
  double hi = std::max(mmf / ls, 0.0) + hc;
  if (lo == hi) {  // zero current and no hysteresis
    const Eval e = eval(0.0);
    out.play = e.p;
    return out;
  }
  double hs = 0.5 * (lo + hi);
  for (int i = 0; i < 200; ++i) {
    const Eval e = eval(hs);
    if (e.st != Status::ok) {
      out.status = e.st;
      return out;
    }
    if (e.r < 0.0) {
      lo = hs;
    } else {
      hi = hs;
    }
    double next = hs - e.r / e.dr;
    const double scale = std::max({std::fabs(hs), std::fabs(next), 1e-300});
    // Converged when the Newton step itself is below rounding; only then the bracket test,
    // so that a root sitting on a bracket end is never bisected away.
    const bool converged = e.r == 0.0 || std::fabs(next - hs) <= 4e-16 * scale;
    if (!converged && !(next > lo && next < hi)) {
      next = 0.5 * (lo + hi);
    }
    if (converged || (hi - lo) <= 4e-16 * scale) {
      const Eval fin = eval(next);
      out.field.steel_field_A_per_m = next;
      out.field.steel_flux_density_T = fin.bs;
      out.field.flux_density_T = fin.bf;
      out.field.field_A_per_m = fin.hf;
      out.field.steel_polarization_fraction =
          std::fabs(fin.bs - kMu0_H_per_m * fin.p) / m.steel.saturation_polarization_T;
      out.field.yield_stress_Pa = yield_stress_Pa(f, fin.hf).value;
      out.play = fin.p;
      return out;
    }
    hs = next;
  }
  out.status = Status::no_convergence;
  return out;
}

Status check_current(double current_A) noexcept {
  return std::isfinite(current_A) ? Status::ok : Status::not_finite;
}

}  // namespace

Result<GapField> gap_field(const MagneticCircuitParams& m, const FluidParams& f, double current_A) noexcept {
  if (const Status s = check_current(current_A); s != Status::ok) {
    return failure<GapField>(s);
  }
  MagneticCircuitParams anhysteretic = m;
  anhysteretic.steel.coercivity_A_per_m = 0.0;
  const Solved s = solve(anhysteretic, f, current_A, 0.0);
  return {s.field, s.status};
}

Result<GapField> gap_field_hysteretic(const MagneticCircuitParams& m, const FluidParams& f, double current_A,
                                      HysteresisState& state) noexcept {
  if (const Status s = check_current(current_A); s != Status::ok) {
    return failure<GapField>(s);
  }
  const Solved s = solve(m, f, current_A, state.play_A_per_m);
  if (s.status == Status::ok) {
    state.play_A_per_m = s.play;
  }
  return {s.field, s.status};
}

double zero_field_reluctance_per_H(const MagneticCircuitParams& m, const FluidParams& f) noexcept {
  const double mu_f = fluid_permeability_H_per_m(f, 0.0);
  const double mu_s = kMu0_H_per_m * m.steel.initial_relative_permeability;
  return m.fluid_gap_m / (mu_f * m.pole_area_m2) + m.spacer_gap_m / (kMu0_H_per_m * m.pole_area_m2) +
         m.steel_path_length_m / (mu_s * m.steel_area_m2);
}

double zero_field_inductance_H(const MagneticCircuitParams& m, const FluidParams& f) noexcept {
  const auto n = static_cast<double>(m.turns);
  return n * n / zero_field_reluctance_per_H(m, f);
}

const char* check_magnetic(const MagneticCircuitParams& m) noexcept {
  auto pos = [](double x) { return std::isfinite(x) && x > 0.0; };
  if (m.turns < 1 || m.turns > 100000) {
    return "turns: must be in 1..100000";
  }
  if (!pos(m.fluid_gap_m)) {
    return "fluid_gap_m: must be > 0";
  }
  if (!(std::isfinite(m.spacer_gap_m) && m.spacer_gap_m >= 0.0)) {
    return "spacer_gap_m: must be >= 0";
  }
  if (!pos(m.pole_area_m2)) {
    return "pole_area_m2: must be > 0";
  }
  if (!pos(m.steel_path_length_m)) {
    return "steel_path_length_m: must be > 0";
  }
  if (!pos(m.steel_area_m2)) {
    return "steel_area_m2: must be > 0";
  }
  if (!pos(m.steel.saturation_polarization_T) || m.steel.saturation_polarization_T > 3.0) {
    return "steel.saturation_polarization_T: must be in (0, 3] T";
  }
  if (!(std::isfinite(m.steel.initial_relative_permeability) &&
        m.steel.initial_relative_permeability > 1.0)) {
    return "steel.initial_relative_permeability: must be > 1";
  }
  if (!(std::isfinite(m.steel.coercivity_A_per_m) && m.steel.coercivity_A_per_m >= 0.0)) {
    return "steel.coercivity_A_per_m: must be >= 0";
  }
  return "";
}

}  // namespace mrskin::model
