#include "mrskin/driver/model/inverse.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#ifdef MRSKIN_INVERSE_DEBUG
#include <cstdio>
#endif
#include <limits>
#include <string>
#include <type_traits>
#include <utility>

#include "mrskin/driver/errors.hpp"

namespace mrskin::model {

namespace {

bool finite(double x) noexcept { return std::isfinite(x); }

// Table resolution (segments): cubic Hermite with exact slopes, so the error goes as K^-4.
constexpr int kTableSegments = 256;
// The loop's branch-flow table: linear, resampled from the Hermite one (two loads, one FMA).
constexpr int kLinearSegments = 4096;
constexpr int kCurrentSegments = 2048;
// Row-space least squares is dense up to this many cells in one component; larger components
// (big grids in full contact) fall back to projected Gauss-Seidel.
constexpr std::size_t kDenseRows = 32;
constexpr int kFallbackSweeps = 60;
constexpr int kMaxActiveSetPasses = 24;
constexpr int kMaxBacktracks = 4;
constexpr std::size_t kMaxEscapes = 8;  // trials: a shared valve opened or shut
// Levenberg-Marquardt damping, relative to a cell's unit sensitivity to its valves.
constexpr double kStartDamping = 1e-3;
constexpr double kMinDamping = 1e-7;
// A flowing cell's row is linearised at its aimed pressure while the predicted correction is
// within this fraction of it, else at its true pressure (one forward solve).
constexpr double kLinearisationReach = 0.02;
// A warm-started component whose every row is within this fraction of its aim takes one
// unverified step (tracking); beyond it, the full damped Gauss-Newton with backtracking.
constexpr double kTrackReach = 0.02;
// Chord steps (the last factorisation reused) while every row is within this fraction of its aim,
// for at most kChordAge ticks.
constexpr double kChordReach = 0.005;
constexpr double kChordFloor_N = 0.005;
constexpr int kChordAge = 16;
constexpr double kMaxRate_m_per_s = 10.0;  // beyond any finger: out_of_range
constexpr double kMinExponent = 0.5;
constexpr double kMaxExponent = 4.0;

// ---- dimensionless branch law (construction only: exact, safeguarded) ---------------------
// x(r): a passage's pressure over its yield threshold at r = dp_N / dp_y (valve.hpp).
double x_exact(double r) { return r <= 0.0 ? 1.0 : bingham_pressure_ratio(r).value; }
// dx/dr = 1 / (zeta (1.5 + r - 1.5 zeta^2)), zeta = 1 / x (differentiating the cubic).
double dx_exact(double r) {
  const double zeta = 1.0 / x_exact(r);
  return 1.0 / (zeta * (1.5 + r - 1.5 * zeta * zeta));
}

// A branch: inlet passage and m outlet passages in parallel (m = 0: one passage to a sink).
struct BranchShape {
  int m = 0;
  double s = 1.0;  // passages in series: threshold multiplier
  double g = 1.0;  // Newtonian resistance over one passage's: 1 + 1/m
  double a = 1.5;  // large-flow intercept: Phi -> g r + a
  double phi(double r) const { return m > 0 ? x_exact(r) + x_exact(r / m) : x_exact(r); }
  double dphi(double r) const { return m > 0 ? dx_exact(r) + dx_exact(r / m) / m : dx_exact(r); }
  // Phi(r) = target, r >= 0; bisection in w = sqrt(r) (Phi has an infinite slope at r = 0).
  double r_of_phi(double target) const {
    double lo = std::sqrt(std::max(0.0, (target - a) / g));
    double hi = std::sqrt(std::max(0.0, (target - s) / g)) * 1.0000001 + 1e-300;
    for (int i = 0; i < 400 && hi - lo > 1e-17 * hi; ++i) {
      const double mid = 0.5 * (lo + hi);
      (phi(mid * mid) < target ? lo : hi) = mid;
    }
    const double w = 0.5 * (lo + hi);
    return w * w;
  }
};

BranchShape shape_of(int m) {
  BranchShape b;
  b.m = m;
  b.s = m > 0 ? 2.0 : 1.0;
  b.g = m > 0 ? 1.0 + 1.0 / m : 1.0;
  b.a = 1.5 * b.s;
  return b;
}

// Cubic Hermite on [0, 1] with K uniform segments: values and slopes at the nodes.
struct Hermite {
  std::vector<double> y;
  std::vector<double> dy;  // d/du
};

struct HermiteValue {
  double value = 0.0;
  double slope = 0.0;
};

// Linear table over [0, 1]: interleaved (value at node k, increment to node k + 1).
inline HermiteValue linear(const double* tab, double u) noexcept {
  constexpr double kK = kLinearSegments;
  const double su = u * kK;
  const int k = std::min(static_cast<int>(su), kLinearSegments - 1);
  const double* p = tab + 2 * static_cast<std::ptrdiff_t>(k);
  return {p[0] + (su - k) * p[1], p[1] * kK};
}

inline HermiteValue hermite(const double* y, const double* dy, double u) noexcept {
  constexpr double kK = kTableSegments;
  const double su = u * kK;
  const int k = std::min(static_cast<int>(su), kTableSegments - 1);
  const double t = su - k;
  const double h = 1.0 / kK;
  const double y0 = y[k];
  const double y1 = y[k + 1];
  const double m0 = dy[k] * h;
  const double m1 = dy[k + 1] * h;
  const double t2 = t * t;
  const double t3 = t2 * t;
  const double d = y1 - y0;
  // y0 + (m0) t + (3d - 2m0 - m1) t^2 + (m0 + m1 - 2d) t^3
  const double c2 = 3.0 * d - 2.0 * m0 - m1;
  const double c3 = m0 + m1 - 2.0 * d;
  return {y0 + m0 * t + c2 * t2 + c3 * t3, (m0 + 2.0 * c2 * t + 3.0 * c3 * t2) * kK};
}

// Solves L L^T x = b in place (L lower triangular, row-major n x n, from a Cholesky factorisation).
void cholesky_solve(const double* l, std::size_t n, double* x) noexcept {
  for (std::size_t i = 0; i < n; ++i) {
    const double* li = l + i * n;
    double sum = x[i];
    for (std::size_t k = 0; k < i; ++k) {
      sum -= li[k] * x[k];
    }
    x[i] = sum / li[i];
  }
  for (std::size_t i = n; i-- > 0;) {
    double sum = x[i];
    for (std::size_t k = i + 1; k < n; ++k) {
      sum -= l[k * n + i] * x[k];
    }
    x[i] = sum / l[i * n + i];
  }
}

}  // namespace

const char* to_string(CellRole r) noexcept {
  switch (r) {
    case CellRole::no_contact:
      return "no_contact";
    case CellRole::expired:
      return "expired";
    case CellRole::unloading:
      return "unloading";
    case CellRole::holding:
      return "holding";
    case CellRole::loading:
      return "loading";
  }
  return "unknown";
}

namespace {
// The law at x > 0 with x^n given.
double law_force_N(const CellImpedanceTarget& g, double xn, double v) noexcept {
  const double f = g.stiffness_N_per_m * xn + g.damping_N_s_per_m * v + g.hc_damping_N_s_per_m2 * xn * v;
  return std::clamp(f, 0.0, g.force_ceiling_N);
}
}  // namespace

double impedance_force_N(const CellImpedanceTarget& target, const CellState& state) noexcept {
  const double x = state.indentation_m - target.surface_offset_m;
  if (!(x > 0.0)) {
    return 0.0;
  }
  const double xn = target.exponent == 1.0 ? x : std::pow(x, target.exponent);
  return law_force_N(target, xn, state.rate_m_per_s);
}

namespace {

CellRole classify(const CellState& s, bool expired, double hold_tol) noexcept {
  if (!(s.indentation_m > 0.0)) {
    return CellRole::no_contact;
  }
  if (expired) {
    return CellRole::expired;
  }
  if (s.rate_m_per_s < -hold_tol) {
    return CellRole::unloading;
  }
  return s.rate_m_per_s > hold_tol ? CellRole::loading : CellRole::holding;
}

bool is_loaded(CellRole r) noexcept { return r == CellRole::holding || r == CellRole::loading; }

Status check_state(const CellState& s, double depth_m) noexcept {
  // One test for the common case (NaN fails every comparison); the reason only on failure.
  if (s.indentation_m >= -std::numeric_limits<double>::max() && s.indentation_m < depth_m &&
      std::fabs(s.rate_m_per_s) <= kMaxRate_m_per_s) {
    return Status::ok;
  }
  if (!finite(s.indentation_m) || !finite(s.rate_m_per_s)) {
    return Status::not_finite;
  }
  return Status::out_of_range;
}

Status check_target(const CellImpedanceTarget& t) noexcept {
  const double v[] = {t.stiffness_N_per_m, t.exponent,        t.damping_N_s_per_m, t.hc_damping_N_s_per_m2,
                      t.surface_offset_m,  t.force_ceiling_N, t.valid_until_s};
  for (const double x : v) {
    if (!finite(x)) {
      return Status::not_finite;
    }
  }
  if (t.stiffness_N_per_m < 0.0 || t.damping_N_s_per_m < 0.0 || t.hc_damping_N_s_per_m2 < 0.0 ||
      t.force_ceiling_N < 0.0) {
    return Status::negative;
  }
  if (t.exponent < kMinExponent || t.exponent > kMaxExponent) {
    return Status::out_of_range;
  }
  return Status::ok;
}

// Targets compare without their validity time: refreshing it is not a change of the law.
// Bitwise equality, on purpose: the cache holds the last call's validated inputs, so a bitwise
// match needs no new validation (a -0 for a +0, or any NaN, differs and is examined again).
template <class T>
bool same_bits(const T& a, const T& b) noexcept {
  static_assert(std::is_trivially_copyable_v<T>);
  return std::memcmp(&a, &b, sizeof(T)) == 0;  // NOLINT(bugprone-suspicious-memory-comparison)
}

// The law without its validity time, bitwise (as above).
bool same_law(const CellImpedanceTarget& a, const CellImpedanceTarget& b) noexcept {
  static_assert(offsetof(CellImpedanceTarget, valid_until_s) == 6 * sizeof(double));
  return std::memcmp(&a, &b, 6 * sizeof(double)) == 0;
}

}  // namespace

// ---- the inverse ---------------------------------------------------------------------------

struct CellInverse::Impl {
  struct Type {  // one per distinct outlet count among magnetised branches
    BranchShape shape;
    Hermite psi;                     // q G N / (P - s t) over z = (P - s t) / (P - (s - 1) t)
    std::vector<double> psi_linear;  // the same, resampled for the loop
    Hermite omega;                   // s u / P over sigma = sqrt(kappa G), kappa = N q / P (uniform demand)
    double omega_slope0 = 0.0;
  };
  struct Branch {
    std::int32_t valve = -1;  // -1: unmagnetised (Newtonian)
    std::uint32_t type = 0;
    std::uint32_t slot = 0;  // index of the valve in its cell's valve list
    double s = 1.0;
    double inv_gn = 0.0;          // 1 / (G N): open conductance, m^3/(s Pa)
    double a = 0.0;               // large-flow intercept of its shape (0 unmagnetised)
    const double* psi = nullptr;  // its shape's linear flow table
  };
  struct CellInfo {
    std::uint32_t branch_begin = 0;
    std::uint32_t branch_end = 0;
    std::uint32_t valve_begin = 0;  // into cell_valves / jac
    std::uint32_t valve_end = 0;
    std::int32_t uniform_type = -1;  // all branches magnetised, one per valve, same shape
    double branches = 0.0;
    double s_min = 0.0;             // smallest threshold multiplier (0 with an unmagnetised branch)
    double open_conductance = 0.0;  // sum of 1 / (G N)
    double open_resistance = 0.0;   // its inverse
    double full_r_per_flow = 0.0;   // uniform cells: r = N (Q / branches) / t_max per unit Q
    double full_outlets = 0.0;      // uniform cells: outlet passages of a branch (m)
  };
  // What a loaded cell needs, from its target and state (recomputed when it is dirty).
  struct Derived {
    CellSolution out;
    double flow_m3_per_s = 0.0;
    double aim_Pa = 0.0;     // valves' pressure to reach
    double lock_Pa = 0.0;    // bulge lock: the cell's pressure cannot exceed it
    bool one_sided = false;  // aim at the lock: any valve pressure above it renders the same
    double demand_Pa = 0.0;  // uniform level that renders the aim alone (< 0: not computed yet)
    double p_open_Pa = 0.0;  // valves' pressure with every valve open
    double p_full_Pa = 0.0;  // ... at the maximum current (capped at the lock)
    // x^n expanded about the last base instead of a pow() a tick (see derive).
    double pow_base_m = 0.0;
    double pow_value = 0.0;
    double pow_exponent = 0.0;
  };
  struct CellCache {
    CellImpedanceTarget target;
    CellState state;
    bool valid = false;
    bool gn_last = false;  // solved by Gauss-Newton last time (warm start)
    CellRole role = CellRole::no_contact;
    unsigned char sel = 0;  // which of the cell's two Derived slots is current
    bool expired = false;
    CellImpedanceTarget raw_target;  // the last call's inputs, bitwise
    CellState raw_state;
  };

