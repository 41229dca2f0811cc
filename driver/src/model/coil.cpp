#include "mrskin/driver/model/coil.hpp"

#include <cmath>
#include <limits>

namespace mrskin::model {

double current_loop_time_constant_s(const CoilParams& c) noexcept {
  return 1.0 / (2.0 * kPi * c.driver_bandwidth_Hz);
}
double coil_time_constant_s(const CoilParams& c) noexcept {
  return current_loop_time_constant_s(c) + c.eddy_time_constant_s;
}
double open_loop_time_constant_s(const CoilParams& c) noexcept { return c.inductance_H / c.resistance_ohm; }

namespace {

// Current after `dt` under the driver, exact for a constant command. loop_decay: e^{-w dt} if the
// caller has it (used when no slew-limited segment shortens the linear one), else NaN.
double advance_current(const CoilParams& c, double i0, double cmd, double dt, double loop_decay) noexcept {
  const double w = 2.0 * kPi * c.driver_bandwidth_Hz;
  const double a = c.resistance_ohm / c.inductance_H;  // 1/s
  double i = i0;
  double t = dt;
  // Slew-limited segment: the loop asks for w (cmd - i) but the supply gives at most
  // (+-V - R i) / L. Follow the rail until the request fits, then the linear loop.
  for (int seg = 0; seg < 2 && t > 0.0; ++seg) {
    const double dir = cmd >= i ? 1.0 : -1.0;
    const double rail_rate = (dir * c.supply_voltage_V - c.resistance_ohm * i) / c.inductance_H;
    const double want = w * (cmd - i);
    if (std::fabs(want) <= std::fabs(rail_rate) || dir * rail_rate <= 0.0) {
      break;  // linear (or the rail cannot help: the loop is as fast as it gets)
    }
    // On the rail: i(t) = i_inf + (i - i_inf) e^{-a t}, i_inf = dir V / R. It leaves the rail when
    // w (cmd - i) = (dir V - R i) / L  ->  i* = (w cmd - dir V / L) / (w - a).
    const double i_inf = dir * c.supply_voltage_V / c.resistance_ohm;
    const double i_star = (w * cmd - dir * c.supply_voltage_V / c.inductance_H) / (w - a);
    double t_rail = t;
    if (w != a && (i_star - i) * dir > 0.0 && (i_inf - i_star) * dir > 0.0) {
      t_rail = std::log((i - i_inf) / (i_star - i_inf)) / a;
    }
    if (!(t_rail >= 0.0) || t_rail > t) {
      t_rail = t;
    }
    i = i_inf + (i - i_inf) * std::exp(-a * t_rail);
    t -= t_rail;
  }
  if (t > 0.0) {
    i = cmd + (i - cmd) * (t == dt && !std::isnan(loop_decay) ? loop_decay : std::exp(-w * t));
  }
  return i;
}

Result<CoilState> step_coil(const CoilParams& c, const CoilState& s, double command_A, double dt_s,
                            double loop_decay, double eddy_decay) noexcept {
  if (!std::isfinite(command_A) || !std::isfinite(dt_s) || !std::isfinite(s.current_A) ||
      !std::isfinite(s.field_current_A)) {
    return failure<CoilState>(Status::not_finite);
  }
  if (dt_s < 0.0) {
    return failure<CoilState>(Status::negative);
  }
  if (std::fabs(command_A) > c.max_current_A) {  // negative: a bipolar driver reversing the field
    return failure<CoilState>(Status::out_of_range);
  }
  CoilState out;
  out.current_A = advance_current(c, s.current_A, command_A, dt_s, loop_decay);
  if (c.eddy_time_constant_s <= 0.0) {
    out.field_current_A = out.current_A;
    return {out};
  }
  // First-order lag with a linear input between the two currents (exact for that input).
  const double h = dt_s / c.eddy_time_constant_s;
  const double slope_tau = h > 0.0 ? (out.current_A - s.current_A) / h : 0.0;
  const double decay = std::isnan(eddy_decay) ? std::exp(-h) : eddy_decay;
  out.field_current_A = out.current_A - slope_tau + (s.field_current_A - s.current_A + slope_tau) * decay;
  return {out};
}

}  // namespace

Result<CoilState> coil_step(const CoilParams& c, const CoilState& s, double command_A, double dt_s) noexcept {
  constexpr double kNone = std::numeric_limits<double>::quiet_NaN();
  return step_coil(c, s, command_A, dt_s, kNone, kNone);
}

CoilDecay coil_decay(const CoilParams& c, double dt_s) noexcept {
  // The same expressions as coil_step's, so the decays are the same bits.
  CoilDecay d;
  d.dt_s = dt_s;
  d.loop = std::exp(-(2.0 * kPi * c.driver_bandwidth_Hz) * dt_s);
  // (Not used where the eddy lag is off; NaN parameters stay NaN, as in coil_step.)
  d.eddy = c.eddy_time_constant_s <= 0.0 ? 1.0 : std::exp(-(dt_s / c.eddy_time_constant_s));
  return d;
}

Result<CoilState> coil_step(const CoilParams& c, const CoilState& s, double command_A,
                            const CoilDecay& decay) noexcept {
  return step_coil(c, s, command_A, decay.dt_s, decay.loop, decay.eddy);
}

const char* check_coil(const CoilParams& c) noexcept {
  auto pos = [](double x) { return std::isfinite(x) && x > 0.0; };
  if (!pos(c.resistance_ohm)) {
    return "resistance_ohm: must be > 0";
  }
  if (!pos(c.inductance_H)) {
    return "inductance_H: must be > 0";
  }
  if (!pos(c.supply_voltage_V)) {
    return "supply_voltage_V: must be > 0";
  }
  if (!pos(c.max_current_A)) {
    return "max_current_A: must be > 0";
  }
  if (c.supply_voltage_V < c.resistance_ohm * c.max_current_A) {
    return "supply_voltage_V: below R * max_current_A, the driver cannot reach its own maximum";
  }
  if (!pos(c.current_resolution_A) || c.current_resolution_A > c.max_current_A) {
    return "current_resolution_A: must be in (0, max_current_A]";
  }
  if (c.max_current_A / c.current_resolution_A > 4095.5) {
    return "current_resolution_A: max_current_A / resolution exceeds the 4095 counts of the wire protocol";
  }
  if (!pos(c.driver_bandwidth_Hz)) {
    return "driver_bandwidth_Hz: must be > 0";
  }
  if (!(std::isfinite(c.eddy_time_constant_s) && c.eddy_time_constant_s >= 0.0)) {
    return "eddy_time_constant_s: must be >= 0";
  }
  return "";
}

}  // namespace mrskin::model
