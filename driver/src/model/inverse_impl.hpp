// CellInverse's private parts, shared by its sources: the branch law's tables, the checks of its
// inputs, and the parts CellInverse::Impl aggregates. Built once (inverse_build.cpp):
// InverseTopology with its ValveGraph. Crossing ticks: CellMemory, ValveLevels, ComponentPartition
// and ChordFactors. Each tick (inverse_solve.cpp, inverse_step.cpp): TickChanges and the
// InverseSolver's scratch. Each function takes the parts it reads as const, those it writes not.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <limits>
#include <span>
#include <type_traits>
#include <utility>
#include <vector>

#include "mrskin/driver/model/device_model.hpp"
#include "mrskin/driver/model/inverse.hpp"
#include "mrskin/driver/model/valve.hpp"

namespace mrskin::model::inverse_detail {

// Table resolution (segments): cubic Hermite with exact slopes, so the error goes as K^-4.
inline constexpr int kTableSegments = 256;
// The loop's branch-flow table: linear, resampled from the Hermite one (two loads, one FMA).
inline constexpr int kLinearSegments = 4096;
inline constexpr int kCurrentSegments = 2048;
// Row-space least squares is dense up to this many cells in one component; larger components
// (big grids in full contact) fall back to projected Gauss-Seidel, at most kFallbackSweeps
// sweeps a step: a step a solve goes on from there next tick (large_component_steps), so 20
// sweeps left the palm's held residual where 60 did, at 30 % less a tick (docs/bridge.md).
inline constexpr std::size_t kDenseRows = 32;
inline constexpr int kFallbackSweeps = 20;
inline constexpr int kMaxActiveSetPasses = 24;
inline constexpr int kMaxBacktracks = 4;
inline constexpr std::size_t kMaxEscapes = 8;  // trials: a shared valve opened or shut
// Escape trials a tick: each is a Gauss-Newton of its own (up to about 12 steps), so a search
// tries them one a tick, in place of that tick's warm solve, until each was tried.
inline constexpr std::size_t kEscapesPerSolve = 1;
// Gauss-Newton stops at a stationary point: a step that lowers the merit by less than this
// fraction. Where no levels meet every aim (more loaded cells than valves can satisfy, e.g. the
// 5x5's 13 cells pressed at once) it stops at the least-squares compromise instead of running to
// max_iterations.
inline constexpr double kStationaryDecrease = 1e-3;
// A solve that does not converge searches again, a stage a tick in place of the warm solve (a
// cold restart, then the stall escapes). When a search lowers the merit by less than kSearchGain,
// the warm solution is the compromise: the component tracks it for kSearchWait_s (on the tick's
// clock: 64 ticks at 1 kHz, 640 at 10 kHz) before searching again.
// Without the wait, an infeasible component searched every tick: up to 6.4M instructions a tick
// with the 5x5's 13 cells pressed (docs/bridge.md, "Cost per tick").
inline constexpr double kSearchGain = 0.01;
inline constexpr double kSearchWait_s = 0.064;
// A component's search, one stage a tick (ChordFactors::search_stage).
inline constexpr unsigned char kSearchIdle = 0;
inline constexpr unsigned char kSearchRestart = 1;  // a cold restart next tick
inline constexpr unsigned char kSearchEscapes = 2;  // escape trials next tick, from escape_next
// Not a search: a Gauss-Newton stopped on large_ or small_component_steps goes on
// next tick from its levels, its inputs held or not.
inline constexpr unsigned char kSearchStepping = 3;
// Warm Gauss-Newton steps a search tick takes before its stage, to follow the tick's targets.
inline constexpr int kSearchTrackSteps = 1;
// With small_component_steps set, a search's trial (a cold restart, a stall escape) takes at most
// this many times those steps and is judged where it stands: a trial that has not beaten the
// best levels by then is dropped.
inline constexpr int kTrialStepsPerStep = 2;
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
      if (!(mid > lo && mid < hi)) {
        break;  // adjacent doubles, closer than the tolerance can ask: mid is the answer
      }
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
  if (!std::isfinite(s.indentation_m) || !std::isfinite(s.rate_m_per_s)) {
    return Status::not_finite;
  }
  return Status::out_of_range;
}