  InverseOptions opt;
  std::size_t cells = 0;
  std::size_t valves = 0;
  double area_m2 = 0.0;
  double p0_Pa = 0.0;
  double depth_m = 0.0;
  double membrane_linear_N_per_m = 0.0;
  double membrane_cubic_N_per_m3 = 0.0;
  double bulge_linear = 0.0;
  double bulge_cubic = 0.0;
  double newton_k = 0.0;  // N = 12 mu L / (w h^3)
  double yield_k = 0.0;   // Y = 2 L / h
  double t_min = 0.0;     // valve level (one passage's yield threshold Y tau) at zero current
  double t_max = 0.0;     // at max current
  double tau_min = 0.0;
  double tau_max = 0.0;
  double max_current = 0.0;
  double tol_Pa = 0.0;
  double chord_floor_Pa = 0.0;
  std::vector<Type> types;
  std::vector<Branch> branches;
  std::vector<CellInfo> info;
  std::vector<std::uint32_t> cell_valves;  // CSR by cell
  std::vector<std::uint32_t> valve_cell_begin;
  std::vector<std::uint32_t> valve_cells;      // CSR by valve
  std::vector<std::uint32_t> valve_cell_slot;  // the valve's slot in that cell's list
  std::vector<double> current_table;           // I at tau_k = tau_min + k (tau_max - tau_min) / K
  double current_scale = 0.0;                  // K / (tau_max - tau_min)
  std::vector<double> current_lerp;            // interleaved (I_k, I_k+1 - I_k)
  double inv_yield_k = 0.0;
  double current_table_error = 0.0;
  double branch_table_error = 0.0;

  // State.
  std::vector<CellCache> cache;
  std::vector<double> t;  // valve levels, Pa
  std::vector<double> current;
  std::vector<double> tau;
  std::vector<double> inv_valve_gain;  // 1 / the calibrated per-valve yield gain
  std::vector<CellSolution> out;
  InverseReport rep;

  // Scratch (preallocated).
  std::vector<Derived> derived;  // two per cell: current and the one pass 1 fills
  [[nodiscard]] const Derived& cur(std::size_t cell) const noexcept {
    return derived[2 * cell + cache[cell].sel];
  }
  std::vector<CellRole> next_role;
  std::vector<std::uint32_t> changed_laws;
  std::vector<std::uint32_t> seen;         // cells whose inputs differ bitwise from the last call
  std::vector<unsigned char> loaded_flag;  // per cell: holding or loading (committed)
  std::vector<std::uint32_t> loaded_list;  // the loaded cells, rebuilt when a dirty cell commits
  bool roles_changed = false;
  std::vector<std::uint32_t> dirty;
  std::vector<std::uint64_t> cell_stamp;
  std::vector<std::uint64_t> comp_stamp;
  std::uint64_t stamp = 0;
  // The partition of the loaded cells into components (CSR), rebuilt when roles change.
  std::vector<std::uint32_t> part_cells;
  std::vector<std::uint32_t> part_cell_begin;
  std::vector<std::uint32_t> part_valves;
  std::vector<std::uint32_t> part_valve_begin;
  std::vector<std::uint32_t> part_inc_begin;  // per component: (its valves + 1) offsets
  std::vector<std::uint32_t> part_inc_row;
  std::vector<std::uint32_t> part_inc_slot;
  std::vector<std::uint32_t> comp_of_cell;
  std::vector<std::int32_t> valve_comp;  // -1: no loaded cell uses the valve
  // Per component, the last bounded step's factorisation (chord steps reuse it).
  std::vector<std::uint32_t> part_factor_off;
  std::vector<double> factor_pool;
  std::vector<double> factor_diag;
  std::vector<int> factor_age;  // chord steps since it was made; -1: none valid
  std::vector<double> part_inc_jac;
  std::vector<unsigned char> part_bound;
  std::vector<unsigned char> part_included;
  std::size_t comp_id = 0;
  // The component being solved (views into the partition).
  std::span<const std::uint32_t> comp_cells;
  std::span<const std::uint32_t> comp_valves;
  const std::uint32_t* inc_begin = nullptr;  // per component valve, into inc_row / inc_slot
  const std::uint32_t* inc_row = nullptr;
  const std::uint32_t* inc_slot = nullptr;
  std::vector<std::uint32_t> row_of;    // cell -> row in its component
  std::vector<std::uint32_t> local_of;  // valve -> index in its component
  std::vector<double> jac;              // per cell-valve slot: d e_i / d t_v
  std::vector<double> e;                // per row
  std::vector<double> aim_row;          // per row: the cell's aimed pressure
  std::vector<unsigned char> one_sided;
  std::vector<unsigned char> included;
  std::vector<double> crow;                  // per row: the linear model's right-hand side
  std::vector<double> t0;                    // per component valve: level at the linearisation
  std::vector<double> t1;                    // proposal
  std::vector<double> tu;                    // unconstrained row-space value
  std::vector<unsigned char> bound;          // 0 free, 1 at t_min, 2 at t_max
  std::vector<unsigned char> excluded_once;  // per row, within one step
  std::vector<double> predicted;             // per row: the linear model's residual after a step
  std::vector<double> mat;                   // kDenseRows^2
  std::vector<double> rhs;
  std::vector<double> dual;           // row-space solution
  std::vector<double> res;            // fallback residuals
  double damping = 0.0;               // Levenberg-Marquardt mu of the component being solved
  std::vector<double> best;           // per component valve: best levels found
  std::vector<std::uint32_t> escape;  // valves to try shutting after a stall

  Impl(const DeviceModel& model, const InverseOptions& options);
  void build_graph(const DeviceModel& model);
  void build_tables();
  void build_current_table(const DeviceModel& model);

  // Branch flow at pressure P and valve level tv, with dq/dP and dq/dt.
  struct Flow {
    double q = 0.0;
    double dq_dp = 0.0;
    double dq_dt = 0.0;
  };
  static Flow branch_flow(const Branch& b, double p, double tv) noexcept {
    if (tv <= 0.0) {  // also every unmagnetised branch
      return {p * b.inv_gn, b.inv_gn, -b.a * b.inv_gn};
    }
    const double over = p - b.s * tv;
    if (!(over > 0.0)) {
      return {};
    }
    const double ee = over + tv;
    const HermiteValue h = linear(b.psi, over / ee);
    const double k = h.slope * over / (ee * ee);
    return {h.value * over * b.inv_gn, (k * tv + h.value) * b.inv_gn, (-k * p - b.s * h.value) * b.inv_gn};
  }
  // Flow and dq/dP only (the residual-only rows).
  static void branch_q(const Branch& b, double p, double tv, double& q, double& dq_dp) noexcept {
    if (tv <= 0.0) {
      q += p * b.inv_gn;
      dq_dp += b.inv_gn;
      return;
    }
    const double over = p - b.s * tv;
    if (over > 0.0) {
      const double inv = 1.0 / (over + tv);
      const double z = over * inv;
      const HermiteValue h = linear(b.psi, z);
      q += h.value * over * b.inv_gn;
      dq_dp += (h.slope * z * inv * tv + h.value) * b.inv_gn;
    }
  }
  // Pressure of one branch carrying q alone at level tv (fast Bingham law; upper bounds).
  double branch_pressure(const Branch& b, double q, double tv) const noexcept {
    if (b.valve < 0 || tv <= 0.0) {
      return q / b.inv_gn;
    }
    const BranchShape& sh = types[b.type].shape;
    const double r = newton_k * q / tv;
    double phi = r + bingham_excess_fast(r);
    if (sh.m > 0) {
      const double r2 = r / sh.m;
      phi += r2 + bingham_excess_fast(r2);
    }
    return tv * phi;
  }
  // Cell pressure at flow q >= 0 with valve levels level(v) (safeguarded Newton from above:
  // the total flow is convex and increasing in P).
  template <class Level>
  double forward(std::size_t cell, double q, const Level& level) const noexcept {
    const CellInfo& ci = info[cell];
    double hold = std::numeric_limits<double>::infinity();
    for (std::uint32_t b = ci.branch_begin; b < ci.branch_end; ++b) {
      const Branch& br = branches[b];
      hold = std::min(hold, br.valve < 0 ? 0.0 : br.s * level(static_cast<std::size_t>(br.valve)));
    }
    if (q <= 0.0) {
      return hold;
    }
    double p = std::numeric_limits<double>::infinity();
    for (std::uint32_t b = ci.branch_begin; b < ci.branch_end; ++b) {
      const Branch& br = branches[b];
      p = std::min(p, branch_pressure(br, q, br.valve < 0 ? 0.0 : level(static_cast<std::size_t>(br.valve))));
    }
    p *= 1.0 + 1e-4;  // the bound uses the fast valve law: step safely above the root
    for (int it = 0; it < 100; ++it) {
      double f = -q;
      double df = 0.0;
      for (std::uint32_t b = ci.branch_begin; b < ci.branch_end; ++b) {
        const Branch& br = branches[b];
        const Flow fl = branch_flow(br, p, br.valve < 0 ? 0.0 : level(static_cast<std::size_t>(br.valve)));
        f += fl.q;
        df += fl.dq_dp;
      }
      if (!(df > 0.0) || f <= 0.0) {
        break;
      }
      const double next_p = std::max(p - f / df, hold);
      if (p - next_p <= 1e-13 * p) {
        p = next_p;
        break;
      }
      p = next_p;
    }
    return p;
  }
  // Uniform cell with every valve at t_max: each branch carries Q / branches.
  double full_pressure(const CellInfo& ci, double q) const noexcept {
    const double r = ci.full_r_per_flow * q;
    double phi = r + bingham_excess_fast(r);
    if (ci.full_outlets > 0.0) {
      const double r2 = r / ci.full_outlets;
      phi += r2 + bingham_excess_fast(r2);
    }
    return t_max * phi;
  }
  double uniform_pressure(std::size_t cell, double q, double level) const noexcept {
    const CellInfo& ci = info[cell];
    if (q <= 0.0) {
      return ci.s_min * level;
    }
    if (level <= 0.0) {
      return q / ci.open_conductance;
    }
    if (ci.uniform_type >= 0) {
      return branch_pressure(branches[ci.branch_begin], q / ci.branches, level);
    }
    return forward(cell, q, [level](std::size_t) { return level; });
  }
  // Uniform level that gives pressure p at flow q (p between the open and the full pressure).
  double demand(std::size_t cell, double q, double p) const noexcept {
    const CellInfo& ci = info[cell];
    if (!(p > 0.0)) {
      return t_min;
    }
    if (q <= 0.0) {
      return ci.s_min > 0.0 ? p / ci.s_min : t_min;
    }
    if (ci.uniform_type >= 0) {
      const Type& ty = types[static_cast<std::size_t>(ci.uniform_type)];
      const double kappa = newton_k * (q / ci.branches) / p;
      const double sigma = std::sqrt(kappa * ty.shape.g);
      if (!(sigma < 1.0)) {
        return t_min;
      }
      const HermiteValue h = hermite(ty.omega.y.data(), ty.omega.dy.data(), sigma);
      return std::clamp(h.value * p / ty.shape.s, t_min, t_max);
    }
    // Generic cell: bisection on the level (flow at p falls as the level rises).
    double lo = t_min;
    double hi = t_max;
    for (int it = 0; it < 60; ++it) {
      const double mid = 0.5 * (lo + hi);
      double f = -q;
      for (std::uint32_t b = ci.branch_begin; b < ci.branch_end; ++b) {
        f += branch_flow(branches[b], p, branches[b].valve < 0 ? 0.0 : mid).q;
      }
      (f > 0.0 ? lo : hi) = mid;
    }
    return 0.5 * (lo + hi);
  }
  double current_for_tau(double tau_Pa) const noexcept {
    const double u =
        std::clamp((tau_Pa - tau_min) * current_scale, 0.0, static_cast<double>(kCurrentSegments));
    const int k = std::min(static_cast<int>(u), kCurrentSegments - 1);
    const double* p = current_lerp.data() + 2 * static_cast<std::ptrdiff_t>(k);
    return p[0] + (u - k) * p[1];
  }

