// CellInverse: a component's rows (residuals and Jacobian) and its steps: bounded, chord, fallback.
#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include "inverse_impl.hpp"
#include "mrskin/driver/errors.hpp"

namespace mrskin::model {

double InverseSolver::evaluate_rows(const InverseTopology& topo, const Component& comp,
                                    const CellMemory& memory, const ValveLevels& levels, Rows rows) noexcept {
  const bool jacobian = rows != Rows::residuals;
  const bool relinearise = rows == Rows::relinearised;
  double merit = 0.0;
  work.rows += comp.cells.size();
  double* jac_p = jac.data();
  const double* t_p = levels.t.data();
  for (std::size_t r = 0; r < comp.cells.size(); ++r) {
    const std::uint32_t cell = comp.cells[r];
    const Derived& d = memory.cur(cell);
    const CellInfo& ci = topo.graph.info[cell];
    const Branch* bb = topo.graph.branches.data() + ci.branch_begin;
    const Branch* be = topo.graph.branches.data() + ci.branch_end;
    double* jc = jac_p + ci.valve_begin;
    const std::size_t nvc = ci.valve_end - ci.valve_begin;
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
                           std::fabs(flow) <= kLinearisationReach * cond * (d.aim_Pa + topo.tol_Pa))) {
        p = topo.forward(cell, d.flow_m3_per_s, [t_p](std::size_t v) { return t_p[v]; });
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
void InverseSolver::bounded_step(const InverseTopology& topo, const Component& comp,
                                 const ValveLevels& levels, double damping, ChordFactors& factors) noexcept {
  const double diag = damping + topo.opt.regularisation;
  const double shrink = topo.opt.regularisation / diag;
  const double keep = 1.0 - shrink;
  start_step(topo, comp, levels, shrink);
  const double eps = 1e-9 * topo.t_max;  // below this a change is round-off: clamp it
  const std::size_t nr = comp.cells.size();
  const std::size_t nv = comp.valves.size();
  // A pass that only binds or releases valves updates the factor by each valve's column (O(n^2)
  // each) instead of assembling and factorising again (O(n^3)); rows changing sides refactorise.
  bool factored = false;
  for (int pass = 0; pass < kMaxActiveSetPasses; ++pass) {
    if (!factored) {
      assemble_step_system(topo, comp, diag, keep);
      factorize_and_solve_step(nr, diag);
      factored = true;
    } else {
      assemble_step_rhs(topo, comp, keep);
      std::copy(rhs.data(), rhs.data() + nr, dual.data());
      cholesky_solve(mat.data(), nr, dual.data());
    }
    std::copy(bound.data(), bound.data() + nv, bound_was.data());
    bool changed = move_bounds(topo, comp, keep, eps);
    predict_step(topo, comp);
    const bool switched = switch_one_sided_rows(topo.tol_Pa, comp.cells.size());
    changed = changed || switched;
    if (!changed) {
      save_factor(comp, factors);
      break;
    }
    factors.age[comp.id] = -1;  // the last factorisation is not the final active set's
    if (switched) {
      factored = false;
      continue;
    }
    for (std::size_t k = 0; k < nv && factored; ++k) {
      if ((bound[k] == 0) != (bound_was[k] == 0)) {
        factored = update_factor(comp, k, bound[k] == 0);
      }
    }
  }
  for (std::size_t r = 0; r < comp.cells.size(); ++r) {
    excluded_once[r] = 0;
  }
}

// The step's right-hand side and the active set it starts from.
void InverseSolver::start_step(const InverseTopology& topo, const Component& comp, const ValveLevels& levels,
                               double shrink) noexcept {
  const double* const t = levels.t.data();
  const std::size_t nr = comp.cells.size();
  const std::size_t nv = comp.valves.size();
  const double* jac_p = jac.data();
  // Each valve's column is its incidence list (1-4 loaded cells): every product below is
  // sparse, O(incidences), never rows x valves.
  for (std::size_t r = 0; r < nr; ++r) {
    crow[r] = -e[r];
    included[r] = one_sided[r] == 0 || e[r] < 0.0 ? 1 : 0;
  }
  // Start from the bounds the levels sit on (the active set rarely changes between steps).
  for (std::size_t k = 0; k < nv; ++k) {
    const double tv = t[comp.valves[k]];
    t0[k] = tv;
    feasible[k] = tv;  // a bound valve's is set when it is released
    bound[k] = tv <= topo.t_min ? 1 : (tv >= topo.t_max ? 2 : 0);
    const double st = shrink * tv;
    for (std::uint32_t j = comp.inc_begin[k]; j < comp.inc_begin[k + 1]; ++j) {
      crow[comp.inc_row[j]] += jac_p[comp.inc_slot[j]] * st;
    }
  }
}

// The row-space system of one active-set pass (mat, rhs).
void InverseSolver::assemble_step_system(const InverseTopology& topo, const Component& comp, double diag,
                                         double keep) noexcept {
  const std::size_t nr = comp.cells.size();
  const std::size_t nv = comp.valves.size();
  const double* jac_p = jac.data();
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
    const std::uint32_t lo = comp.inc_begin[k];
    const std::uint32_t hi = comp.inc_begin[k + 1];
    if (bound[k] != 0) {
      const double tb = (bound[k] == 1 ? topo.t_min : topo.t_max) - keep * t0[k];
      for (std::uint32_t j = lo; j < hi; ++j) {
        rhs[comp.inc_row[j]] -= included[comp.inc_row[j]] != 0 ? jac_p[comp.inc_slot[j]] * tb : 0.0;
      }
      continue;
    }
    for (std::uint32_t j1 = lo; j1 < hi; ++j1) {
      const std::uint32_t a = comp.inc_row[j1];
      if (included[a] == 0) {
        continue;
      }
      const double ja = jac_p[comp.inc_slot[j1]];
      double* ma = &mat[a * nr];
      for (std::uint32_t j2 = lo; j2 < hi; ++j2) {
        const std::uint32_t b = comp.inc_row[j2];
        ma[b] += included[b] != 0 ? ja * jac_p[comp.inc_slot[j2]] : 0.0;
      }
    }
  }
}

// The right-hand side alone (the matrix kept: its factor is updated valve by valve).
void InverseSolver::assemble_step_rhs(const InverseTopology& topo, const Component& comp,
                                      double keep) noexcept {
  const std::size_t nr = comp.cells.size();
  const std::size_t nv = comp.valves.size();
  const double* jac_p = jac.data();
  for (std::size_t a = 0; a < nr; ++a) {
    rhs[a] = included[a] != 0 ? crow[a] : 0.0;
  }
  for (std::size_t k = 0; k < nv; ++k) {
    if (bound[k] == 0) {
      continue;
    }
    const double tb = (bound[k] == 1 ? topo.t_min : topo.t_max) - keep * t0[k];
    for (std::uint32_t j = comp.inc_begin[k]; j < comp.inc_begin[k + 1]; ++j) {
      rhs[comp.inc_row[j]] -= included[comp.inc_row[j]] != 0 ? jac_p[comp.inc_slot[j]] * tb : 0.0;
    }
  }
}

// The factor of M +- v v^T (v: valve k's column over the included rows); false when a downdate
// would lose definiteness (the caller refactorises).
bool InverseSolver::update_factor(const Component& comp, std::size_t k, bool add) noexcept {
  const std::size_t nr = comp.cells.size();
  double* x = rank_one.data();
  std::fill(x, x + nr, 0.0);
  std::size_t first = nr;
  for (std::uint32_t j = comp.inc_begin[k]; j < comp.inc_begin[k + 1]; ++j) {
    const std::uint32_t r = comp.inc_row[j];
    if (included[r] != 0) {
      x[r] += jac[comp.inc_slot[j]];
      first = std::min<std::size_t>(first, r);
    }
  }
  const double sign = add ? 1.0 : -1.0;
  double* l = mat.data();
  for (std::size_t c = first; c < nr; ++c) {
    double* lc = l + c * nr;
    const double lcc = lc[c];
    const double r2 = lcc * lcc + sign * x[c] * x[c];
    if (!(r2 > 1e-12 * lcc * lcc)) {
      return false;
    }
    const double r = std::sqrt(r2);
    const double cs = r / lcc;
    const double sn = x[c] / lcc;
    lc[c] = r;
    for (std::size_t i = c + 1; i < nr; ++i) {
      double* li = l + i * nr;
      li[c] = (li[c] + sign * sn * x[i]) / cs;
      x[i] = cs * x[i] - sn * li[c];
    }
  }
  return true;
}

// Cholesky (lower, in place) and the two triangular solves into dual.
void InverseSolver::factorize_and_solve_step(std::size_t nr, double diag) noexcept {
  // The damping keeps it definite.
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
}

// The unconstrained levels (tu) and the bound changes they call for; true when the set changed.
// A primal active set: the passes keep feasible levels (feasible) and move it towards tu only as
// far as the first bound a free valve meets, which binds that valve alone. Binding every valve tu
// leaves outside at once overshot: on the 5x5's full press a step bound 7 valves, released them
// one a pass, and bound 5 again (19 passes). The optimum is the same (the step's problem is
// strictly convex in the levels), reached in fewer passes.
bool InverseSolver::move_bounds(const InverseTopology& topo, const Component& comp, double keep,
                                double eps) noexcept {
  const std::size_t nv = comp.valves.size();
  const double* jac_p = jac.data();
  double most = eps;
  std::size_t release = nv;
  double reach = 1.0;  // of the way from feasible to tu before a free valve meets a bound
  for (std::size_t k = 0; k < nv; ++k) {
    double u = keep * t0[k];
    for (std::uint32_t j = comp.inc_begin[k]; j < comp.inc_begin[k + 1]; ++j) {
      u += jac_p[comp.inc_slot[j]] * dual[comp.inc_row[j]];
    }
    tu[k] = u;
    if (bound[k] == 0) {
      if (u < topo.t_min - eps) {
        reach = std::min(reach, (feasible[k] - topo.t_min) / (feasible[k] - u));
      } else if (u > topo.t_max + eps) {
        reach = std::min(reach, (topo.t_max - feasible[k]) / (u - feasible[k]));
      }
    } else {
      const double inside = bound[k] == 1 ? u - topo.t_min : topo.t_max - u;
      if (inside > most) {
        most = inside;
        release = k;
      }
    }
  }
  if (reach < 1.0) {
    // Move to where the first bound is met; the valves that meet it there are bound.
    const double meets = reach + 1e-12;
    for (std::size_t k = 0; k < nv; ++k) {
      if (bound[k] != 0) {
        continue;
      }
      const double u = tu[k];
      if (u < topo.t_min - eps && (feasible[k] - topo.t_min) <= meets * (feasible[k] - u)) {
        bound[k] = 1;
        feasible[k] = topo.t_min;
      } else if (u > topo.t_max + eps && (topo.t_max - feasible[k]) <= meets * (u - feasible[k])) {
        bound[k] = 2;
        feasible[k] = topo.t_max;
      } else {
        feasible[k] = std::clamp(feasible[k] + reach * (u - feasible[k]), topo.t_min, topo.t_max);
      }
    }
    return true;
  }
  // Release the bound valve whose gradient points inside most (one a pass: releasing all at once
  // makes coupled valves cycle); the free valves reached their levels. A final pass leaves them
  // (no pass reads them after it).
  if (release == nv) {
    return false;
  }
  for (std::size_t k = 0; k < nv; ++k) {
    if (bound[k] == 0) {
      feasible[k] = std::clamp(tu[k], topo.t_min, topo.t_max);
    }
  }
  feasible[release] = bound[release] == 1 ? topo.t_min : topo.t_max;
  bound[release] = 0;
  return true;
}

// The proposal t1 within the bounds, and the linear model's residuals after it (predicted).
void InverseSolver::predict_step(const InverseTopology& topo, const Component& comp) noexcept {
  const std::size_t nr = comp.cells.size();
  const std::size_t nv = comp.valves.size();
  const double* jac_p = jac.data();
  for (std::size_t r = 0; r < nr; ++r) {
    predicted[r] = e[r];
  }
  for (std::size_t k = 0; k < nv; ++k) {
    const double tk =
        bound[k] == 0 ? std::clamp(tu[k], topo.t_min, topo.t_max) : (bound[k] == 1 ? topo.t_min : topo.t_max);
    t1[k] = tk;
    const double dk = tk - t0[k];
    for (std::uint32_t j = comp.inc_begin[k]; j < comp.inc_begin[k + 1]; ++j) {
      predicted[comp.inc_row[j]] += jac_p[comp.inc_slot[j]] * dk;
    }
  }
}

// True when a one-sided row changed sides.
bool InverseSolver::switch_one_sided_rows(double tol_Pa, std::size_t nr) noexcept {
  bool changed = false;
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
  return changed;
}

// Keeps the final factorisation of a bounded step with its Jacobian, bounds and rows, for the
// chord steps of the next ticks.
void InverseSolver::save_factor(const Component& comp, ChordFactors& factors) noexcept {
  const std::size_t nr = comp.cells.size();
  const std::size_t nv = comp.valves.size();
  double* f = factors.pool.data() + factors.offset[comp.id];
  std::copy(mat.data(), mat.data() + nr * nr, f);
  const std::uint32_t first = comp.inc_begin[0];
  for (std::uint32_t j = first; j < comp.inc_begin[nv]; ++j) {
    factors.inc_jac[j] = jac[comp.inc_slot[j]];
  }
  unsigned char* pb = factors.bound.data() + comp.first_valve;
  for (std::size_t k = 0; k < nv; ++k) {
    pb[k] = bound[k];
  }
  unsigned char* pi = factors.included.data() + comp.first_cell;
  for (std::size_t r = 0; r < nr; ++r) {
    pi[r] = included[r] == 1 || included[r] == 3 ? 1 : 0;
  }
  factors.age[comp.id] = 0;
}

// A chord step: the saved factorisation and Jacobian with this tick's residuals. Returns false
// (nothing changed) when the saved active set no longer holds, so that the caller refactorises.
bool InverseSolver::chord_step(const InverseTopology& topo, const Component& comp, const ValveLevels& levels,
                               ChordFactors& factors) noexcept {
  // Pure damped step (the ridge's pull is left to the refactorising steps): bound valves stay
  // on their bound, z = M^-1 (-e), free valves move by J^T z.
  const std::size_t nr = comp.cells.size();
  const std::size_t nv = comp.valves.size();
  const double* f = factors.pool.data() + factors.offset[comp.id];
  const double* ij = factors.inc_jac.data();
  const unsigned char* pb = factors.bound.data() + comp.first_valve;
  const unsigned char* pi = factors.included.data() + comp.first_cell;
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
  const double* tp = levels.t.data();
  const std::uint32_t* vp = comp.valves.data();
  const double eps = 1e-9 * topo.t_max;
  for (std::size_t k = 0; k < nv; ++k) {
    const double tk = tp[vp[k]];
    const std::uint32_t lo = comp.inc_begin[k];
    const std::uint32_t hi = comp.inc_begin[k + 1];
    double u = tk;
    for (std::uint32_t j = lo; j < hi; ++j) {
      u += ij[j] * dual[comp.inc_row[j]];
    }
    if (pb[k] != 0) {
      // A bound valve the step would pull inside: the active set changed, refactorise.
      if ((pb[k] == 1 && u > topo.t_min + eps) || (pb[k] == 2 && u < topo.t_max - eps)) {
        factors.age[comp.id] = -1;
        return false;
      }
      t1[k] = tk;
      continue;
    }
    clamped = clamped || u < topo.t_min || u > topo.t_max;
    u = std::clamp(u, topo.t_min, topo.t_max);
    t1[k] = u;
    const double dk = u - tk;
    for (std::uint32_t j = lo; j < hi; ++j) {
      predicted[comp.inc_row[j]] += ij[j] * dk;
    }
  }
  // A valve reached a bound: its step is clamped; refactorise next time.
  factors.age[comp.id] = clamped ? -1 : factors.age[comp.id] + 1;
  return true;
}

// Large components: projected Gauss-Seidel on the same linearised problem (sparse, O(nnz) a sweep).
void InverseSolver::fallback_step(const InverseTopology& topo, const Component& comp,
                                  const ValveLevels& levels, double damping) noexcept {
  const double* const t = levels.t.data();
  const std::size_t nr = comp.cells.size();
  const std::size_t nv = comp.valves.size();
  for (std::size_t r = 0; r < nr; ++r) {
    res[r] = e[r];
    included[r] = one_sided[r] == 0 || e[r] < 0.0 ? 1 : 0;
  }
  for (std::size_t k = 0; k < nv; ++k) {
    t1[k] = t[comp.valves[k]];
  }
  const double lambda = topo.opt.regularisation;
  // Stop sweeping once no valve moves its rows by more than a tenth of the tolerance: a small
  // patch settles in a few sweeps, so its cost follows its size, not the sweep cap.
  const double settled_Pa = 0.1 * topo.tol_Pa;
  for (int sweep = 0; sweep < kFallbackSweeps; ++sweep) {
    double moved_Pa = 0.0;
    for (std::size_t k = 0; k < nv; ++k) {
      double a = lambda + damping;
      double g = lambda * t1[k] + damping * (t1[k] - t0[k]);
      for (std::uint32_t j = comp.inc_begin[k]; j < comp.inc_begin[k + 1]; ++j) {
        const std::uint32_t r = comp.inc_row[j];
        const double jv = jac[comp.inc_slot[j]];
        if (included[r] != 0 || res[r] < 0.0) {
          a += jv * jv;
          g += jv * res[r];
        }
      }
      const double next_t = std::clamp(t1[k] - g / a, topo.t_min, topo.t_max);
      const double delta = next_t - t1[k];
      if (delta == 0.0) {
        continue;
      }
      t1[k] = next_t;
      moved_Pa = std::max(moved_Pa, std::fabs(delta) * std::sqrt(a));
      for (std::uint32_t j = comp.inc_begin[k]; j < comp.inc_begin[k + 1]; ++j) {
        res[comp.inc_row[j]] += jac[comp.inc_slot[j]] * delta;
      }
    }
    if (moved_Pa <= settled_Pa) {
      break;
    }
  }
}

}  // namespace mrskin::model
