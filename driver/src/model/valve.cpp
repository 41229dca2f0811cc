#include "mrskin/driver/model/valve.hpp"

#include <array>
#include <bit>
#include <cmath>
#include <cstdint>
#include <initializer_list>
#include <string>

#include "mrskin/driver/errors.hpp"

namespace mrskin::model {

// ---- the dimensionless inverse -------------------------------------------------------

namespace {

// Exact x = dp / dp_y = 1 / zeta for r = dp_N / dp_y, and the safeguarded solve behind it.
// Returns x; for r >= 1 also gives q = 0.5 zeta^3 so that dp = (1.5 dp_y + dp_N) / (1 + q)
// can be formed without the rounding of dp_y * r.
struct RatioSolve {
  double x = 1.0;
  double q = 0.0;  // 0.5 zeta^3 (r >= 1 branch), else unused
  bool newtonian_form = false;
  Status status = Status::ok;
};

RatioSolve solve_ratio(double r) noexcept {
  RatioSolve out;
  if (r == 0.0) {
    return out;  // x = 1: the threshold
  }
  if (std::isinf(r)) {
    out.newtonian_form = true;
    return out;  // q = 0
  }
  if (r < 1.0) {
    // h(e) = 0.5 e^2 (3 - e) - r (1 - e): increasing and convex on [0, 1], h(0) = -r, h(1) = 1.
    // Start at the root of the quadratic 1.5 e^2 + r e - r (h <= that quadratic, so the start is
    // left of the root); the first Newton step lands right of it and the rest descend monotonically.
    double lo = 2.0 * r / (std::sqrt(r * r + 6.0 * r) + r);
    double hi = 1.0;
    double e = lo;
    for (int i = 0; i < 60; ++i) {
      const double h = 0.5 * e * e * (3.0 - e) - r * (1.0 - e);
      if (h < 0.0) {
        lo = e;
      } else {
        hi = e;
      }
      const double dh = e * (3.0 - 1.5 * e) + r;
      double next = e - h / dh;
      const bool converged = h == 0.0 || std::fabs(next - e) <= 4.5e-16 * e;
      if (!converged && !(next >= lo && next <= hi)) {
        next = 0.5 * (lo + hi);  // safeguard: never leave the bracket
      }
      if (converged || hi - lo <= 4.5e-16 * hi) {
        out.x = 1.0 / (1.0 - next);
        return out;
      }
      e = next;
    }
    out.status = Status::no_convergence;
    return out;
  }
  // r >= 1: g(z) = 0.5 z^3 - (1.5 + r) z + 1, decreasing and convex on [0, 1]; root in
  // [1 / (1.5 + r), 1.5 / (1.5 + r)]. Newton from the left end climbs monotonically.
  const double s = 1.5 + r;
  double lo = 1.0 / s;
  double hi = 1.5 / s;
  double z = lo;
  for (int i = 0; i < 60; ++i) {
    const double g = (0.5 * z * z * z + 1.0) - s * z;
    if (g > 0.0) {
      lo = z;
    } else {
      hi = z;
    }
    const double dg = 1.5 * z * z - s;
    double next = z - g / dg;
    const bool converged = g == 0.0 || std::fabs(next - z) <= 4.5e-16 * z;
    if (!converged && !(next >= lo && next <= hi)) {
      next = 0.5 * (lo + hi);
    }
    if (converged || hi - lo <= 4.5e-16 * hi) {
      out.q = 0.5 * next * next * next;
      out.x = s / (1.0 + out.q);
      out.newtonian_form = true;
      return out;
    }
    z = next;
  }
  out.status = Status::no_convergence;
  return out;
}

// Compile-time evaluation of c(r) = x - r for the fast table (plain Newton, no std:: math).
constexpr double table_excess(double r) {
  if (r < 1.0) {
    double e = 1.0;  // right end: Newton descends monotonically on a convex increasing h
    for (int i = 0; i < 400; ++i) {
      const double h = 0.5 * e * e * (3.0 - e) - r * (1.0 - e);
      const double next = e - h / (e * (3.0 - 1.5 * e) + r);
      if (!(next < e)) {
        break;
      }
      e = next;
    }
    return 1.0 / (1.0 - e) - r;
  }
  const double s = 1.5 + r;
  double z = 1.0 / s;
  for (int i = 0; i < 400; ++i) {
    const double next = z - ((0.5 * z * z * z + 1.0) - s * z) / (1.5 * z * z - s);
    if (!(next > z)) {
      break;
    }
    z = next;
  }
  const double q = 0.5 * z * z * z;
  return (1.5 - r * q) / (1.0 + q);
}

constexpr int kSubBits = 4;  // 16 linear segments per octave
constexpr int kOctaveMin = -40;
constexpr int kOctaveMax = 40;
constexpr int kBins = (kOctaveMax - kOctaveMin) << kSubBits;
constexpr std::int64_t kKeyMin = static_cast<std::int64_t>(kOctaveMin + 1023) << kSubBits;
constexpr int kMantissaShift = 52 - kSubBits;

struct Segment {
  double c0;
  double slope;
};

constexpr double pow2(int e) {
  double p = 1.0;
  for (int i = 0; i < (e < 0 ? -e : e); ++i) {
    p = e < 0 ? p * 0.5 : p * 2.0;
  }
  return p;
}

constexpr double node(int i) {
  const int e = kOctaveMin + (i >> kSubBits);
  const int j = i & ((1 << kSubBits) - 1);
  return pow2(e) * (1.0 + static_cast<double>(j) / static_cast<double>(1 << kSubBits));
}

constexpr std::array<Segment, kBins> make_table() {
  std::array<Segment, kBins> t{};
  double r0 = node(0);
  double c0 = table_excess(r0);
  for (int i = 0; i < kBins; ++i) {
    const double r1 = node(i + 1);
    const double c1 = table_excess(r1);
    t[static_cast<std::size_t>(i)] = {c0, (c1 - c0) / (r1 - r0)};
    r0 = r1;
    c0 = c1;
  }
  return t;
}

constexpr std::array<Segment, kBins> kExcessTable = make_table();

inline double excess_lookup(double r) noexcept {
  const auto bits = std::bit_cast<std::uint64_t>(r);
  const std::int64_t idx = static_cast<std::int64_t>(bits >> kMantissaShift) - kKeyMin;
  if (idx < 0) {
    return 1.0;  // r < 2^-40 (and r = 0): dp = dp_y (1 + sqrt(2r/3) + ...), error < 1e-6
  }
  if (idx >= kBins) {
    return 1.5;  // r >= 2^40 or inf (tau_y = 0): c -> 1.5, and dp_y c is negligible or zero
  }
  const auto left = std::bit_cast<double>(bits & ~((std::uint64_t{1} << kMantissaShift) - 1));
  const Segment& s = kExcessTable[static_cast<std::size_t>(idx)];
  return s.c0 + s.slope * (r - left);
}

Status check_inputs(double a, double tau) noexcept {
  if (!std::isfinite(a) || !std::isfinite(tau)) {
    return Status::not_finite;
  }
  if (tau < 0.0) {
    return Status::negative;
  }
  return Status::ok;
}

Result<double> finish(double dp, double sign_of) noexcept {
  if (!std::isfinite(dp)) {
    return failure<double>(Status::overflow);
  }
  return {std::copysign(dp, sign_of)};
}

}  // namespace

Result<double> bingham_pressure_ratio(double r) noexcept {
  if (std::isnan(r)) {
    return failure<double>(Status::not_finite);
  }
  if (r < 0.0) {
    return failure<double>(Status::negative);
  }
  const RatioSolve s = solve_ratio(r);
  if (std::isinf(r)) {
    return {r};
  }
  return {s.x, s.status};
}

double bingham_excess_fast(double r) noexcept { return excess_lookup(r); }

Result<double> paper_eq3_flow_m3_per_s(double dp_Pa, double yield_stress_Pa, double gap_m, double length_m,
                                       double mean_diameter_m, double viscosity_Pa_s) noexcept {
  for (const double x : {dp_Pa, yield_stress_Pa, gap_m, length_m, mean_diameter_m, viscosity_Pa_s}) {
    if (!std::isfinite(x)) {
      return failure<double>(Status::not_finite);
    }
  }
  if (dp_Pa == 0.0 || !(gap_m > 0.0 && length_m > 0.0 && mean_diameter_m > 0.0 && viscosity_Pa_s > 0.0)) {
    return failure<double>(Status::degenerate);
  }
  const double t = yield_stress_Pa;
  const double g = dp_Pa / length_m;  // pressure gradient
  const double h = gap_m;
  const double bracket =
      20.0 * t * t * t - 12.0 * g * t * t + 15.0 * h * h * g * g * t + 2.0 * h * h * h * g * g * g;
  const double l_over_dp = length_m / dp_Pa;
  const double q = kPi * mean_diameter_m / (24.0 * viscosity_Pa_s) * l_over_dp * l_over_dp * bracket;
  if (!std::isfinite(q)) {
    return failure<double>(Status::overflow);
  }
  return {q, Status::out_of_regime};
}

// ---- geometry ------------------------------------------------------------------------

ValveGeometry slot_geometry(double gap_m, double width_m, double length_m) noexcept {
  ValveGeometry g;
  g.shape = ValveGeometry::Shape::slot;
  g.gap_m = gap_m;
  g.width_m = width_m;
  g.length_m = length_m;
  return g;
}

ValveGeometry annulus_geometry(double gap_m, double mean_diameter_m, double length_m) noexcept {
  ValveGeometry g;
  g.shape = ValveGeometry::Shape::annulus;
  g.gap_m = gap_m;
  g.mean_diameter_m = mean_diameter_m;
  g.width_m = kPi * mean_diameter_m;
  g.length_m = length_m;
  return g;
}

const char* check_valve_geometry(const ValveGeometry& g) noexcept {
  auto pos = [](double x) { return std::isfinite(x) && x > 0.0; };
  if (!pos(g.gap_m)) {
    return "gap_m: must be > 0";
  }
  if (!pos(g.length_m)) {
    return "length_m: must be > 0";
  }
  if (g.shape == ValveGeometry::Shape::annulus) {
    if (!pos(g.mean_diameter_m)) {
      return "mean_diameter_m: must be > 0 for an annulus";
    }
    if (g.gap_m > 0.1 * g.mean_diameter_m) {
      return "gap_m: the annulus law needs gap <= 0.1 * mean_diameter_m (narrow-gap flat-plate limit)";
    }
    return "";
  }
  if (!pos(g.width_m)) {
    return "width_m: must be > 0";
  }
  if (g.gap_m > 0.2 * g.width_m) {
    return "gap_m: the slot law needs gap <= 0.2 * width_m (parallel-plate limit)";
  }
  return "";
}

const char* to_string(ValveMethod m) noexcept {
  switch (m) {
    case ValveMethod::exact:
      return "exact";
    case ValveMethod::wereley_pang:
      return "wereley-pang";
    case ValveMethod::fast:
      return "fast";
  }
  return "unknown";
}

// ---- the law -------------------------------------------------------------------------

ValveLaw::ValveLaw(const ValveGeometry& g, double viscosity_Pa_s, double density_kg_per_m3)
    : geometry_(g), viscosity_(viscosity_Pa_s), density_(density_kg_per_m3) {
  if (const std::string why = check_valve_geometry(g); !why.empty()) {
    throw InvalidArgument("valve " + why);
  }
  if (!(std::isfinite(viscosity_Pa_s) && viscosity_Pa_s > 0.0)) {
    throw InvalidArgument("valve viscosity_Pa_s: must be > 0 (got " + std::to_string(viscosity_Pa_s) + ")");
  }
  if (!(std::isfinite(density_kg_per_m3) && density_kg_per_m3 > 0.0)) {
    throw InvalidArgument("valve density_kg_per_m3: must be > 0 (got " + std::to_string(density_kg_per_m3) +
                          ")");
  }
  const double h = g.gap_m;
  const double w = g.width_m;
  const double l = g.length_m;
  newton_k_ = 12.0 * viscosity_Pa_s * l / (w * h * h * h);
  yield_k_ = 2.0 * l / h;
  flow_k_ = w * h * h * h / (12.0 * viscosity_Pa_s * l);
  hydraulic_diameter_m_ = 2.0 * w * h / (w + h);
  reynolds_k_ = density_kg_per_m3 * hydraulic_diameter_m_ / (viscosity_Pa_s * w * h);
  critical_flow_ = kCriticalReynolds / reynolds_k_;
  wp_k_ = 0.4 * w * h * h;
}

double ValveLaw::reynolds_number(double flow_m3_per_s) const noexcept {
  return reynolds_k_ * std::fabs(flow_m3_per_s);
}

double ValveLaw::turbulent_pressure_Pa(double flow_m3_per_s) const noexcept {
  const double q = std::fabs(flow_m3_per_s);
  if (!(q > critical_flow_)) {
    return 0.0;  // laminar: not computed
  }
  const double re = reynolds_k_ * q;
  const double excess_friction = 0.316 / std::sqrt(std::sqrt(re)) - 96.0 / re;
  if (excess_friction <= 0.0) {
    return 0.0;
  }
  const double v = q / (geometry_.width_m * geometry_.gap_m);
  return excess_friction * (geometry_.length_m / hydraulic_diameter_m_) * 0.5 * density_ * v * v;
}

Result<double> ValveLaw::pressure_exact_Pa(double flow_m3_per_s, double yield_stress_Pa) const noexcept {
  const double q = std::fabs(flow_m3_per_s);
  if (const Status s = check_inputs(flow_m3_per_s, yield_stress_Pa); s != Status::ok) {
    return failure<double>(s);
  }
  const double dp_n = newton_k_ * q;
  const double dp_y = yield_k_ * yield_stress_Pa;
  double dp = 0.0;
  if (dp_y == 0.0) {
    dp = dp_n;
  } else if (dp_n == 0.0) {
    dp = dp_y;
  } else {
    const RatioSolve s = solve_ratio(dp_n / dp_y);
    if (s.status != Status::ok) {
      return failure<double>(s.status);
    }
    dp = s.newtonian_form ? (1.5 * dp_y + dp_n) / (1.0 + s.q) : dp_y * s.x;
  }
  dp += turbulent_pressure_Pa(q);
  return finish(dp, flow_m3_per_s);
}

Result<double> ValveLaw::pressure_fast_Pa(double flow_m3_per_s, double yield_stress_Pa) const noexcept {
  const double q = std::fabs(flow_m3_per_s);
  if (const Status s = check_inputs(flow_m3_per_s, yield_stress_Pa); s != Status::ok) {
    return failure<double>(s);
  }
  const double dp_n = newton_k_ * q;
  const double dp_y = yield_k_ * yield_stress_Pa;
  double dp = dp_y == 0.0 ? dp_n : dp_n + dp_y * excess_lookup(dp_n / dp_y);
  if (q > critical_flow_) {
    dp += turbulent_pressure_Pa(q);
  }
  return finish(dp, flow_m3_per_s);
}

Result<double> ValveLaw::pressure_wereley_pang_Pa(double flow_m3_per_s,
                                                  double yield_stress_Pa) const noexcept {
  const double q = std::fabs(flow_m3_per_s);
  if (const Status s = check_inputs(flow_m3_per_s, yield_stress_Pa); s != Status::ok) {
    return failure<double>(s);
  }
  const double dp_n = newton_k_ * q;
  const double viscous = 12.0 * q * viscosity_;
  const double denom = viscous + wp_k_ * yield_stress_Pa;
  const double c = 2.07 + (denom > 0.0 ? viscous / denom : 0.0);
  double dp = dp_n + c * 0.5 * yield_k_ * yield_stress_Pa;
  dp += turbulent_pressure_Pa(q);
  return finish(dp, flow_m3_per_s);
}

Result<double> ValveLaw::pressure_Pa(double flow_m3_per_s, double yield_stress_Pa,
                                     ValveMethod method) const noexcept {
  switch (method) {
    case ValveMethod::exact:
      return pressure_exact_Pa(flow_m3_per_s, yield_stress_Pa);
    case ValveMethod::wereley_pang:
      return pressure_wereley_pang_Pa(flow_m3_per_s, yield_stress_Pa);
    case ValveMethod::fast:
      return pressure_fast_Pa(flow_m3_per_s, yield_stress_Pa);
  }
  return failure<double>(Status::out_of_range);
}

Result<FlowPoint> ValveLaw::flow_point(double dp_Pa, double yield_stress_Pa) const noexcept {
  const double a = std::fabs(dp_Pa);
  if (const Status s = check_inputs(dp_Pa, yield_stress_Pa); s != Status::ok) {
    return failure<FlowPoint>(s);
  }
  const double dp_y = yield_k_ * yield_stress_Pa;
  if (a <= dp_y) {
    return {FlowPoint{0.0, 0.0}};
  }
  // Factored form; 1 - zeta as (|dp| - dp_y) / |dp| (exact subtraction near the threshold).
  const double one_minus = (a - dp_y) / a;
  const double zeta = dp_y / a;
  double q = flow_k_ * a * one_minus * one_minus * (1.0 + 0.5 * zeta);
  double dq = flow_k_ * one_minus * (1.0 + zeta + zeta * zeta);  // flow_k (1 - zeta^3)
  if (q > critical_flow_) {
    // Turbulent branch: dp(Q) = laminar(Q) + turbulent(Q) is increasing and has no turbulent
    // part up to the critical flow; find Q in [Q_crit, Q_laminar] by bisection on the exact
    // inverse, geometric while the bracket spans more than a factor 2 (rare: Re > 2300 only).
    double lo = critical_flow_;
    double hi = q;
    for (int i = 0; i < 400 && hi - lo > 1e-15 * hi; ++i) {
      const double mid = hi > 2.0 * lo ? std::sqrt(lo) * std::sqrt(hi) : 0.5 * (lo + hi);
      const Result<double> p = pressure_exact_Pa(mid, yield_stress_Pa);
      if (p.ok() && p.value < a) {
        lo = mid;
      } else if (p.ok() || p.status == Status::overflow) {
        hi = mid;  // an overflowing pressure is above any finite |dp|
      } else {
        return failure<FlowPoint>(p.status);
      }
    }
    q = 0.5 * (lo + hi);
    const double h = 1e-6 * q;
    const double p1 = pressure_exact_Pa(q + h, yield_stress_Pa).value;
    const double p0 = pressure_exact_Pa(q - h, yield_stress_Pa).value;
    dq = p1 > p0 ? 2.0 * h / (p1 - p0) : 0.0;
  }
  if (!std::isfinite(q) || !std::isfinite(dq)) {
    return failure<FlowPoint>(Status::overflow);
  }
  return {FlowPoint{std::copysign(q, dp_Pa), dq}};
}

Result<double> ValveLaw::flow_m3_per_s(double dp_Pa, double yield_stress_Pa) const noexcept {
  const Result<FlowPoint> p = flow_point(dp_Pa, yield_stress_Pa);
  return {p.value.flow_m3_per_s, p.status};
}

Result<double> ValveLaw::flow_m3_per_s(double dp_Pa, double yield_stress_Pa,
                                       ValveMethod method) const noexcept {
  if (method == ValveMethod::exact) {
    return flow_m3_per_s(dp_Pa, yield_stress_Pa);
  }
  const double a = std::fabs(dp_Pa);
  if (const Status s = check_inputs(dp_Pa, yield_stress_Pa); s != Status::ok) {
    return failure<double>(s);
  }
  const Result<double> at_zero = pressure_Pa(0.0, yield_stress_Pa, method);
  if (a <= at_zero.value) {
    return {std::copysign(0.0, dp_Pa)};  // below the method's own threshold
  }
  // Every method's pressure is at least the Newtonian drop, so Q <= |dp| / k_N brackets it.
  double lo = 0.0;
  double hi = a / newton_k_;
  for (int i = 0; i < 2000 && hi - lo > 1e-15 * hi; ++i) {
    const double mid = 0.5 * (lo + hi);
    const Result<double> p = pressure_Pa(mid, yield_stress_Pa, method);
    if (!p.ok()) {
      return failure<double>(p.status);
    }
    (p.value < a ? lo : hi) = mid;
  }
  return finish(0.5 * (lo + hi), dp_Pa);
}

}  // namespace mrskin::model