  Status derive(std::size_t cell, const CellImpedanceTarget& g, const CellState& s, CellRole role,
                const Derived& prev, Derived& d) const noexcept;
  // A loaded cell's uniform demand, computed on first use after its targets changed.
  double demand_of(std::size_t cell) noexcept {
    Derived& d = derived[2 * cell + cache[cell].sel];
    if (d.demand_Pa < 0.0) {
      if (d.aim_Pa <= d.p_open_Pa) {
        d.demand_Pa = t_min;  // the floor (or a lock at or below it)
      } else if (d.aim_Pa >= d.p_full_Pa && !d.one_sided) {
        d.demand_Pa = t_max;  // the ceiling: exactly the maximum current
      } else {
        d.demand_Pa = std::clamp(demand(cell, d.flow_m3_per_s, d.aim_Pa), t_min, t_max);
      }
    }
    return d.demand_Pa;
  }
  Status solve(std::span<const CellImpedanceTarget> targets, std::span<const CellState> states,
               double now_s) noexcept;
  void rebuild_partition() noexcept;
  void solve_component(std::size_t comp) noexcept;
  // From the current levels, with the rows already evaluated there (merit: their merit).
  double gauss_newton(double start_damping, bool& converged, double merit) noexcept;
  // Fills e and jac for the component's rows; returns the merit. relinearise: a flowing row far
  // from its aim is linearised at its true pressure (a forward solve) instead of at the aim.
  // jacobian: also fill jac (else residuals only).
  double evaluate_rows(bool relinearise = true, bool jacobian = true) noexcept;
  void bounded_step() noexcept;  // t0 (+ rows) -> t1
  void save_factor(double diag) noexcept;
  bool chord_step() noexcept;
  void fallback_step() noexcept;
  void write_valves() noexcept;
  Status fail(Status s, std::size_t cell) noexcept {
    rep.status = s;
    rep.error_cell = cell;
    rep.from_cache = false;
    rep.dirty_cells = 0;
    rep.cell_updates = 0;
    rep.valve_updates = 0;
    rep.components_solved = 0;
    rep.iterations = 0;
    return s;
  }
};

CellInverse::Impl::Impl(const DeviceModel& model, const InverseOptions& options) : opt(options) {
  const DeviceProfile& p = model.profile();
  const std::string& origin = p.origin;
  if (!(opt.hold_rate_tolerance_m_per_s >= 0.0) || !(opt.indentation_tolerance_m >= 0.0) ||
      !(opt.rate_tolerance_m_per_s >= 0.0) || !(opt.force_tolerance_N > 0.0) || opt.max_iterations < 0 ||
      !(opt.regularisation > 0.0) || !finite(opt.hold_rate_tolerance_m_per_s) ||
      !finite(opt.indentation_tolerance_m) || !finite(opt.rate_tolerance_m_per_s) ||
      !finite(opt.force_tolerance_N) || !finite(opt.regularisation)) {
    throw InvalidArgument(
        "InverseOptions: tolerances must be finite and >= 0, force_tolerance_N and regularisation > 0, "
        "max_iterations >= 0");
  }
  cells = model.layout().fluid_cell_count();
  valves = model.layout().valve_count();
  const ContactPatch& patch = model.contact();
  area_m2 = patch.effective_area_m2;
  p0_Pa = p.reservoir.initial_pressure_Pa;
  depth_m = p.cell_depth_m;
  // Pad membrane force F_m(d) = k1 d + k3 d^3 (membrane.hpp, point load through the pad).
  const MembraneParams& mem = patch.membrane;
  const double a2 = patch.cell_radius_m * patch.cell_radius_m;
  const double qn = point_load_q(mem.poisson_ratio);
  membrane_linear_N_per_m =
      16.0 * kPi * bending_stiffness_N_m(mem) / a2 +
      2.0 * kPi * mem.pretension_N_per_m / std::log(patch.cell_radius_m / patch.contact_radius_m);
  membrane_cubic_N_per_m3 = mem.youngs_modulus_Pa * mem.thickness_m / (a2 * qn * qn * qn);
  bulge_linear = patch.bulge_linear_Pa_per_m3;
  bulge_cubic = patch.bulge_cubic_Pa_per_m9;
  newton_k = model.valve_law().newtonian_pressure_Pa(1.0);
  yield_k = model.valve_law().yield_pressure_Pa(1.0);
  max_current = p.coil.max_current_A;
  tol_Pa = opt.force_tolerance_N / area_m2;
  chord_floor_Pa = kChordFloor_N / area_m2;
  if (!(area_m2 > 0.0) || !(newton_k > 0.0) || !(yield_k > 0.0)) {
    throw InvalidArgument(origin + ": the inverse needs a positive contact area and valve constants");
  }
  build_graph(model);
  build_tables();
  for (Branch& b : branches) {
    if (b.valve >= 0) {
      const Type& ty = types[b.type];
      b.a = ty.shape.a;
      b.psi = ty.psi_linear.data();
    }
  }
  build_current_table(model);
  for (CellInfo& ci : info) {
    if (ci.uniform_type >= 0) {
      ci.full_r_per_flow = newton_k / (ci.branches * t_max);
      ci.full_outlets = types[static_cast<std::size_t>(ci.uniform_type)].shape.m;
    }
  }

  cache.assign(cells, CellCache{});
  t.assign(valves, t_min);
  current.assign(valves, 0.0);
  tau.assign(valves, tau_min);
  inv_valve_gain.assign(valves, 1.0);
  out.assign(cells, CellSolution{});
  derived.assign(2 * cells, Derived{});
  next_role.assign(cells, CellRole::no_contact);
  changed_laws.reserve(cells);
  seen.reserve(cells);
  loaded_flag.assign(cells, 0);
  loaded_list.reserve(cells);
  dirty.reserve(cells);
  cell_stamp.assign(cells, 0);
  comp_stamp.assign(cells, 0);
  part_cells.assign(cells, 0);
  part_cell_begin.assign(cells + 1, 0);
  part_valves.assign(valves, 0);
  part_valve_begin.assign(cells + 1, 0);
  part_inc_begin.assign(valves + cells + 1, 0);
  part_inc_row.assign(valve_cells.size(), 0);
  part_inc_slot.assign(valve_cells.size(), 0);
  comp_of_cell.assign(cells, 0);
  valve_comp.assign(valves, -1);
  part_factor_off.assign(cells + 1, 0);
  factor_pool.assign(kDenseRows * cells, 0.0);
  factor_diag.assign(cells, 0.0);
  factor_age.assign(cells, -1);
  part_inc_jac.assign(valve_cells.size(), 0.0);
  part_bound.assign(valves, 0);
  part_included.assign(cells, 0);
  inc_row = part_inc_row.data();
  inc_slot = part_inc_slot.data();
  row_of.assign(cells, 0);
  local_of.assign(valves, 0);
  jac.assign(cell_valves.size(), 0.0);
  e.assign(cells, 0.0);
  aim_row.assign(cells, 0.0);
  one_sided.assign(cells, 0);
  included.assign(cells, 0);
  crow.assign(cells, 0.0);
  t0.assign(valves, 0.0);
  t1.assign(valves, 0.0);
  tu.assign(valves, 0.0);
  bound.assign(valves, 0);
  excluded_once.assign(cells, 0);
  predicted.assign(cells, 0.0);
  mat.assign(kDenseRows * kDenseRows, 0.0);
  rhs.assign(kDenseRows, 0.0);
  dual.assign(kDenseRows, 0.0);
  res.assign(cells, 0.0);
  best.assign(valves, 0.0);
  escape.assign(valves, 0);
}

void CellInverse::Impl::build_graph(const DeviceModel& model) {
  const DeviceProfile& p = model.profile();
  const std::vector<HydraulicLink>& links = p.links;
  std::vector<std::vector<std::uint32_t>> chamber_links(valves);
  for (std::size_t i = 0; i < links.size(); ++i) {
    for (const NodeRef n : {links[i].a, links[i].b}) {
      if (n.kind == NodeKind::chamber) {
        chamber_links[n.index].push_back(static_cast<std::uint32_t>(i));
      }
    }
  }
  const double open = 1.0 / newton_k;
  std::vector<int> type_of_m;
  info.assign(cells, CellInfo{});
  std::vector<std::vector<std::uint32_t>> cells_of(valves);
  for (std::size_t cell = 0; cell < cells; ++cell) {
    CellInfo& ci = info[cell];
    ci.branch_begin = static_cast<std::uint32_t>(branches.size());
    ci.valve_begin = static_cast<std::uint32_t>(cell_valves.size());
    for (std::size_t i = 0; i < links.size(); ++i) {
      const HydraulicLink& k = links[i];
      const bool a_is = k.a.kind == NodeKind::fluid_cell && k.a.index == cell;
      const bool b_is = k.b.kind == NodeKind::fluid_cell && k.b.index == cell;
      if (!a_is && !b_is) {
        continue;
      }
      const NodeRef other = a_is ? k.b : k.a;
      int m = 0;
      if (other.kind == NodeKind::chamber) {
        for (const std::uint32_t j : chamber_links[other.index]) {
          if (j == i) {
            continue;
          }
          if (links[j].valve != k.valve) {
            throw InvalidArgument(p.origin + ": [hydraulics] link " + std::to_string(i) + " and link " +
                                  std::to_string(j) +
                                  " meet in one chamber but are magnetised by different coils; the "
                                  "inverse supports branches whose passages share one coil (the chamber and "
                                  "direct topologies): give them the same valve");
          }
          ++m;
        }
      }
      Branch br;
      br.valve = k.valve;
      const BranchShape sh = shape_of(m);
      br.s = sh.s;
      br.inv_gn = open / sh.g;
      if (k.valve >= 0) {
        if (type_of_m.size() <= static_cast<std::size_t>(m)) {
          type_of_m.resize(static_cast<std::size_t>(m) + 1, -1);
        }
        if (type_of_m[static_cast<std::size_t>(m)] < 0) {
          type_of_m[static_cast<std::size_t>(m)] = static_cast<int>(types.size());
          types.push_back(Type{sh, {}, {}, {}, 0.0});
        }
        br.type = static_cast<std::uint32_t>(type_of_m[static_cast<std::size_t>(m)]);
        const auto v = static_cast<std::uint32_t>(k.valve);
        auto first = cell_valves.begin() + ci.valve_begin;
        auto it = std::find(first, cell_valves.end(), v);
        if (it == cell_valves.end()) {
          cell_valves.push_back(v);
          cells_of[v].push_back(static_cast<std::uint32_t>(cell));
          it = cell_valves.end() - 1;
        }
        br.slot = static_cast<std::uint32_t>(it - cell_valves.begin());
      }
      branches.push_back(br);
    }
    ci.branch_end = static_cast<std::uint32_t>(branches.size());
    ci.valve_end = static_cast<std::uint32_t>(cell_valves.size());
    ci.branches = ci.branch_end - ci.branch_begin;
    if (ci.branch_end == ci.branch_begin) {
      throw InvalidArgument(p.origin + ": [hydraulics] fluid cell " + std::to_string(cell) +
                            " has no passage: it could never be indented");
    }
    ci.s_min = std::numeric_limits<double>::infinity();
    bool uniform = ci.branches == static_cast<double>(ci.valve_end - ci.valve_begin);
    for (std::uint32_t b = ci.branch_begin; b < ci.branch_end; ++b) {
      const Branch& br = branches[b];
      ci.open_conductance += br.inv_gn;
      ci.s_min = std::min(ci.s_min, br.valve < 0 ? 0.0 : br.s);
      uniform = uniform && br.valve >= 0 && br.type == branches[ci.branch_begin].type;
    }
    ci.uniform_type = uniform ? static_cast<std::int32_t>(branches[ci.branch_begin].type) : -1;
    ci.open_resistance = 1.0 / ci.open_conductance;
  }
  valve_cell_begin.assign(valves + 1, 0);
  for (std::size_t v = 0; v < valves; ++v) {
    valve_cell_begin[v] = static_cast<std::uint32_t>(valve_cells.size());
    for (const std::uint32_t cell : cells_of[v]) {
      valve_cells.push_back(cell);
      const CellInfo& ci = info[cell];
      const auto first = cell_valves.begin() + ci.valve_begin;
      const auto last = cell_valves.begin() + ci.valve_end;
      valve_cell_slot.push_back(static_cast<std::uint32_t>(std::find(first, last, v) - cell_valves.begin()));
    }
  }
  valve_cell_begin[valves] = static_cast<std::uint32_t>(valve_cells.size());
}

void CellInverse::Impl::build_tables() {
  constexpr int kK = kTableSegments;
  for (Type& ty : types) {
    const BranchShape& sh = ty.shape;
    ty.psi.y.assign(kK + 1, 0.0);
    ty.psi.dy.assign(kK + 1, 0.0);
    ty.omega.y.assign(kK + 1, 0.0);
    ty.omega.dy.assign(kK + 1, 0.0);
    // Near the threshold Phi - s ~ a' sqrt(r); far above it Phi -> g r + a.
    const double a1 =
        std::sqrt(2.0 / 3.0) * (1.0 + (sh.m > 0 ? 1.0 / std::sqrt(static_cast<double>(sh.m)) : 0.0));
    ty.psi.y[0] = 0.0;
    ty.psi.dy[0] = sh.g / (a1 * a1);
    ty.psi.y[kK] = 1.0;
    ty.psi.dy[kK] = sh.a - sh.s;
    for (int k = 1; k < kK; ++k) {
      const double zk = static_cast<double>(k) / kK;
      const double over = zk / (1.0 - zk);  // phi - s
      const double r = sh.r_of_phi(sh.s + over);
      const double gp = 1.0 / sh.dphi(r);
      const auto ku = static_cast<std::size_t>(k);
      ty.psi.y[ku] = r * sh.g / over;
      ty.psi.dy[ku] = sh.g * (gp * over - r) / (over * over) / ((1.0 - zk) * (1.0 - zk));
    }
    // Uniform demand: phi solves Phi(kappa phi) = phi; omega = s / phi.
    ty.omega.y[0] = 1.0;
    ty.omega.dy[0] = -a1 / std::sqrt(sh.s * sh.g);
    ty.omega_slope0 = ty.omega.dy[0];
    ty.omega.y[kK] = 0.0;
    ty.omega.dy[kK] = -2.0 * sh.s / sh.a;
    for (int k = 1; k < kK; ++k) {
      const double sigma = static_cast<double>(k) / kK;
      const double kappa = sigma * sigma / sh.g;
      double lo = sh.s;
      double hi = sh.a / (1.0 - kappa * sh.g) * 1.0000001 + 1.0;
      for (int i = 0; i < 400 && hi - lo > 1e-16 * hi; ++i) {
        const double mid = 0.5 * (lo + hi);
        (sh.phi(kappa * mid) - mid > 0.0 ? lo : hi) = mid;
      }
      const double phi = 0.5 * (lo + hi);
      const double dp = sh.dphi(kappa * phi);
      const double dphi_dkappa = -dp * phi / (dp * kappa - 1.0);
      const auto ku = static_cast<std::size_t>(k);
      ty.omega.y[ku] = sh.s / phi;
      ty.omega.dy[ku] = -sh.s / (phi * phi) * dphi_dkappa * 2.0 * sigma / sh.g;
    }
    ty.psi_linear.assign(2 * (static_cast<std::size_t>(kLinearSegments) + 1), 0.0);
    for (int k = 0; k <= kLinearSegments; ++k) {
      const double zk = static_cast<double>(k) / kLinearSegments;
      ty.psi_linear[2 * static_cast<std::size_t>(k)] = hermite(ty.psi.y.data(), ty.psi.dy.data(), zk).value;
    }
    for (int k = 0; k < kLinearSegments; ++k) {
      const auto ku = 2 * static_cast<std::size_t>(k);
      ty.psi_linear[ku + 1] = ty.psi_linear[ku + 2] - ty.psi_linear[ku];
    }
    // The loop table's error against the exact law, as a relative flow error: at the Hermite
    // table's midpoints (its own worst places) and at the linear table's, near the threshold
    // where the curvature is largest.
    auto check = [&](double zk) {
      const double over = zk / (1.0 - zk);
      const double r = sh.r_of_phi(sh.s + over);
      const double exact = r * sh.g / over;
      const double fast = linear(ty.psi_linear.data(), zk).value;
      branch_table_error = std::max(branch_table_error, std::fabs(fast - exact) / exact);
    };
    for (int k = 0; k < kK; ++k) {
      check((k + 0.5) / kK);
    }
    for (int k = 0; k < 64; ++k) {
      check((k + 0.5) / kLinearSegments);
    }
  }
}

void CellInverse::Impl::build_current_table(const DeviceModel& model) {
  const DeviceProfile& p = model.profile();
  tau_min = model.yield_stress_at_current_Pa(0.0).value;
  tau_max = model.yield_stress_at_current_Pa(max_current).value;
  if (!(tau_max > tau_min)) {
    throw InvalidArgument(p.origin + ": [coil] max_current_A: the coil cannot raise the yield stress (" +
                          std::to_string(tau_min) + " Pa at 0 A, " + std::to_string(tau_max) +
                          " Pa at max_current_A): nothing to allocate; raise turns or max_current_A");
  }
  t_min = yield_k * tau_min;
  t_max = yield_k * tau_max;
  current_scale = kCurrentSegments / (tau_max - tau_min);
  inv_yield_k = 1.0 / yield_k;
  // I(tau) by bisection on the model's own (monotone) table, so that the round trip is exact at
  // the nodes.
  auto invert = [&](double tau_Pa) {
    double lo = 0.0;
    double hi = max_current;
    for (int i = 0; i < 200 && hi - lo > 1e-15 * max_current; ++i) {
      const double mid = 0.5 * (lo + hi);
      (model.yield_stress_at_current_Pa(mid).value < tau_Pa ? lo : hi) = mid;
    }
    return 0.5 * (lo + hi);
  };
  current_table.assign(kCurrentSegments + 1, 0.0);
  for (int k = 0; k <= kCurrentSegments; ++k) {
    current_table[static_cast<std::size_t>(k)] =
        invert(tau_min + (tau_max - tau_min) * static_cast<double>(k) / kCurrentSegments);
  }
  current_table.front() = 0.0;
  current_table.back() = max_current;
  current_lerp.assign(2 * (static_cast<std::size_t>(kCurrentSegments) + 1), 0.0);
  for (int k = 0; k <= kCurrentSegments; ++k) {
    const auto ku = static_cast<std::size_t>(k);
    current_lerp[2 * ku] = current_table[ku];
    current_lerp[2 * ku + 1] = k < kCurrentSegments ? current_table[ku + 1] - current_table[ku] : 0.0;
  }
  for (int k = 0; k < kCurrentSegments; ++k) {
    const double tau_mid = tau_min + (tau_max - tau_min) * (k + 0.5) / kCurrentSegments;
    const double back = model.yield_stress_at_current_Pa(current_for_tau(tau_mid)).value;
    current_table_error = std::max(current_table_error, std::fabs(back - tau_mid));
  }
}

Status CellInverse::Impl::derive(std::size_t cell, const CellImpedanceTarget& g, const CellState& s,
                                 CellRole role, const Derived& prev, Derived& d) const noexcept {
  if (!is_loaded(role)) {
    d = Derived{};
    d.out.role = role;
    return Status::ok;
  }
  d.out.role = role;
  d.out.residual_N = 0.0;
  const double dd = s.indentation_m;
  const double q = role == CellRole::loading ? area_m2 * s.rate_m_per_s : 0.0;
  const double fm = (membrane_linear_N_per_m + membrane_cubic_N_per_m3 * dd * dd) * dd;
  const double vol = area_m2 * dd;
  const double lock = (bulge_linear + bulge_cubic * vol * vol) * vol;
  const CellInfo& ci = info[cell];
  const double p_open =
      std::min(lock, t_min > 0.0 ? uniform_pressure(cell, q, t_min) : q * ci.open_resistance);
  const double p_full =
      std::min(lock, ci.uniform_type >= 0 ? full_pressure(ci, q) : uniform_pressure(cell, q, t_max));
  const double base = fm + area_m2 * p0_Pa;
  // The law's x^n: within 5 % of the last base, its binomial series to fourth order (exact for
  // n = 1..4, relative error below 1e-8 otherwise), else pow() and a new base. A press moves
  // micrometres a tick: pow() runs every few dozen ticks.
  const double x = dd - g.surface_offset_m;
  double requested = 0.0;
  d.pow_base_m = prev.pow_base_m;
  d.pow_value = prev.pow_value;
  d.pow_exponent = prev.pow_exponent;
  if (x > 0.0) {
    const double n = g.exponent;
    double xn = x;
    if (n != 1.0) {
      const double eps = (x - d.pow_base_m) / d.pow_base_m;
      if (n == d.pow_exponent && d.pow_base_m > 0.0 && std::fabs(eps) <= 0.05) {
        const double c1 = n;
        const double c2 = c1 * (n - 1.0) / 2.0;
        const double c3 = c2 * (n - 2.0) / 3.0;
        const double c4 = c3 * (n - 3.0) / 4.0;
        xn = d.pow_value * (1.0 + eps * (c1 + eps * (c2 + eps * (c3 + eps * c4))));
      } else {
        xn = std::pow(x, n);
        d.pow_base_m = x;
        d.pow_value = xn;
        d.pow_exponent = n;
      }
    }
    requested = law_force_N(g, xn, s.rate_m_per_s);
  }
  CellSolution& o = d.out;
  o.requested_force_N = requested;
  o.force_min_N = base + area_m2 * p_open;
  o.force_max_N = base + area_m2 * p_full;
  if (!finite(o.force_min_N) || !finite(o.force_max_N) || !finite(requested)) {
    return Status::overflow;
  }
  // Flag only what is outside by more than round-off (a target computed from a rendered force
  // lands on the envelope's edge).
  const double slack = 1e-9 * (1.0 + o.force_max_N);
  o.clamped_low = requested < o.force_min_N - slack;
  o.clamped_high = requested > o.force_max_N + slack;
  o.target_force_N = std::clamp(requested, o.force_min_N, o.force_max_N);
  d.flow_m3_per_s = q;
  d.lock_Pa = lock;
  d.aim_Pa = std::clamp((o.target_force_N - base) / area_m2, p_open, p_full);
  d.one_sided = d.aim_Pa >= lock * (1.0 - 1e-12);
  if (d.one_sided) {
    d.aim_Pa = lock;
  }
  d.p_open_Pa = p_open;
  d.p_full_Pa = p_full;
  d.demand_Pa = -1.0;  // computed when a cold solve needs it (demand_of)
  return Status::ok;
}

Status CellInverse::Impl::solve(std::span<const CellImpedanceTarget> targets,
                                std::span<const CellState> states, double now_s) noexcept {
  if (targets.size() != cells || states.size() != cells) {
    return fail(Status::out_of_range, 0);
  }
  if (!finite(now_s)) {
    return fail(Status::not_finite, 0);
  }
  // Pass 1: validate everything and work out what changed; nothing cached is touched.
  dirty.clear();
  changed_laws.clear();
  seen.clear();
  for (std::size_t i = 0; i < cells; ++i) {
    const CellState& s = states[i];
    const CellImpedanceTarget& g = targets[i];
    const CellCache& cc = cache[i];
    // Inputs bitwise as last time (validated then): only the clock can change the role.
    const bool expired = now_s > g.valid_until_s;
    if (cc.valid && same_bits(g, cc.raw_target) && same_bits(s, cc.raw_state) && expired == cc.expired) {
      continue;
    }
    seen.push_back(static_cast<std::uint32_t>(i));
    if (const Status st = check_state(s, depth_m); st != Status::ok) {
      return fail(st, i);
    }
    const bool changed = !cc.valid || !same_law(g, cc.target);
    if (changed) {
      if (const Status st = check_target(g); st != Status::ok) {
        return fail(st, i);
      }
    } else if (!finite(g.valid_until_s)) {
      return fail(Status::not_finite, i);
    }
    if (changed) {
      changed_laws.push_back(static_cast<std::uint32_t>(i));
    }
    const CellRole role = classify(s, expired, opt.hold_rate_tolerance_m_per_s);
    next_role[i] = role;
    bool is_dirty = !cc.valid || role != cc.role;
    if (is_loaded(role) && !is_dirty) {
      is_dirty = changed ||
                 std::fabs(s.indentation_m - cc.state.indentation_m) > opt.indentation_tolerance_m ||
                 std::fabs(s.rate_m_per_s - cc.state.rate_m_per_s) > opt.rate_tolerance_m_per_s;
    }
    if (is_dirty) {
      if (const Status st = derive(i, g, s, role, derived[2 * i + cc.sel], derived[2 * i + (1 - cc.sel)]);
          st != Status::ok) {
        return fail(st, i);
      }
      dirty.push_back(static_cast<std::uint32_t>(i));
    }
  }
  // Pass 2: commit.
  rep.status = Status::ok;
  rep.error_cell = 0;
  rep.dirty_cells = dirty.size();
  rep.cell_updates = 0;
  rep.valve_updates = 0;
  rep.components_solved = 0;
  rep.iterations = 0;
  for (const std::uint32_t i : changed_laws) {
    cache[i].target = targets[i];
  }
  for (const std::uint32_t i : seen) {
    CellCache& cc = cache[i];
    cc.raw_target = targets[i];
    cc.raw_state = states[i];
    cc.expired = now_s > targets[i].valid_until_s;
  }
  if (dirty.empty()) {
    rep.from_cache = true;
    return Status::ok;
  }
  rep.from_cache = false;
  rep.converged = true;
  rep.residual_predicted = false;
  for (const std::uint32_t i : dirty) {
    CellCache& cc = cache[i];
    cc.state = states[i];  // (the target was committed above if it changed)
    cc.valid = true;
    cc.role = next_role[i];
    const unsigned char now_loaded = is_loaded(cc.role) ? 1 : 0;
    roles_changed = roles_changed || now_loaded != loaded_flag[i];
    loaded_flag[i] = now_loaded;
    cc.sel = static_cast<unsigned char>(1 - cc.sel);  // the slot derived in pass 1 becomes current
    out[i] = cur(i).out;
    ++rep.cell_updates;
  }
  if (roles_changed) {
    rebuild_partition();
    roles_changed = false;
  }
  // Re-solve every component that holds a dirty cell or one of its valves; release the valves of
  // dirty cells that no loaded cell needs.
  ++stamp;
  for (const std::uint32_t i : dirty) {
    if (loaded_flag[i] != 0) {
      const std::uint32_t c = comp_of_cell[i];
      if (comp_stamp[c] != stamp) {
        comp_stamp[c] = stamp;
        solve_component(c);
      }
      continue;
    }
    const CellInfo& ci = info[i];
    for (std::uint32_t k = ci.valve_begin; k < ci.valve_end; ++k) {
      const std::uint32_t v = cell_valves[k];
      const std::int32_t c = valve_comp[v];
      if (c < 0) {
        if (t[v] != t_min || current[v] != 0.0) {
          t[v] = t_min;
          tau[v] = tau_min;
          current[v] = 0.0;
          ++rep.valve_updates;
        }
      } else if (comp_stamp[static_cast<std::size_t>(c)] != stamp) {
        comp_stamp[static_cast<std::size_t>(c)] = stamp;
        solve_component(static_cast<std::size_t>(c));
      }
    }
  }
  // Summary over the loaded cells.
  rep.loaded_cells = loaded_list.size();
  rep.clamped_cells = 0;
  double sum2 = 0.0;
  double worst = 0.0;
  for (const std::uint32_t i : loaded_list) {
    const CellSolution& o = out[i];
    rep.clamped_cells += (o.clamped_low || o.clamped_high) ? 1 : 0;
    sum2 += o.residual_N * o.residual_N;
    worst = std::max(worst, std::fabs(o.residual_N));
  }
  rep.residual_norm_N = std::sqrt(sum2);
  rep.max_residual_N = worst;
  return Status::ok;
}

// The loaded cells' components (joined by shared valves) with their incidence: for each valve,
// the rows and Jacobian slots of its loaded cells. Rebuilt only when a cell starts or stops
// being loaded.
void CellInverse::Impl::rebuild_partition() noexcept {
  ++stamp;
  std::size_t nc = 0;
  std::uint32_t ncell = 0;
  std::uint32_t nval = 0;
  std::uint32_t ninc = 0;
  std::uint32_t nbeg = 0;
  part_cell_begin[0] = 0;
  part_valve_begin[0] = 0;
  for (std::size_t v = 0; v < valves; ++v) {
    valve_comp[v] = -1;
  }
  for (std::size_t seed = 0; seed < cells; ++seed) {
    if (loaded_flag[seed] == 0 || cell_stamp[seed] == stamp) {
      continue;
    }
    const std::uint32_t first_cell = ncell;
    cell_stamp[seed] = stamp;
    row_of[seed] = 0;
    comp_of_cell[seed] = static_cast<std::uint32_t>(nc);
    part_cells[ncell++] = static_cast<std::uint32_t>(seed);
    const std::uint32_t first_valve = nval;
    part_inc_begin[nbeg++] = ninc;
    for (std::uint32_t head = first_cell; head < ncell; ++head) {
      const CellInfo& ci = info[part_cells[head]];
      for (std::uint32_t k = ci.valve_begin; k < ci.valve_end; ++k) {
        const std::uint32_t v = cell_valves[k];
        if (valve_comp[v] >= 0) {
          continue;
        }
        valve_comp[v] = static_cast<std::int32_t>(nc);
        local_of[v] = nval - first_valve;
        part_valves[nval++] = v;
        for (std::uint32_t j = valve_cell_begin[v]; j < valve_cell_begin[v + 1]; ++j) {
          const std::uint32_t other = valve_cells[j];
          if (loaded_flag[other] == 0) {
            continue;
          }
          if (cell_stamp[other] != stamp) {
            cell_stamp[other] = stamp;
            row_of[other] = ncell - first_cell;
            comp_of_cell[other] = static_cast<std::uint32_t>(nc);
            part_cells[ncell++] = other;
          }
          part_inc_row[ninc] = row_of[other];
          part_inc_slot[ninc] = valve_cell_slot[j];
          ++ninc;
        }
        part_inc_begin[nbeg++] = ninc;
      }
    }
    const std::uint32_t rows = ncell - first_cell;
    part_factor_off[nc + 1] = part_factor_off[nc] + (rows <= kDenseRows ? rows * rows : 0);
    factor_age[nc] = -1;
    ++nc;
    part_cell_begin[nc] = ncell;
    part_valve_begin[nc] = nval;
  }
  // Cells that left a component keep no stale warm start.
  for (std::size_t i = 0; i < cells; ++i) {
    if (loaded_flag[i] == 0) {
      cache[i].gn_last = false;
    }
  }
  loaded_list.clear();
  for (std::size_t i = 0; i < cells; ++i) {
    if (loaded_flag[i] != 0) {
      loaded_list.push_back(static_cast<std::uint32_t>(i));
    }
  }
}

void CellInverse::Impl::solve_component(std::size_t comp) noexcept {
  comp_id = comp;
  comp_cells = std::span<const std::uint32_t>(part_cells.data() + part_cell_begin[comp],
                                              part_cell_begin[comp + 1] - part_cell_begin[comp]);
  comp_valves = std::span<const std::uint32_t>(part_valves.data() + part_valve_begin[comp],
                                               part_valve_begin[comp + 1] - part_valve_begin[comp]);
  inc_begin = part_inc_begin.data() + part_valve_begin[comp] + comp;
  ++rep.components_solved;
  // Each valve takes the largest uniform demand of its loaded cells: exact when no cell has a
  // valve raised above its own demand. Otherwise Gauss-Newton, warm-started from the last solve
  // when every cell of the component was solved that way then.
  bool warm = true;
  for (const std::uint32_t cell : comp_cells) {
    warm = warm && cache[cell].gn_last;
  }
  bool conflict = warm;  // a warm component keeps tracking (its levels already resolve it)
  for (std::size_t k = 0; k < comp_valves.size() && !warm; ++k) {
    double level = t_min;
    for (std::uint32_t j = inc_begin[k]; j < inc_begin[k + 1]; ++j) {
      level = std::max(level, demand_of(comp_cells[inc_row[j]]));
    }
    t1[k] = level;
  }
  // A flowing cell with any valve raised renders too much; a holding cell only when every valve
  // is raised (its weakest branch sets its pressure).
  for (std::size_t r = 0; r < comp_cells.size() && !warm; ++r) {
    const std::uint32_t cell = comp_cells[r];
    const CellInfo& ci = info[cell];
    const Derived& d = cur(cell);
    bool any = false;
    bool all = true;
    for (std::uint32_t k = ci.valve_begin; k < ci.valve_end; ++k) {
      const bool raised = t1[local_of[cell_valves[k]]] > demand_of(cell);
      any = any || raised;
      all = all && raised;
    }
    conflict = conflict || (d.flow_m3_per_s > 0.0 ? any : all && !d.one_sided);
  }
  if (!conflict || !warm) {
    for (std::size_t k = 0; k < comp_valves.size(); ++k) {
      t[comp_valves[k]] = t1[k];
    }
  }
  for (const std::uint32_t cell : comp_cells) {
    out[cell].residual_N = 0.0;
  }
  bool used_gn = false;
  if (conflict) {
    used_gn = true;
    bool converged = false;
    bool tracked = false;
    // Warm: residuals only first (a chord step reuses the saved Jacobian).
    double merit = evaluate_rows(!warm, !warm);
    if (warm && comp_cells.size() <= kDenseRows) {
      // Tracking: the last solve's levels with this tick's targets. A small error takes one
      // damped step, unverified: its residuals are the linear model's prediction, and the next
      // tick's rows check it.
      double worst = 0.0;
      bool near = true;
      for (std::size_t r = 0; r < comp_cells.size(); ++r) {
        const double er = one_sided[r] != 0 && e[r] > 0.0 ? 0.0 : std::fabs(e[r]);
        worst = std::max(worst, er);
        near = near && er <= kTrackReach * (aim_row[r] + tol_Pa);
      }
      if (worst <= tol_Pa) {
        converged = true;
        tracked = true;
      } else if (near) {
        damping = kMinDamping;
        // A small correction reuses the last factorisation (a chord step: J frozen); a larger
        // one, an old factor or a changed active set refactorises.
        bool chord = factor_age[comp_id] >= 0 && factor_age[comp_id] < kChordAge;
        for (std::size_t r = 0; r < comp_cells.size() && chord; ++r) {
          chord = std::fabs(e[r]) <= kChordReach * aim_row[r] + chord_floor_Pa;
        }
        if (!chord || !chord_step()) {
          evaluate_rows(false, true);
          bounded_step();
        }
        ++rep.iterations;
        double worst_pred = 0.0;
        for (std::size_t k = 0; k < comp_valves.size(); ++k) {
          t[comp_valves[k]] = t1[k];
        }
        for (std::size_t r = 0; r < comp_cells.size(); ++r) {
          e[r] = predicted[r];
          worst_pred = std::max(worst_pred, one_sided[r] != 0 && e[r] > 0.0 ? 0.0 : std::fabs(e[r]));
        }
        converged = worst_pred <= tol_Pa;
        tracked = true;
        rep.residual_predicted = true;
      }
    }
    if (!tracked) {
      if (warm) {
        merit = evaluate_rows();  // far from the aim: relinearise where needed
      }
      merit = gauss_newton(warm ? kMinDamping : kStartDamping, converged, merit);
      if (!converged && warm) {
        // The last solve's levels led nowhere (e.g. a press turned into a hold, where the weakest
        // valve rules): start again from the demands, as a cold solve would.
        for (std::size_t k = 0; k < comp_valves.size(); ++k) {
          double level = t_min;
          for (std::uint32_t j = inc_begin[k]; j < inc_begin[k + 1]; ++j) {
            level = std::max(level, demand_of(comp_cells[inc_row[j]]));
          }
          best[k] = t[comp_valves[k]];
          t[comp_valves[k]] = level;
        }
        bool cold_converged = false;
        const double cold = gauss_newton(kStartDamping, cold_converged, evaluate_rows());
        if (cold < merit) {
          merit = cold;
          converged = cold_converged;
        } else {
          for (std::size_t k = 0; k < comp_valves.size(); ++k) {
            t[comp_valves[k]] = best[k];
          }
          merit = evaluate_rows();
        }
        warm = false;  // and the escapes below if still short
      }
    }
    if (!converged && !warm) {
      // A cold start can stall where two cells pull a shared valve both ways and symmetry keeps
      // the valves together (e.g. a corner cell that must flow through one of its two valves
      // while its neighbour needs both high). Try opening or shutting each such valve.
      std::size_t candidates = 0;
      for (std::size_t k = 0; k < comp_valves.size(); ++k) {
        const std::uint32_t v = comp_valves[k];
        bool high = false;
        bool low = false;
        for (std::uint32_t j = inc_begin[k]; j < inc_begin[k + 1]; ++j) {
          const double er = e[inc_row[j]];
          high = high || (er > tol_Pa && one_sided[inc_row[j]] == 0);
          low = low || er < -tol_Pa;
        }
        if (high && low) {
          escape[candidates++] = static_cast<std::uint32_t>(k);
        }
        best[k] = t[v];
      }
      double best_merit = merit;
      for (std::size_t i = 0; i < 2 * candidates && i < kMaxEscapes && !converged; ++i) {
        for (std::size_t k = 0; k < comp_valves.size(); ++k) {
          t[comp_valves[k]] = best[k];
        }
        t[comp_valves[escape[i / 2]]] = i % 2 == 0 ? t_min : t_max;
        bool conv_i = false;
        const double merit_i = gauss_newton(kStartDamping, conv_i, evaluate_rows());
        if (merit_i < best_merit) {
          best_merit = merit_i;
          converged = conv_i;
          for (std::size_t k = 0; k < comp_valves.size(); ++k) {
            best[k] = t[comp_valves[k]];
          }
        }
      }
      if (candidates > 0) {
        for (std::size_t k = 0; k < comp_valves.size(); ++k) {
          t[comp_valves[k]] = best[k];
        }
        evaluate_rows();
      }
    }
    double worst = 0.0;
    for (std::size_t r = 0; r < comp_cells.size(); ++r) {
      const double er = one_sided[r] != 0 && e[r] > 0.0 ? 0.0 : e[r];
      out[comp_cells[r]].residual_N = area_m2 * er;
      worst = std::max(worst, std::fabs(er));
    }
    converged = converged || worst <= tol_Pa;
    rep.converged = rep.converged && converged;
  }
  for (const std::uint32_t cell : comp_cells) {
    cache[cell].gn_last = used_gn;
  }
  write_valves();
}

// Damped Gauss-Newton (Levenberg-Marquardt with backtracking) from the current levels of the
// component; leaves the rows evaluated at the final levels. Returns the merit.
double CellInverse::Impl::gauss_newton(double start_damping, bool& converged, double merit) noexcept {
  damping = start_damping;
  converged = false;
  for (int it = 0;; ++it) {
    double worst = 0.0;
    for (std::size_t r = 0; r < comp_cells.size(); ++r) {
      worst = std::max(worst, one_sided[r] != 0 && e[r] > 0.0 ? 0.0 : std::fabs(e[r]));
    }
    if (worst <= tol_Pa) {
      converged = true;
      break;
    }
    if (it >= opt.max_iterations) {
      break;
    }
    ++rep.iterations;
    for (std::size_t k = 0; k < comp_valves.size(); ++k) {
      t0[k] = t[comp_valves[k]];
    }
    if (comp_cells.size() <= kDenseRows) {
      bounded_step();
    } else {
      fallback_step();
    }
    // Backtrack on the merit (the rows are piecewise smooth: holding cells take a minimum).
    double trial = 1.0;
    double merit_new = merit;
    for (int bt = 0; bt <= kMaxBacktracks; ++bt) {
      for (std::size_t k = 0; k < comp_valves.size(); ++k) {
        t[comp_valves[k]] = t0[k] + trial * (t1[k] - t0[k]);
      }
      merit_new = evaluate_rows();
      if (merit_new <= merit) {
        break;
      }
      trial *= 0.5;
    }
    damping = trial < 1.0 ? damping * 8.0 : std::max(damping * 0.25, kMinDamping);
    if (!(merit_new <= merit)) {
      for (std::size_t k = 0; k < comp_valves.size(); ++k) {
        t[comp_valves[k]] = t0[k];
      }
      merit = evaluate_rows();
      break;  // no descent left at this linearisation: stop here
    }
    const bool stalled = merit - merit_new <= 1e-15 * merit;
    merit = merit_new;
    if (stalled) {
      break;
    }
  }
  return merit;
}

void CellInverse::Impl::write_valves() noexcept {
  const std::uint32_t* vp = comp_valves.data();
  const std::size_t nv = comp_valves.size();
  double* tp = t.data();
  for (std::size_t i = 0; i < nv; ++i) {
    const std::uint32_t v = vp[i];
    const double level = std::clamp(tp[v], t_min, t_max);
    tp[v] = level;
    const double ta = level * inv_yield_k;
    tau[v] = ta;
    current[v] = current_for_tau(ta * inv_valve_gain[v]);
  }
  rep.valve_updates += nv;
}

double CellInverse::Impl::evaluate_rows(bool relinearise, bool jacobian) noexcept {
  double merit = 0.0;
  double* jac_p = jac.data();
  const double* t_p = t.data();
  for (std::size_t r = 0; r < comp_cells.size(); ++r) {
    const std::uint32_t cell = comp_cells[r];
    const Derived& d = cur(cell);
    const CellInfo& ci = info[cell];
    const Branch* bb = branches.data() + ci.branch_begin;
    const Branch* be = branches.data() + ci.branch_end;
    double* jc = jac_p + ci.valve_begin;
    const std::size_t nvc = ci.valve_end - ci.valve_begin;
    ++rep.cell_updates;
    one_sided[r] = d.one_sided ? 1 : 0;
    aim_row[r] = d.aim_Pa;
    for (std::size_t k = 0; k < nvc && (jacobian || relinearise); ++k) {
      jc[k] = 0.0;
    }
    double er = 0.0;
    if (d.flow_m3_per_s <= 0.0) {
      // Holding: the weakest branch sets the pressure; ties share the sensitivity.
      double p = std::numeric_limits<double>::infinity();
      for (const Branch* br = bb; br != be; ++br) {
        p = std::min(p, br->valve < 0 ? 0.0 : br->s * t_p[br->valve]);
      }
      er = p - d.aim_Pa;
      if (!jacobian && !relinearise) {
        e[r] = er;
        merit += one_sided[r] != 0 && er > 0.0 ? 0.0 : er * er;
        continue;
      }
      const double tie = p * (1.0 + 1e-9) + 1e-12;
      double n = 0.0;
      for (const Branch* br = bb; br != be; ++br) {
        if (br->valve >= 0 && br->s * t_p[br->valve] <= tie) {
          jac_p[br->slot] += br->s;
          n += 1.0;
        }
      }
      const double inv = n > 0.0 ? 1.0 / n : 0.0;
      for (std::size_t k = 0; k < nvc; ++k) {
        jc[k] *= inv;
      }
      er = p - d.aim_Pa;
    } else {
      // Flowing: residual of the flow balance at the aimed pressure over the cell's conductance
      // (Newton's pressure correction); exact at convergence and free of inner solves.
      double p = d.aim_Pa;
      double flow = -d.flow_m3_per_s;
      double cond = 0.0;
      if (!jacobian && !relinearise) {
        for (const Branch* br = bb; br != be; ++br) {
          branch_q(*br, p, br->valve < 0 ? 0.0 : t_p[br->valve], flow, cond);
        }
        // Nothing flows at the aim: the true pressure is above it by an unknown amount.
        er = cond > 1e-9 * ci.open_conductance ? -flow / cond : std::numeric_limits<double>::infinity();
        e[r] = er;
        merit += one_sided[r] != 0 && er > 0.0 ? 0.0 : er * er;
        continue;
      }
      for (const Branch* br = bb; br != be; ++br) {
        const Flow f = branch_flow(*br, p, br->valve < 0 ? 0.0 : t_p[br->valve]);
        flow += f.q;
        cond += f.dq_dp;
        jac_p[br->slot] += br->valve < 0 ? 0.0 : f.dq_dt;
      }
      // Near the aim this is Newton's correction. Far from it, valves that hold at the aim but
      // flow at the true pressure would look inert: linearise at the true pressure instead.
      if (relinearise && !(cond > 1e-9 * ci.open_conductance &&
                           std::fabs(flow) <= kLinearisationReach * cond * (d.aim_Pa + tol_Pa))) {
        p = forward(cell, d.flow_m3_per_s, [t_p](std::size_t v) { return t_p[v]; });
        flow = -d.flow_m3_per_s;
        cond = 0.0;
        for (std::size_t k = 0; k < nvc; ++k) {
          jc[k] = 0.0;
        }
        for (const Branch* br = bb; br != be; ++br) {
          const Flow f = branch_flow(*br, p, br->valve < 0 ? 0.0 : t_p[br->valve]);
          flow += f.q;
          cond += f.dq_dp;
          jac_p[br->slot] += br->valve < 0 ? 0.0 : f.dq_dt;
        }
      }
      if (cond > 0.0) {
        const double inv = 1.0 / cond;
        er = p - d.aim_Pa - flow * inv;
        for (std::size_t k = 0; k < nvc; ++k) {
          jc[k] *= -inv;
        }
      } else {
        er = p - d.aim_Pa;
      }
    }
    e[r] = er;
    merit += one_sided[r] != 0 && er > 0.0 ? 0.0 : er * er;
  }
  return merit;
}

// One bounded Levenberg-Marquardt step in the row space:
//   min |e + J (t1 - t)|^2 + mu |t1 - t|^2 + lambda |t1|^2,  t_min <= t1 <= t_max,
// t1 = (1 - lambda / D) t + J^T z with (J_F J_F^T + D I) z = c - J_B (t_B - (1 - lambda / D) t_B),
// D = mu + lambda, c = (lambda / D) J t - e; an active set on the bounds and on one-sided rows.
// The damping is towards the current levels, so that a valve no cell is sensitive to at this
// linearisation (a branch held shut) stays where it is.
void CellInverse::Impl::bounded_step() noexcept {
  const std::size_t nr = comp_cells.size();
  const std::size_t nv = comp_valves.size();
  const double diag = damping + opt.regularisation;
  const double shrink = opt.regularisation / diag;
  const double keep = 1.0 - shrink;
  const double* jac_p = jac.data();
  // Each valve's column is its incidence list (1-4 loaded cells): every product below is
  // sparse, O(incidences), never rows x valves.
  for (std::size_t r = 0; r < nr; ++r) {
    crow[r] = -e[r];
    included[r] = one_sided[r] == 0 || e[r] < 0.0 ? 1 : 0;
  }
  // Start from the bounds the levels sit on (the active set rarely changes between steps).
  for (std::size_t k = 0; k < nv; ++k) {
    const double tv = t[comp_valves[k]];
    t0[k] = tv;
    bound[k] = tv <= t_min ? 1 : (tv >= t_max ? 2 : 0);
    const double st = shrink * tv;
    for (std::uint32_t j = inc_begin[k]; j < inc_begin[k + 1]; ++j) {
      crow[inc_row[j]] += jac_p[inc_slot[j]] * st;
    }
  }
  const double eps = 1e-9 * t_max;  // below this a change is round-off: clamp it
  for (int pass = 0; pass < kMaxActiveSetPasses; ++pass) {
    // System over all rows; an excluded row gets a unit diagonal and a zero right-hand side.
    for (std::size_t a = 0; a < nr; ++a) {
      double* ma = &mat[a * nr];
      for (std::size_t b = 0; b < nr; ++b) {
        ma[b] = 0.0;
      }
      ma[a] = included[a] != 0 ? diag : 1.0;
      rhs[a] = included[a] != 0 ? crow[a] : 0.0;
    }
    for (std::size_t k = 0; k < nv; ++k) {
      const std::uint32_t lo = inc_begin[k];
      const std::uint32_t hi = inc_begin[k + 1];
      if (bound[k] != 0) {
        const double tb = (bound[k] == 1 ? t_min : t_max) - keep * t0[k];
        for (std::uint32_t j = lo; j < hi; ++j) {
          rhs[inc_row[j]] -= included[inc_row[j]] != 0 ? jac_p[inc_slot[j]] * tb : 0.0;
        }
        continue;
      }
      for (std::uint32_t j1 = lo; j1 < hi; ++j1) {
        const std::uint32_t a = inc_row[j1];
        if (included[a] == 0) {
          continue;
        }
        const double ja = jac_p[inc_slot[j1]];
        double* ma = &mat[a * nr];
        for (std::uint32_t j2 = lo; j2 < hi; ++j2) {
          const std::uint32_t b = inc_row[j2];
          ma[b] += included[b] != 0 ? ja * jac_p[inc_slot[j2]] : 0.0;
        }
      }
    }
    // Cholesky (lower, in place) and the two triangular solves; the damping keeps it definite.
    for (std::size_t j = 0; j < nr; ++j) {
      double* mj = &mat[j * nr];
      double dj = mj[j];
      for (std::size_t k = 0; k < j; ++k) {
        dj -= mj[k] * mj[k];
      }
      dj = std::sqrt(std::max(dj, diag));
      mj[j] = dj;
      const double inv = 1.0 / dj;
      for (std::size_t i = j + 1; i < nr; ++i) {
        double* mi = &mat[i * nr];
        double sum = mi[j];
        for (std::size_t k = 0; k < j; ++k) {
          sum -= mi[k] * mj[k];
        }
        mi[j] = sum * inv;
      }
    }
    std::copy(rhs.data(), rhs.data() + nr, dual.data());
    cholesky_solve(mat.data(), nr, dual.data());
    // Unconstrained values J^T z + the shrunk levels, and the bound changes they call for.
    bool changed = false;
    double most = eps;
    std::size_t release = nv;
    for (std::size_t k = 0; k < nv; ++k) {
      double u = keep * t0[k];
      for (std::uint32_t j = inc_begin[k]; j < inc_begin[k + 1]; ++j) {
        u += jac_p[inc_slot[j]] * dual[inc_row[j]];
      }
      tu[k] = u;
      if (bound[k] == 0) {
        if (u < t_min - eps || u > t_max + eps) {
          bound[k] = u < t_min ? 1 : 2;
          changed = true;
        }
      } else {
        const double inside = bound[k] == 1 ? u - t_min : t_max - u;
        if (inside > most) {
          most = inside;
          release = k;
        }
      }
    }
    // Release the bound valve whose gradient points inside most (one a pass, and only once the
    // free set is consistent: releasing all at once makes coupled valves cycle).
    if (!changed && release < nv) {
      bound[release] = 0;
      changed = true;
    }
    for (std::size_t r = 0; r < nr; ++r) {
      predicted[r] = e[r];
    }
    for (std::size_t k = 0; k < nv; ++k) {
      const double tk = bound[k] == 0 ? std::clamp(tu[k], t_min, t_max) : (bound[k] == 1 ? t_min : t_max);
      t1[k] = tk;
      const double dk = tk - t0[k];
      for (std::uint32_t j = inc_begin[k]; j < inc_begin[k + 1]; ++j) {
        predicted[inc_row[j]] += jac_p[inc_slot[j]] * dk;
      }
    }
    // One-sided rows (aim at the lock) count only below their aim. A row changes sides at most
    // twice a step, and only beyond a band (no cycling). States: 0 out, 1 in, 2 out after being
    // in, 3 back in for good.
    const double hysteresis = 0.01 * tol_Pa;
    for (std::size_t r = 0; r < nr; ++r) {
      if (one_sided[r] == 0) {
        continue;
      }
      const unsigned char st = included[r];
      if (st == 1 && predicted[r] > hysteresis) {
        included[r] = 0;
        excluded_once[r] = 1;
        changed = true;
      } else if (st == 0 && predicted[r] < -hysteresis) {
        included[r] = excluded_once[r] != 0 ? 3 : 1;
        changed = true;
      }
    }
    if (!changed) {
      save_factor(diag);
      break;
    }
    factor_age[comp_id] = -1;  // the last factorisation is not the final active set's
  }
  for (std::size_t r = 0; r < nr; ++r) {
    excluded_once[r] = 0;
  }
}

// Keeps the final factorisation of a bounded step with its Jacobian, bounds and rows, for the
// chord steps of the next ticks.
void CellInverse::Impl::save_factor(double diag) noexcept {
  const std::size_t nr = comp_cells.size();
  const std::size_t nv = comp_valves.size();
  double* f = factor_pool.data() + part_factor_off[comp_id];
  std::copy(mat.data(), mat.data() + nr * nr, f);
  const std::uint32_t first = inc_begin[0];
  for (std::uint32_t j = first; j < inc_begin[nv]; ++j) {
    part_inc_jac[j] = jac[inc_slot[j]];
  }
  unsigned char* pb = part_bound.data() + part_valve_begin[comp_id];
  for (std::size_t k = 0; k < nv; ++k) {
    pb[k] = bound[k];
  }
  unsigned char* pi = part_included.data() + part_cell_begin[comp_id];
  for (std::size_t r = 0; r < nr; ++r) {
    pi[r] = included[r] == 1 || included[r] == 3 ? 1 : 0;
  }
  factor_diag[comp_id] = diag;
  factor_age[comp_id] = 0;
}

// A chord step: the saved factorisation and Jacobian with this tick's residuals. Returns false
// (nothing changed) when the saved active set no longer holds, so that the caller refactorises.
bool CellInverse::Impl::chord_step() noexcept {
  // Pure damped step (the ridge's pull is left to the refactorising steps): bound valves stay
  // on their bound, z = M^-1 (-e), free valves move by J^T z.
  const std::size_t nr = comp_cells.size();
  const std::size_t nv = comp_valves.size();
  const double* f = factor_pool.data() + part_factor_off[comp_id];
  const double* ij = part_inc_jac.data();
  const unsigned char* pb = part_bound.data() + part_valve_begin[comp_id];
  const unsigned char* pi = part_included.data() + part_cell_begin[comp_id];
  for (std::size_t r = 0; r < nr; ++r) {
    if (one_sided[r] != 0 && (pi[r] != 0) != (e[r] < 0.0)) {
      return false;  // a one-sided row changed sides
    }
  }
  for (std::size_t i = 0; i < nr; ++i) {
    dual[i] = pi[i] != 0 ? -e[i] : 0.0;
  }
  cholesky_solve(f, nr, dual.data());
  for (std::size_t r = 0; r < nr; ++r) {
    predicted[r] = e[r];
  }
  bool clamped = false;
  const double* tp = t.data();
  const std::uint32_t* vp = comp_valves.data();
  const double eps = 1e-9 * t_max;
  for (std::size_t k = 0; k < nv; ++k) {
    const double tk = tp[vp[k]];
    const std::uint32_t lo = inc_begin[k];
    const std::uint32_t hi = inc_begin[k + 1];
    double u = tk;
    for (std::uint32_t j = lo; j < hi; ++j) {
      u += ij[j] * dual[inc_row[j]];
    }
    if (pb[k] != 0) {
      // A bound valve the step would pull inside: the active set changed, refactorise.
      if ((pb[k] == 1 && u > t_min + eps) || (pb[k] == 2 && u < t_max - eps)) {
        factor_age[comp_id] = -1;
        return false;
      }
      t1[k] = tk;
      continue;
    }
    clamped = clamped || u < t_min || u > t_max;
    u = std::clamp(u, t_min, t_max);
    t1[k] = u;
    const double dk = u - tk;
    for (std::uint32_t j = lo; j < hi; ++j) {
      predicted[inc_row[j]] += ij[j] * dk;
    }
  }
  // A valve reached a bound: its step is clamped; refactorise next time.
  factor_age[comp_id] = clamped ? -1 : factor_age[comp_id] + 1;
  return true;
}

// Large components: projected Gauss-Seidel on the same linearised problem (sparse, O(nnz) a sweep).
void CellInverse::Impl::fallback_step() noexcept {
  const std::size_t nr = comp_cells.size();
  const std::size_t nv = comp_valves.size();
  for (std::size_t r = 0; r < nr; ++r) {
    res[r] = e[r];
    included[r] = one_sided[r] == 0 || e[r] < 0.0 ? 1 : 0;
  }
  for (std::size_t k = 0; k < nv; ++k) {
    t1[k] = t[comp_valves[k]];
  }
  const double lambda = opt.regularisation;
  // Stop sweeping once no valve moves its rows by more than a tenth of the tolerance: a small
  // patch settles in a few sweeps, so its cost follows its size, not the sweep cap.
  const double settled_Pa = 0.1 * tol_Pa;
  for (int sweep = 0; sweep < kFallbackSweeps; ++sweep) {
    double moved_Pa = 0.0;
    for (std::size_t k = 0; k < nv; ++k) {
      double a = lambda + damping;
      double g = lambda * t1[k] + damping * (t1[k] - t0[k]);
      for (std::uint32_t j = inc_begin[k]; j < inc_begin[k + 1]; ++j) {
        const std::uint32_t r = inc_row[j];
        const double jv = jac[inc_slot[j]];
        if (included[r] != 0 || res[r] < 0.0) {
          a += jv * jv;
          g += jv * res[r];
        }
      }
      const double next_t = std::clamp(t1[k] - g / a, t_min, t_max);
      const double delta = next_t - t1[k];
      if (delta == 0.0) {
        continue;
      }
      t1[k] = next_t;
      moved_Pa = std::max(moved_Pa, std::fabs(delta) * std::sqrt(a));
      for (std::uint32_t j = inc_begin[k]; j < inc_begin[k + 1]; ++j) {
        res[inc_row[j]] += jac[inc_slot[j]] * delta;
      }
    }
    if (moved_Pa <= settled_Pa) {
      break;
    }
  }
}

// ---- public surface ------------------------------------------------------------------------

CellInverse::CellInverse(const DeviceModel& model, const InverseOptions& options)
    : impl_(std::make_unique<Impl>(model, options)) {}
CellInverse::~CellInverse() = default;
CellInverse::CellInverse(CellInverse&&) noexcept = default;
CellInverse& CellInverse::operator=(CellInverse&&) noexcept = default;

std::size_t CellInverse::fluid_cell_count() const noexcept { return impl_->cells; }
std::size_t CellInverse::valve_count() const noexcept { return impl_->valves; }

Status CellInverse::solve(std::span<const CellImpedanceTarget> targets, std::span<const CellState> states,
                          double now_s) noexcept {
  return impl_->solve(targets, states, now_s);
}

std::span<const double> CellInverse::currents_A() const noexcept { return impl_->current; }
std::span<const double> CellInverse::valve_yield_stress_Pa() const noexcept { return impl_->tau; }
std::span<const CellSolution> CellInverse::cells() const noexcept { return impl_->out; }
const InverseReport& CellInverse::report() const noexcept { return impl_->rep; }

void CellInverse::invalidate() noexcept {
  for (Impl::CellCache& c : impl_->cache) {
    c.valid = false;
    c.gn_last = false;
  }
}

Result<double> CellInverse::valve_pressure_Pa(std::size_t cell, double flow_m3_per_s,
                                              std::span<const double> valve_yield_Pa) const noexcept {
  const Impl& m = *impl_;
  if (cell >= m.cells || valve_yield_Pa.size() != m.valves) {
    return failure<double>(Status::out_of_range);
  }
  if (!finite(flow_m3_per_s)) {
    return failure<double>(Status::not_finite);
  }
  if (flow_m3_per_s < 0.0) {
    return failure<double>(Status::negative);
  }
  for (const double y : valve_yield_Pa) {
    if (!finite(y)) {
      return failure<double>(Status::not_finite);
    }
    if (y < 0.0) {
      return failure<double>(Status::negative);
    }
  }
  const double k = m.yield_k;
  return {m.forward(cell, flow_m3_per_s, [&](std::size_t v) { return k * valve_yield_Pa[v]; })};
}

Status CellInverse::set_valve_yield_gain(std::span<const double> gain) noexcept {
  if (gain.size() != impl_->inv_valve_gain.size()) {
    return Status::out_of_range;
  }
  for (const double g : gain) {
    if (!finite(g) || !(g > 0.0)) {
      return Status::out_of_range;
    }
  }
  for (std::size_t v = 0; v < gain.size(); ++v) {
    impl_->inv_valve_gain[v] = 1.0 / gain[v];
  }
  return Status::ok;
}

Result<double> CellInverse::current_for_yield_stress_A(double yield_stress_Pa) const noexcept {
  if (!finite(yield_stress_Pa)) {
    return failure<double>(Status::not_finite);
  }
  if (yield_stress_Pa < 0.0) {
    return failure<double>(Status::negative);
  }
  if (yield_stress_Pa > impl_->tau_max) {
    return failure<double>(Status::out_of_range);
  }
  return {impl_->current_for_tau(yield_stress_Pa)};
}

double CellInverse::current_table_max_error_Pa() const noexcept { return impl_->current_table_error; }
double CellInverse::branch_table_max_relative_error() const noexcept { return impl_->branch_table_error; }

// ---- the slow exact reference --------------------------------------------------------------

namespace {

struct ExactProblem {
  const DeviceModel& model;
  std::vector<std::size_t> loaded;
  std::vector<double> depth;
  std::vector<double> rate;
  std::vector<double> target;
  long evaluations = 0;

