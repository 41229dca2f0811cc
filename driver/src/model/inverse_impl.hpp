// CellInverse's private parts, shared by its sources: the branch law's tables, the checks of its
// inputs, and the state behind CellInverse (Impl). inverse_build.cpp makes the topology and the
// tables once; inverse_solve.cpp (the partition into components and each component's solve) and
// inverse_step.cpp (a component's rows and its bounded, chord and fallback steps) run every tick.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <limits>
#include <span>
#include <type_traits>
#include <vector>

#include "mrskin/driver/model/device_model.hpp"
#include "mrskin/driver/model/inverse.hpp"
#include "mrskin/driver/model/valve.hpp"

namespace mrskin::model::inverse_detail {

inline bool finite(double x) noexcept { return std::isfinite(x); }

// Table resolution (segments): cubic Hermite with exact slopes, so the error goes as K^-4.
inline constexpr int kTableSegments = 256;
// The loop's branch-flow table: linear, resampled from the Hermite one (two loads, one FMA).
inline constexpr int kLinearSegments = 4096;
inline constexpr int kCurrentSegments = 2048;
// Row-space least squares is dense up to this many cells in one component; larger components
// (big grids in full contact) fall back to projected Gauss-Seidel.
inline constexpr std::size_t kDenseRows = 32;
inline constexpr int kFallbackSweeps = 60;
inline constexpr int kMaxActiveSetPasses = 24;
inline constexpr int kMaxBacktracks = 4;
inline constexpr std::size_t kMaxEscapes = 8;  // trials: a shared valve opened or shut
// Levenberg-Marquardt damping, relative to a cell's unit sensitivity to its valves.
inline constexpr double kStartDamping = 1e-3;
inline constexpr double kMinDamping = 1e-7;
// A flowing cell's row is linearised at its aimed pressure while the predicted correction is
// within this fraction of it, else at its true pressure (one forward solve).
inline constexpr double kLinearisationReach = 0.02;
// A warm-started component whose every row is within this fraction of its aim takes one
// unverified step (tracking); beyond it, the full damped Gauss-Newton with backtracking.
inline constexpr double kTrackReach = 0.02;
// Chord steps (the last factorisation reused) while every row is within this fraction of its aim,
// for at most kChordAge ticks.
inline constexpr double kChordReach = 0.005;
inline constexpr double kChordFloor_N = 0.005;
inline constexpr int kChordAge = 16;
inline constexpr double kMaxRate_m_per_s = 10.0;  // beyond any finger: out_of_range
inline constexpr double kMinExponent = 0.5;
inline constexpr double kMaxExponent = 4.0;

// ---- dimensionless branch law (construction only: exact, safeguarded) ---------------------
// x(r): a passage's pressure over its yield threshold at r = dp_N / dp_y (valve.hpp).
inline double x_exact(double r) { return r <= 0.0 ? 1.0 : bingham_pressure_ratio(r).value; }
// dx/dr = 1 / (zeta (1.5 + r - 1.5 zeta^2)), zeta = 1 / x (differentiating the cubic).
inline double dx_exact(double r) {
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

inline BranchShape shape_of(int m) {
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
inline void cholesky_solve(const double* l, std::size_t n, double* x) noexcept {
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

// The law at x > 0 with x^n given.
inline double law_force_N(const CellImpedanceTarget& g, double xn, double v) noexcept {
  const double f = g.stiffness_N_per_m * xn + g.damping_N_s_per_m * v + g.hc_damping_N_s_per_m2 * xn * v;
  return std::clamp(f, 0.0, g.force_ceiling_N);
}

inline CellRole classify(const CellState& s, bool expired, double hold_tol) noexcept {
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

inline bool is_loaded(CellRole r) noexcept { return r == CellRole::holding || r == CellRole::loading; }

inline Status check_state(const CellState& s, double depth_m) noexcept {
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

inline Status check_target(const CellImpedanceTarget& t) noexcept {
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
inline bool same_bits(const T& a, const T& b) noexcept {
  static_assert(std::is_trivially_copyable_v<T>);
  return std::memcmp(&a, &b, sizeof(T)) == 0;  // NOLINT(bugprone-suspicious-memory-comparison)
}

// The law without its validity time, bitwise (as above).
inline bool same_law(const CellImpedanceTarget& a, const CellImpedanceTarget& b) noexcept {
  static_assert(offsetof(CellImpedanceTarget, valid_until_s) == 6 * sizeof(double));
  return std::memcmp(&a, &b, 6 * sizeof(double)) == 0;
}

}  // namespace mrskin::model::inverse_detail

namespace mrskin::model {

// The inverse's sources share these parts by name (only they include this header).
using namespace inverse_detail;

// Hidden: its functions are called directly (and inlined) within the library, never through the PLT.
struct __attribute__((visibility("hidden"))) CellInverse::Impl {
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
  Status examine(std::span<const CellImpedanceTarget> targets, std::span<const CellState> states,
                 double now_s) noexcept;
  bool commit(std::span<const CellImpedanceTarget> targets, std::span<const CellState> states,
              double now_s) noexcept;
  void resolve_dirty() noexcept;
  void summarise() noexcept;
  void rebuild_partition() noexcept;
  void solve_component(std::size_t comp) noexcept;
  void select_component(std::size_t comp) noexcept;
  double max_demand(std::size_t k) noexcept;  // the largest demand of component valve k's cells
  bool demands_conflict() noexcept;
  void solve_conflict(bool warm) noexcept;
  bool track(bool& converged) noexcept;
  double restart_cold(double merit, bool& converged) noexcept;
  void escape_stall(double merit, bool& converged) noexcept;
  // From the current levels, with the rows already evaluated there (merit: their merit).
  double gauss_newton(double start_damping, bool& converged, double merit) noexcept;
  // Fills e and jac for the component's rows; returns the merit. relinearise: a flowing row far
  // from its aim is linearised at its true pressure (a forward solve) instead of at the aim.
  // jacobian: also fill jac (else residuals only).
  double evaluate_rows(bool relinearise = true, bool jacobian = true) noexcept;
  void bounded_step() noexcept;  // t0 (+ rows) -> t1
  void start_step(double shrink) noexcept;
  void assemble_step_system(double diag, double keep) noexcept;
  void factorize_and_solve_step(double diag) noexcept;
  bool move_bounds(double keep, double eps) noexcept;
  void predict_step() noexcept;
  bool switch_one_sided_rows() noexcept;
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

}  // namespace mrskin::model
