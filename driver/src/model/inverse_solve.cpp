// CellInverse: each tick's solve, the partition of the loaded cells into components, and a
// component's Gauss-Newton.
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
  if (const Status st = examine(targets, states, now_s); st != Status::ok) {
    return st;
  }
  if (commit(targets, states, now_s)) {
    resolve_dirty();
    summarise();
  }
  return Status::ok;
}

// Pass 1: validates everything and works out what changed (dirty cells derived into their spare
// slot); nothing cached is touched, so a failure leaves the last solve standing.
Status CellInverse::Impl::examine(std::span<const CellImpedanceTarget> targets,
                                  std::span<const CellState> states, double now_s) noexcept {
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
  return Status::ok;
}

// Pass 2: commits the inputs and the dirty cells' derivations; false when nothing is dirty (the
// cached currents stand).
bool CellInverse::Impl::commit(std::span<const CellImpedanceTarget> targets,
                               std::span<const CellState> states, double now_s) noexcept {
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
    return false;
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
  return true;
}

// Re-solves every component that holds a dirty cell or one of its valves; releases the valves of
// dirty cells that no loaded cell needs.
void CellInverse::Impl::resolve_dirty() noexcept {
  if (roles_changed) {
    rebuild_partition();
    roles_changed = false;
  }
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
}

// The report's summary over the loaded cells.
void CellInverse::Impl::summarise() noexcept {
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
  select_component(comp);
  // Each valve takes the largest uniform demand of its loaded cells: exact when no cell has a
  // valve raised above its own demand. Otherwise Gauss-Newton, warm-started from the last solve
  // when every cell of the component was solved that way then.
  bool warm = true;
  for (const std::uint32_t cell : comp_cells) {
    warm = warm && cache[cell].gn_last;
  }
  const bool conflict = warm || demands_conflict();  // a warm component keeps tracking
  if (!conflict || !warm) {
    for (std::size_t k = 0; k < comp_valves.size(); ++k) {
      t[comp_valves[k]] = t1[k];
    }
  }
  for (const std::uint32_t cell : comp_cells) {
    out[cell].residual_N = 0.0;
  }
  if (conflict) {
    solve_conflict(warm);
  }
  for (const std::uint32_t cell : comp_cells) {
    cache[cell].gn_last = conflict;
  }
  write_valves();
}

void CellInverse::Impl::select_component(std::size_t comp) noexcept {
  comp_id = comp;
  comp_cells = std::span<const std::uint32_t>(part_cells.data() + part_cell_begin[comp],
                                              part_cell_begin[comp + 1] - part_cell_begin[comp]);
  comp_valves = std::span<const std::uint32_t>(part_valves.data() + part_valve_begin[comp],
                                               part_valve_begin[comp + 1] - part_valve_begin[comp]);
  inc_begin = part_inc_begin.data() + part_valve_begin[comp] + comp;
  ++rep.components_solved;
}

double CellInverse::Impl::max_demand(std::size_t k) noexcept {
  double level = t_min;
  for (std::uint32_t j = inc_begin[k]; j < inc_begin[k + 1]; ++j) {
    level = std::max(level, demand_of(comp_cells[inc_row[j]]));
  }
  return level;
}

// Every valve at its cells' largest demand (into t1): true when some cell then renders too much.
// A flowing cell with any valve raised does; a holding cell only when every valve is raised (its
// weakest branch sets its pressure).
bool CellInverse::Impl::demands_conflict() noexcept {
  for (std::size_t k = 0; k < comp_valves.size(); ++k) {
    t1[k] = max_demand(k);
  }
  bool conflict = false;
  for (const std::uint32_t cell : comp_cells) {
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
  return conflict;
}

// Gauss-Newton on a component whose demands conflict: tracking when warm and near, else the full
// solve, a cold restart when the warm one leads nowhere, and escapes from a symmetric stall.
void CellInverse::Impl::solve_conflict(bool warm) noexcept {
  bool converged = false;
  bool tracked = false;
  // Warm: residuals only first (a chord step reuses the saved Jacobian).
  double merit = evaluate_rows(!warm, !warm);
  if (warm && comp_cells.size() <= kDenseRows) {
    tracked = track(converged);
  }
  if (!tracked) {
    if (warm) {
      merit = evaluate_rows();  // far from the aim: relinearise where needed
    }
    merit = gauss_newton(warm ? kMinDamping : kStartDamping, converged, merit);
    if (!converged && warm) {
      merit = restart_cold(merit, converged);
      warm = false;  // and the escapes below if still short
    }
  }
  if (!converged && !warm) {
    escape_stall(merit, converged);
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

// Tracking: the last solve's levels with this tick's targets. A small error takes one damped
// step, unverified: its residuals are the linear model's prediction, and the next tick's rows
// check it. False when the error is too large to track.
bool CellInverse::Impl::track(bool& converged) noexcept {
  double worst = 0.0;
  bool near = true;
  for (std::size_t r = 0; r < comp_cells.size(); ++r) {
    const double er = one_sided[r] != 0 && e[r] > 0.0 ? 0.0 : std::fabs(e[r]);
    worst = std::max(worst, er);
    near = near && er <= kTrackReach * (aim_row[r] + tol_Pa);
  }
  if (worst <= tol_Pa) {
    converged = true;
    return true;
  }
  if (!near) {
    return false;
  }
  damping = kMinDamping;
  // A small correction reuses the last factorisation (a chord step: J frozen); a larger one, an
  // old factor or a changed active set refactorises.
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
  rep.residual_predicted = true;
  return true;
}

// The last solve's levels led nowhere (e.g. a press turned into a hold, where the weakest valve
// rules): starts again from the demands, as a cold solve would, and keeps the better of the two.
double CellInverse::Impl::restart_cold(double merit, bool& converged) noexcept {
  for (std::size_t k = 0; k < comp_valves.size(); ++k) {
    const double level = max_demand(k);
    best[k] = t[comp_valves[k]];
    t[comp_valves[k]] = level;
  }
  bool cold_converged = false;
  const double cold = gauss_newton(kStartDamping, cold_converged, evaluate_rows());
  if (cold < merit) {
    converged = cold_converged;
    return cold;
  }
  for (std::size_t k = 0; k < comp_valves.size(); ++k) {
    t[comp_valves[k]] = best[k];
  }
  return evaluate_rows();
}

// A cold start can stall where two cells pull a shared valve both ways and symmetry keeps the
// valves together (e.g. a corner cell that must flow through one of its two valves while its
// neighbour needs both high). Tries opening or shutting each such valve.
void CellInverse::Impl::escape_stall(double merit, bool& converged) noexcept {
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

}  // namespace mrskin::model