  double force(std::size_t cell, std::span<const double> currents) {
    ++evaluations;
    const Result<CellLoad> l = model.cell_force(cell, depth[cell], rate[cell], currents);
    return l.ok() ? l.value.force_N : std::numeric_limits<double>::quiet_NaN();
  }
  double objective(std::span<const double> currents) {
    double s = 0.0;
    for (const std::size_t i : loaded) {
      const double d = force(i, currents) - target[i];
      s += d * d;
    }
    return s;
  }
};

// Pattern search along `dir` (clamped into the box): a scan then golden section on the best
// bracket. Only `cells` change with this direction.
double line_search(ExactProblem& pb, std::vector<double>& cur, const std::vector<double>& dir,
                   const std::vector<std::size_t>& cells, double imax) {
  const std::vector<double> base = cur;
  auto at = [&](double a) {
    for (std::size_t v = 0; v < cur.size(); ++v) {
      cur[v] = dir[v] == 0.0 ? base[v] : std::clamp(base[v] + a * dir[v], 0.0, imax);
    }
    double s = 0.0;
    for (const std::size_t i : cells) {
      const double d = pb.force(i, cur) - pb.target[i];
      s += d * d;
    }
    return std::isfinite(s) ? s : std::numeric_limits<double>::infinity();
  };
  constexpr int kScan = 16;
  double best_a = 0.0;
  double best = at(0.0);
  const double start = best;
  std::array<double, kScan + 1> as{};
  std::array<double, kScan + 1> fs{};
  for (int k = 0; k <= kScan; ++k) {
    as[static_cast<std::size_t>(k)] = -imax + 2.0 * imax * k / kScan;
    fs[static_cast<std::size_t>(k)] = at(as[static_cast<std::size_t>(k)]);
    if (fs[static_cast<std::size_t>(k)] < best) {
      best = fs[static_cast<std::size_t>(k)];
      best_a = as[static_cast<std::size_t>(k)];
    }
  }
  // Golden section around the best point found (one scan step each side).
  double lo = best_a - 2.0 * imax / kScan;
  double hi = best_a + 2.0 * imax / kScan;
  const double gr = 0.5 * (std::sqrt(5.0) - 1.0);
  double x1 = hi - gr * (hi - lo);
  double x2 = lo + gr * (hi - lo);
  double f1 = at(x1);
  double f2 = at(x2);
  for (int it = 0; it < 60 && hi - lo > 1e-12 * imax; ++it) {
    if (f1 < f2) {
      hi = x2;
      x2 = x1;
      f2 = f1;
      x1 = hi - gr * (hi - lo);
      f1 = at(x1);
    } else {
      lo = x1;
      x1 = x2;
      f1 = f2;
      x2 = lo + gr * (hi - lo);
      f2 = at(x2);
    }
  }
  if (f1 < best) {
    best = f1;
    best_a = x1;
  }
  if (f2 < best) {
    best = f2;
    best_a = x2;
  }
  at(best < start ? best_a : 0.0);
  return start - std::min(best, start);
}

void pattern_search(ExactProblem& pb, std::vector<double>& cur, int max_sweeps, int& sweeps) {
  const DeviceModel& m = pb.model;
  const double imax = m.profile().coil.max_current_A;
  const GridLayout& l = m.layout();
  // Directions: each valve of a loaded cell, then each loaded cell's valves together.
  std::vector<std::vector<double>> dirs;
  std::vector<std::vector<std::size_t>> touched;
  std::vector<char> used(cur.size(), 0);
  auto cells_of_valves = [&](const std::vector<double>& dir) {
    std::vector<std::size_t> cs;
    for (const std::size_t i : pb.loaded) {
      for (const std::size_t v : l.valves_of_cell(i)) {
        if (dir[v] != 0.0) {
          cs.push_back(i);
          break;
        }
      }
    }
    return cs;
  };
  for (const std::size_t i : pb.loaded) {
    for (const std::size_t v : l.valves_of_cell(i)) {
      if (used[v] == 0) {
        used[v] = 1;
        std::vector<double> d(cur.size(), 0.0);
        d[v] = 1.0;
        touched.push_back(cells_of_valves(d));
        dirs.push_back(std::move(d));
      }
    }
  }
  for (const std::size_t i : pb.loaded) {
    std::vector<double> d(cur.size(), 0.0);
    for (const std::size_t v : l.valves_of_cell(i)) {
      d[v] = 1.0;
    }
    touched.push_back(cells_of_valves(d));
    dirs.push_back(std::move(d));
  }
  double f = pb.objective(cur);
  for (sweeps = 0; sweeps < max_sweeps; ++sweeps) {
    double gain = 0.0;
    for (std::size_t k = 0; k < dirs.size(); ++k) {
      gain += line_search(pb, cur, dirs[k], touched[k], imax);
    }
    f -= gain;
    if (gain <= 1e-14 * std::max(f, 1e-12) || f <= 1e-20) {
      ++sweeps;
      break;
    }
  }
}

}  // namespace

ExactInverseResult solve_inverse_exact(const DeviceModel& model, std::span<const CellImpedanceTarget> targets,
                                       std::span<const CellState> states, double now_s,
                                       std::span<const double> start_currents_A,
                                       const InverseOptions& options, int max_sweeps) {
  const std::size_t cells = model.layout().fluid_cell_count();
  const std::size_t valves = model.layout().valve_count();
  ExactInverseResult out;
  if (targets.size() != cells || states.size() != cells || start_currents_A.size() != valves) {
    out.status = Status::out_of_range;
    return out;
  }
  ExactProblem pb{model,
                  {},
                  std::vector<double>(cells, 0.0),
                  std::vector<double>(cells, 0.0),
                  std::vector<double>(cells, 0.0)};
  out.roles.assign(cells, CellRole::no_contact);
  out.target_force_N.assign(cells, 0.0);
  out.force_N.assign(cells, 0.0);
  for (std::size_t i = 0; i < cells; ++i) {
    const CellRole role =
        classify(states[i], now_s > targets[i].valid_until_s, options.hold_rate_tolerance_m_per_s);
    out.roles[i] = role;
    if (!is_loaded(role)) {
      continue;
    }
    pb.loaded.push_back(i);
    pb.depth[i] = states[i].indentation_m;
    pb.rate[i] = role == CellRole::loading ? states[i].rate_m_per_s : 0.0;
    const Result<CellEnvelope> env = model.envelope(i, pb.depth[i], pb.rate[i]);
    if (!env.ok()) {
      out.status = env.status;
      return out;
    }
    pb.target[i] =
        std::clamp(impedance_force_N(targets[i], states[i]), env.value.force_min_N, env.value.force_max_N);
    out.target_force_N[i] = pb.target[i];
  }
  const double imax = model.profile().coil.max_current_A;
  std::vector<double> a(start_currents_A.begin(), start_currents_A.end());
  for (double& x : a) {
    x = std::clamp(x, 0.0, imax);
  }
  // Second start: every valve at the largest uniform current its loaded cells need.
  std::vector<double> b(valves, 0.0);
  for (const std::size_t i : pb.loaded) {
    const Result<double> ic = model.current_for_force_A(i, pb.depth[i], pb.rate[i], pb.target[i]);
    const double cur = ic.ok() ? ic.value : (pb.target[i] > 0.5 * imax ? imax : 0.0);
    for (const std::size_t v : model.layout().valves_of_cell(i)) {
      b[v] = std::max(b[v], cur);
    }
  }
  int sa = 0;
  int sb = 0;
  pattern_search(pb, a, max_sweeps, sa);
  pattern_search(pb, b, max_sweeps, sb);
  const double fa = pb.objective(a);
  const double fb = pb.objective(b);
  out.currents_A = fa <= fb ? a : b;
  out.sweeps = sa + sb;
  double sum = 0.0;
  for (const std::size_t i : pb.loaded) {
    out.force_N[i] = pb.force(i, out.currents_A);
    const double d = out.force_N[i] - pb.target[i];
    sum += d * d;
  }
  out.residual_norm_N = std::sqrt(sum);
  out.evaluations = pb.evaluations;
  return out;
}

Status exact_rendered_forces_N(const DeviceModel& model, std::span<const CellImpedanceTarget> targets,
                               std::span<const CellState> states, double now_s,
                               std::span<const double> currents_A, std::span<double> out,
                               const InverseOptions& options) {
  const std::size_t cells = model.layout().fluid_cell_count();
  if (targets.size() != cells || states.size() != cells || out.size() != cells ||
      currents_A.size() != model.layout().valve_count()) {
    return Status::out_of_range;
  }
  for (std::size_t i = 0; i < cells; ++i) {
    out[i] = 0.0;
    const CellRole role =
        classify(states[i], now_s > targets[i].valid_until_s, options.hold_rate_tolerance_m_per_s);
    if (!is_loaded(role)) {
      continue;
    }
    const double v = role == CellRole::loading ? states[i].rate_m_per_s : 0.0;
    const Result<CellLoad> l = model.cell_force(i, states[i].indentation_m, v, currents_A);
    if (!l.ok()) {
      return l.status;
    }
    out[i] = l.value.force_N;
  }
  return Status::ok;
}

}  // namespace mrskin::model