inline Status check_target(const CellImpedanceTarget& t) noexcept {
  const double v[] = {t.stiffness_N_per_m, t.exponent,        t.damping_N_s_per_m, t.hc_damping_N_s_per_m2,
                      t.surface_offset_m,  t.force_ceiling_N, t.valid_until_s};
  for (const double x : v) {
    if (!std::isfinite(x)) {
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
// match needs no new validation (a -0 for a +0, or any NaN, differs and is examined again). Word
// by word, stopping at the first difference, rather than memcmp: clang 14 calls the library for
// it (about 25 instructions a compare, 13 compares a call on the 5 x 5), g++ expands it inline;
// this form is inline and as cheap in both.
template <class T>
inline std::uint64_t word_of(const T& x, std::size_t k) noexcept {
  std::uint64_t w = 0;
  std::memcpy(&w, static_cast<const unsigned char*>(static_cast<const void*>(&x)) + k * sizeof w, sizeof w);
  return w;
}

template <class T, std::size_t... K>
inline bool same_words(const T& a, const T& b, std::index_sequence<K...> /*words*/) noexcept {
  static_assert(std::is_trivially_copyable_v<T> && sizeof(T) % sizeof(std::uint64_t) == 0);
  static_assert(sizeof...(K) <= sizeof(T) / sizeof(std::uint64_t));
  return ((word_of(a, K) == word_of(b, K)) && ...);
}

template <class T>
inline bool same_bits(const T& a, const T& b) noexcept {
  return same_words(a, b, std::make_index_sequence<sizeof(T) / sizeof(std::uint64_t)>{});
}

// The law without its validity time, bitwise (as above).
inline bool same_law(const CellImpedanceTarget& a, const CellImpedanceTarget& b) noexcept {
  static_assert(offsetof(CellImpedanceTarget, valid_until_s) == 6 * sizeof(double));
  return same_words(a, b, std::make_index_sequence<6>{});
}

// ---- the topology: built once, read-only afterwards -----------------------------------------

struct BranchType {  // one per distinct outlet count among magnetised branches
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

// Branch flow at pressure P and valve level tv, with dq/dP and dq/dt.
struct Flow {
  double q = 0.0;
  double dq_dp = 0.0;
  double dq_dt = 0.0;
};
inline Flow branch_flow(const Branch& b, double p, double tv) noexcept {
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
inline void branch_q(const Branch& b, double p, double tv, double& q, double& dq_dp) noexcept {
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

// Which cell reaches which valve through which branches (CSR both ways), from the layout's links.
struct ValveGraph {
  std::size_t cells = 0;
  std::size_t valves = 0;
  std::vector<Branch> branches;
  std::vector<CellInfo> info;
  std::vector<std::uint32_t> cell_valves;  // CSR by cell
  std::vector<std::uint32_t> valve_cell_begin;
  std::vector<std::uint32_t> valve_cells;      // CSR by valve
  std::vector<std::uint32_t> valve_cell_slot;  // the valve's slot in that cell's list
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

// The options, the device's constants, the valve graph and the law's tables, made once at
// construction (inverse_build.cpp); the laws below only read them.
struct InverseTopology {
  InverseTopology(const DeviceModel& model, const InverseOptions& options);

  InverseOptions opt;
  ValveGraph graph;
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
  std::vector<BranchType> types;
  double current_scale = 0.0;        // K / (tau_max - tau_min)
  std::vector<double> current_lerp;  // interleaved (I_k, I_k+1 - I_k), I_k at tau_min + k / scale
  double inv_yield_k = 0.0;
  double current_table_error = 0.0;
  double branch_table_error = 0.0;

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
    const CellInfo& ci = graph.info[cell];
    const Branch* bb = graph.branches.data() + ci.branch_begin;
    const Branch* be = graph.branches.data() + ci.branch_end;
    double hold = std::numeric_limits<double>::infinity();
    for (const Branch* br = bb; br != be; ++br) {
      hold = std::min(hold, br->valve < 0 ? 0.0 : br->s * level(static_cast<std::size_t>(br->valve)));
    }
    if (q <= 0.0) {
      return hold;
    }
    double p = std::numeric_limits<double>::infinity();
    for (const Branch* br = bb; br != be; ++br) {
      p = std::min(p,
                   branch_pressure(*br, q, br->valve < 0 ? 0.0 : level(static_cast<std::size_t>(br->valve))));
    }
    p *= 1.0 + 1e-4;  // the bound uses the fast valve law: step safely above the root
    for (int it = 0; it < 100; ++it) {
      double f = -q;
      double df = 0.0;
      for (const Branch* br = bb; br != be; ++br) {
        const Flow fl = branch_flow(*br, p, br->valve < 0 ? 0.0 : level(static_cast<std::size_t>(br->valve)));
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
    const CellInfo& ci = graph.info[cell];
    if (q <= 0.0) {
      return ci.s_min * level;
    }
    if (level <= 0.0) {
      return q / ci.open_conductance;
    }
    if (ci.uniform_type >= 0) {
      return branch_pressure(graph.branches[ci.branch_begin], q / ci.branches, level);
    }
    return forward(cell, q, [level](std::size_t) { return level; });
  }
  // Uniform level that gives pressure p at flow q (p between the open and the full pressure).
  double demand(std::size_t cell, double q, double p) const noexcept {
    const CellInfo& ci = graph.info[cell];
    if (!(p > 0.0)) {
      return t_min;
    }
    if (q <= 0.0) {
      return ci.s_min > 0.0 ? p / ci.s_min : t_min;
    }
    if (ci.uniform_type >= 0) {
      const BranchType& ty = types[static_cast<std::size_t>(ci.uniform_type)];
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
        const Branch& br = graph.branches[b];
        f += branch_flow(br, p, br.valve < 0 ? 0.0 : mid).q;
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
  // A cell's envelope, aim and law at a target and state (prev: its last derivation, for x^n).
  Status derive(std::size_t cell, const CellImpedanceTarget& g, const CellState& s, CellRole role,
                const Derived& prev, Derived& d) const noexcept;

 private:
  void build_graph(const DeviceModel& model);
  void build_tables();
  void build_current_table(const DeviceModel& model);
};

// ---- what crosses ticks ----------------------------------------------------------------------

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

// Each cell's last inputs, their derivations and its committed role: what lets a tick redo only
// the cells that changed. examine derives into the spare slot, commit makes it current.
struct CellMemory {
  explicit CellMemory(std::size_t cells) : cache(cells), derived(2 * cells), loaded(cells, 0) {
    loaded_list.reserve(cells);
  }

  std::vector<CellCache> cache;
  std::vector<Derived> derived;            // two per cell: current and spare
  std::vector<unsigned char> loaded;       // per cell: holding or loading (committed)
  std::vector<std::uint32_t> loaded_list;  // the loaded cells, rebuilt when roles change

  [[nodiscard]] const Derived& cur(std::size_t cell) const noexcept {
    return derived[2 * cell + cache[cell].sel];
  }
  Derived& spare(std::size_t cell) noexcept { return derived[2 * cell + (1 - cache[cell].sel)]; }
  // A loaded cell's uniform demand, computed on first use after its targets changed.
  double demand_of(const InverseTopology& topo, std::size_t cell) noexcept {
    Derived& d = derived[2 * cell + cache[cell].sel];
    if (d.demand_Pa < 0.0) {
      if (d.aim_Pa <= d.p_open_Pa) {
        d.demand_Pa = topo.t_min;  // the floor (or a lock at or below it)
      } else if (d.aim_Pa >= d.p_full_Pa && !d.one_sided) {
        d.demand_Pa = topo.t_max;  // the ceiling: exactly the maximum current
      } else {
        d.demand_Pa = std::clamp(topo.demand(cell, d.flow_m3_per_s, d.aim_Pa), topo.t_min, topo.t_max);
      }
    }
    return d.demand_Pa;
  }
  // After the partition is rebuilt: cells that left a component keep no stale warm start; the
  // loaded list again.
  void roles_rebuilt() noexcept {
    for (std::size_t i = 0; i < cache.size(); ++i) {
      if (loaded[i] == 0) {
        cache[i].gn_last = false;
      }
    }
    loaded_list.clear();
    for (std::size_t i = 0; i < cache.size(); ++i) {
      if (loaded[i] != 0) {
        loaded_list.push_back(static_cast<std::uint32_t>(i));
      }
    }
  }
};

// The valves' levels and what is sent for them: written by the solver (t) and when the valves
// of a component are written out (tau, current).
struct ValveLevels {
  explicit ValveLevels(const InverseTopology& topo)
      : t(topo.graph.valves, topo.t_min),
        current(topo.graph.valves, 0.0),
        tau(topo.graph.valves, topo.tau_min),
        inv_gain(topo.graph.valves, 1.0) {}

  std::vector<double> t;  // valve levels, Pa
  std::vector<double> current;
  std::vector<double> tau;
  std::vector<double> inv_gain;  // 1 / the calibrated per-valve yield gain (setup only)

  // A valve no loaded cell needs, to its floor; true when it changed.
  bool release(const InverseTopology& topo, std::uint32_t v) noexcept {
    if (t[v] == topo.t_min && current[v] == 0.0) {
      return false;
    }
    t[v] = topo.t_min;
    tau[v] = topo.tau_min;
    current[v] = 0.0;
    return true;
  }
  // Levels clamped into range, with their yield stresses and currents.
  void write(const InverseTopology& topo, std::span<const std::uint32_t> valves) noexcept {
    double* tp = t.data();
    for (const std::uint32_t v : valves) {
      const double level = std::clamp(tp[v], topo.t_min, topo.t_max);
      tp[v] = level;
      const double ta = level * topo.inv_yield_k;
      tau[v] = ta;
      current[v] = topo.current_for_tau(ta * inv_gain[v]);
    }
  }
};

// One component of the partition as the solver sees it: views into ComponentPartition.
struct Component {
  std::size_t id = 0;
  std::uint32_t first_cell = 0;   // offset of its cells in the partition
  std::uint32_t first_valve = 0;  // ... of its valves
  std::span<const std::uint32_t> cells;
  std::span<const std::uint32_t> valves;
  const std::uint32_t* inc_begin = nullptr;  // per component valve, into inc_row / inc_slot
  const std::uint32_t* inc_row = nullptr;    // the row of each incident loaded cell
  const std::uint32_t* inc_slot = nullptr;   // its Jacobian slot
  const std::uint32_t* local_of = nullptr;   // valve -> index in its component
};

// The loaded cells' components (joined by shared valves) with their incidence: for each valve,
// the rows and Jacobian slots of its loaded cells. Rebuilt only when a cell starts or stops
// being loaded (inverse_solve.cpp).
struct ComponentPartition {
  explicit ComponentPartition(const ValveGraph& g);

  std::size_t count = 0;
  std::vector<std::uint32_t> cells;  // CSR by component
  std::vector<std::uint32_t> cell_begin;
  std::vector<std::uint32_t> valves;
  std::vector<std::uint32_t> valve_begin;
  std::vector<std::uint32_t> inc_begin;  // per component: (its valves + 1) offsets
  std::vector<std::uint32_t> inc_row;
  std::vector<std::uint32_t> inc_slot;
  std::vector<std::uint32_t> comp_of_cell;
  std::vector<std::int32_t> valve_comp;  // -1: no loaded cell uses the valve
  std::vector<std::uint32_t> row_of;     // cell -> row in its component
  std::vector<std::uint32_t> local_of;   // valve -> index in its component
  std::vector<std::uint64_t> visited;    // per cell: the rebuild that placed it
  std::uint64_t rebuilds = 0;

  std::vector<Component> components;  // the views of each, made by rebuild

  void rebuild(const ValveGraph& g, std::span<const unsigned char> loaded) noexcept;
};

// Per component, the last bounded step's factorisation with its Jacobian, bounds and rows:
// chord steps on later ticks reuse it. Reset with the partition.
struct ChordFactors {
  explicit ChordFactors(const ValveGraph& g)
      : offset(g.cells + 1, 0),
        pool(kDenseRows * g.cells, 0.0),
        age(g.cells, -1),
        search_after_s(g.cells, -std::numeric_limits<double>::infinity()),
        escape_next(g.cells, 0),
        escape_valves(g.cells * (kMaxEscapes / 2), 0),
        escape_count(g.cells, 0),
        search_stage(g.cells, 0),
        search_gained(g.cells, 0),
        inc_jac(g.valve_cells.size(), 0.0),
        bound(g.valves, 0),
        included(g.cells, 0) {}

  std::vector<std::uint32_t> offset;  // per component, into pool
  std::vector<double> pool;
  std::vector<int> age;                    // chord steps since it was made; -1: none valid
  std::vector<double> search_after_s;      // a non-converging warm solve searches again from then
  std::vector<std::uint32_t> escape_next;  // the escape trial the search's next tick starts with
  // Per component, the valves (indices into its valves) its escapes try, listed when the first
  // trial runs: later trials go down the same list, although the errors that chose it move.
  std::vector<std::uint32_t> escape_valves;  // kMaxEscapes / 2 a component
  std::vector<unsigned char> escape_count;
  std::vector<unsigned char> search_stage;   // kSearchIdle, kSearchRestart or kSearchEscapes
  std::vector<unsigned char> search_gained;  // this search's stages found better levels
  bool searching = false;                    // some component may have a search under way
  std::vector<double> inc_jac;
  std::vector<unsigned char> bound;
  std::vector<unsigned char> included;

  void reset(const ComponentPartition& part) noexcept {
    searching = false;
    for (std::size_t c = 0; c < part.count; ++c) {
      const std::uint32_t rows = part.cell_begin[c + 1] - part.cell_begin[c];
      offset[c + 1] = offset[c] + (rows <= kDenseRows ? rows * rows : 0);
      age[c] = -1;
      search_after_s[c] = -std::numeric_limits<double>::infinity();
      escape_next[c] = 0;
      escape_count[c] = 0;
      search_stage[c] = kSearchIdle;
      search_gained[c] = 0;
    }
  }
};

// ---- each tick -------------------------------------------------------------------------------

// What one call's inputs change: examine fills it, commit and the re-solve read it.
struct TickChanges {
  explicit TickChanges(std::size_t cells) : next_role(cells, CellRole::no_contact), solved(cells, 0) {
    changed_laws.reserve(cells);
    seen.reserve(cells);
    dirty.reserve(cells);
  }

  std::vector<CellRole> next_role;
  std::vector<std::uint32_t> changed_laws;
  std::vector<std::uint32_t> seen;  // cells whose inputs differ bitwise from the last call
  std::vector<std::uint32_t> dirty;
  std::vector<std::uint64_t> solved;  // per component: the re-solve that last solved it
  std::uint64_t resolves = 0;
  // The last solve (renew_at_rest() calls since keep it) succeeded and found every cell
  // untouched and at rest (no contact, no indentation, its law as cached): what
  // renew_at_rest() may stand on.
  bool all_untouched = false;
  // The last solve succeeded but examined some cell: whether it left every cell at rest is not
  // known until renew_at_rest() looks (once).
  bool rest_unscanned = false;
};

// The per-cell solutions and the report of the last call.
struct InverseOutput {
  explicit InverseOutput(std::size_t cell_count) : cells(cell_count) {}

  std::vector<CellSolution> cells;
  InverseReport rep;

  // A successful call's counters, before any work is counted (dirty: the cells it found dirty).
  void begin_report(std::size_t dirty) noexcept {
    rep.status = Status::ok;
    rep.error_cell = 0;
    rep.dirty_cells = dirty;
    rep.cell_updates = 0;
    rep.valve_updates = 0;
    rep.components_solved = 0;
    rep.iterations = 0;
  }
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
  // A tick with no cell changed that still solves a component (a search spread over ticks): the
  // report's counters, reset by the commit, count that work, and its verdicts are over the
  // components solved this tick, as on any tick.
  void reopen() noexcept {
    rep.from_cache = false;
    rep.converged = true;
    rep.residual_predicted = false;
  }
};

// The work of one component's solve, folded into the report at its end.
struct ComponentWork {
  bool converged = true;
  bool predicted = false;  // residuals are a tracked step's prediction
  std::size_t rows = 0;    // rows evaluated
  int iterations = 0;
};

// One component's Gauss-Newton (inverse_solve.cpp) and its rows and steps (inverse_step.cpp),
// with scratch preallocated for the largest component. Reads the topology and the cells'
// derivations; writes the component's levels, chord factors, its cells' residuals and warm-start
// flags (and their demands, on first use) and the report's work counters.
class InverseSolver {
 public:
  explicit InverseSolver(const ValveGraph& g);

  double now_s = 0.0;  // the tick's clock (CellInverse::solve's now_s): when a search may begin

  void solve(const InverseTopology& topo, const Component& comp, CellMemory& memory, ChordFactors& factors,
             ValveLevels& levels, InverseOutput& output) noexcept;

 private:
  std::vector<double> jac;  // per cell-valve slot: d e_i / d t_v
  std::vector<double> e;    // per row
  std::vector<double> aim_row;
  std::vector<unsigned char> one_sided;
  std::vector<unsigned char> included;
  std::vector<double> crow;                  // per row: the linear model's right-hand side
  std::vector<double> t0;                    // per component valve: level at the linearisation
  std::vector<double> t1;                    // proposal
  std::vector<double> tu;                    // unconstrained row-space value
  std::vector<unsigned char> bound;          // 0 free, 1 at t_min, 2 at t_max
  std::vector<unsigned char> bound_was;      // the pass before's
  std::vector<double> feasible;              // the active-set passes' feasible levels
  std::vector<double> rank_one;              // a valve's column over the rows
  std::vector<unsigned char> excluded_once;  // per row, within one step
  std::vector<double> predicted;             // per row: the linear model's residual after a step
  std::vector<double> mat;                   // kDenseRows^2
  std::vector<double> rhs;
  std::vector<double> dual;  // row-space solution
  std::vector<double> res;   // fallback residuals
  std::vector<double> best;  // per component valve: best levels found
  ComponentWork work;        // of the component being solved
  // The last Gauss-Newton stopped on its step cap (large_ or small_component_steps), not converged (set by
  // each; kept out of ComponentWork, whose reset every solve pays for).
  bool step_capped = false;
  void assemble_step_rhs(const InverseTopology& topo, const Component& comp, double keep) noexcept;
  bool update_factor(const Component& comp, std::size_t k, bool add) noexcept;

  bool demands_conflict(const InverseTopology& topo, const Component& comp, CellMemory& memory) noexcept;
  void solve_conflict(const InverseTopology& topo, const Component& comp, CellMemory& memory,
                      ChordFactors& factors, ValveLevels& levels, InverseOutput& output, bool warm) noexcept;
  bool track(const InverseTopology& topo, const Component& comp, const CellMemory& memory,
             ChordFactors& factors, ValveLevels& levels, bool& converged) noexcept;
  double restart_cold(const InverseTopology& topo, const Component& comp, CellMemory& memory,
                      ChordFactors& factors, ValveLevels& levels, double merit, bool& converged) noexcept;
  void plan_search(const Component& comp, ChordFactors& factors, bool warm) const noexcept;
  double search(const InverseTopology& topo, const Component& comp, CellMemory& memory, ChordFactors& factors,
                ValveLevels& levels, double merit, bool& converged) noexcept;
  double escape_stall(const InverseTopology& topo, const Component& comp, const CellMemory& memory,
                      ChordFactors& factors, ValveLevels& levels, double merit, bool& converged) noexcept;
  // A Gauss-Newton's role: the solve's own, or a search's trial (a cold restart, a stall escape),
  // which a small component's step cap allows kTrialStepsPerStep times the steps.
  enum class Run : unsigned char { solve, trial };
  // From the current levels, with the rows already evaluated there (merit: their merit).
  double gauss_newton(const InverseTopology& topo, const Component& comp, const CellMemory& memory,
                      ChordFactors& factors, ValveLevels& levels, double start_damping, bool& converged,
                      double merit, Run run, int max_steps = -1) noexcept;
  // What evaluate_rows fills: the residuals alone; also the Jacobian, linearised at the aim; or
  // also relinearised, where a flowing row far from its aim is linearised at its true pressure (a
  // forward solve) instead.
  enum class Rows : unsigned char { residuals, at_aim, relinearised };
  // Fills e (and jac) for the component's rows; returns the merit.
  double evaluate_rows(const InverseTopology& topo, const Component& comp, const CellMemory& memory,
                       const ValveLevels& levels, Rows rows = Rows::relinearised) noexcept;
  // t0 (+ rows) -> t1.
  void bounded_step(const InverseTopology& topo, const Component& comp, const ValveLevels& levels,
                    double damping, ChordFactors& factors) noexcept;
  void start_step(const InverseTopology& topo, const Component& comp, const ValveLevels& levels,
                  double shrink) noexcept;
  void assemble_step_system(const InverseTopology& topo, const Component& comp, double diag,
                            double keep) noexcept;
  void factorize_and_solve_step(std::size_t nr, double diag) noexcept;
  bool move_bounds(const InverseTopology& topo, const Component& comp, double keep, double eps) noexcept;
  void predict_step(const InverseTopology& topo, const Component& comp) noexcept;
  bool switch_one_sided_rows(double tol_Pa, std::size_t nr) noexcept;
  void save_factor(const Component& comp, ChordFactors& factors) noexcept;
  bool chord_step(const InverseTopology& topo, const Component& comp, const ValveLevels& levels,
                  ChordFactors& factors) noexcept;
  void fallback_step(const InverseTopology& topo, const Component& comp, const ValveLevels& levels,
                     double damping) noexcept;
};

}  // namespace mrskin::model::inverse_detail

namespace mrskin::model {

// The inverse's sources share these parts by name (only they include this header).
using namespace inverse_detail;

// One of each part; solve() runs them in order. Hidden: its functions are called directly (and
// inlined) within the library, never through the PLT.
struct __attribute__((visibility("hidden"))) CellInverse::Impl {
  Impl(const DeviceModel& model, const InverseOptions& options)
      : topo(model, options),
        memory(topo.graph.cells),
        levels(topo),
        partition(topo.graph),
        factors(topo.graph),
        changes(topo.graph.cells),
        solver(topo.graph),
        output(topo.graph.cells) {}

  const InverseTopology topo;
  CellMemory memory;
  ValveLevels levels;
  ComponentPartition partition;
  ChordFactors factors;
  TickChanges changes;
  InverseSolver solver;
  InverseOutput output;

  Status solve(std::span<const CellImpedanceTarget> targets, std::span<const CellState> states,
               double now_s) noexcept;
  bool renew_at_rest(double valid_until_s, double now_s) noexcept;
  void resolve_dirty(std::uint64_t pass) noexcept;
  bool continue_searches(std::uint64_t pass) noexcept;
  void solve_component(std::size_t c, std::uint64_t pass) noexcept;
};

}  // namespace mrskin::model
