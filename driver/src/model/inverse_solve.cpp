// CellInverse: each tick's solve (examine the inputs, commit them, re-solve the components they
// touch), the partition of the loaded cells into components, and a component's Gauss-Newton.
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

Status InverseTopology::derive(std::size_t cell, const CellImpedanceTarget& g, const CellState& s,
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
  const CellInfo& ci = graph.info[cell];
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
  if (!std::isfinite(o.force_min_N) || !std::isfinite(o.force_max_N) || !std::isfinite(requested)) {
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

namespace {

struct Verdict {
  Status status = Status::ok;
  std::size_t cell = 0;
};

// Pass 1: validates everything and works out what changed (dirty cells derived into their spare
// slot); nothing else cached is touched, so a failure leaves the last solve standing.
Verdict examine(const InverseTopology& topo, CellMemory& memory, TickChanges& changes,
                std::span<const CellImpedanceTarget> targets, std::span<const CellState> states,
                double now_s) noexcept {
  const InverseOptions& opt = topo.opt;
  changes.dirty.clear();
  changes.changed_laws.clear();
  changes.seen.clear();
  bool all_untouched = true;
  for (std::size_t i = 0; i < topo.graph.cells; ++i) {
    const CellState& s = states[i];
    const CellImpedanceTarget& g = targets[i];
    const CellCache& cc = memory.cache[i];
    const bool expired = now_s > g.valid_until_s;
    // An untouched cell whose law only moved its validity time (a stream sample every tick)
    // stays untouched: without indentation the clock cannot change its role. Tested first, as most
    // cells of a large grid are untouched; its cached raw inputs stay as they were (they are only
    // ever compared).
    if (cc.valid && cc.role == CellRole::no_contact && !(s.indentation_m > 0.0) &&
        same_bits(s, cc.raw_state) && same_law(g, cc.target) && std::isfinite(g.valid_until_s)) {
      continue;
    }
    all_untouched = false;
    // Inputs bitwise as last time (validated then): only the clock can change the role.
    if (cc.valid && same_bits(g, cc.raw_target) && same_bits(s, cc.raw_state) && expired == cc.expired) {
      continue;
    }
    changes.seen.push_back(static_cast<std::uint32_t>(i));
    if (const Status st = check_state(s, topo.depth_m); st != Status::ok) {
      return {st, i};
    }
    const bool changed = !cc.valid || !same_law(g, cc.target);
    if (changed) {
      if (const Status st = check_target(g); st != Status::ok) {
        return {st, i};
      }
    } else if (!std::isfinite(g.valid_until_s)) {
      return {Status::not_finite, i};
    }
    if (changed) {
      changes.changed_laws.push_back(static_cast<std::uint32_t>(i));
    }
    const CellRole role = classify(s, expired, opt.hold_rate_tolerance_m_per_s);
    changes.next_role[i] = role;
    bool is_dirty = !cc.valid || role != cc.role;
    if (is_loaded(role) && !is_dirty) {
      is_dirty = changed ||
                 std::fabs(s.indentation_m - cc.state.indentation_m) > opt.indentation_tolerance_m ||
                 std::fabs(s.rate_m_per_s - cc.state.rate_m_per_s) > opt.rate_tolerance_m_per_s;
    }
    if (is_dirty) {
      if (const Status st = topo.derive(i, g, s, role, memory.cur(i), memory.spare(i)); st != Status::ok) {
        return {st, i};
      }
      changes.dirty.push_back(static_cast<std::uint32_t>(i));
    }
  }
  changes.all_untouched = all_untouched;
  return {};
}

enum class Committed { nothing, cells, roles };  // roles: a cell started or stopped being loaded

// Pass 2: commits the inputs and the dirty cells' derivations; nothing when no cell is dirty (the
// cached currents stand).
Committed commit(const TickChanges& changes, CellMemory& memory, InverseOutput& output,
                 std::span<const CellImpedanceTarget> targets, std::span<const CellState> states,
                 double now_s) noexcept {
  InverseReport& rep = output.rep;
  output.begin_report(changes.dirty.size());
  for (const std::uint32_t i : changes.changed_laws) {
    memory.cache[i].target = targets[i];
  }
  for (const std::uint32_t i : changes.seen) {
    CellCache& cc = memory.cache[i];
    cc.raw_target = targets[i];
    cc.raw_state = states[i];
    cc.expired = now_s > targets[i].valid_until_s;
  }
  if (changes.dirty.empty()) {
    rep.from_cache = true;
    return Committed::nothing;
  }
  rep.from_cache = false;
  rep.converged = true;
  rep.residual_predicted = false;
  bool roles_changed = false;
  for (const std::uint32_t i : changes.dirty) {
    CellCache& cc = memory.cache[i];
    cc.state = states[i];  // (the target was committed above if it changed)
    cc.valid = true;
    cc.role = changes.next_role[i];
    const unsigned char now_loaded = is_loaded(cc.role) ? 1 : 0;
    roles_changed = roles_changed || now_loaded != memory.loaded[i];
    memory.loaded[i] = now_loaded;
    cc.sel = static_cast<unsigned char>(1 - cc.sel);  // the slot derived in pass 1 becomes current
    output.cells[i] = memory.cur(i).out;
    ++rep.cell_updates;
  }
  return roles_changed ? Committed::roles : Committed::cells;
}

// The report's summary over the loaded cells.
void summarise(std::span<const std::uint32_t> loaded, InverseOutput& output) noexcept {
  InverseReport& rep = output.rep;
  rep.loaded_cells = loaded.size();
  rep.clamped_cells = 0;
  double sum2 = 0.0;
  double worst = 0.0;
  for (const std::uint32_t i : loaded) {
    const CellSolution& o = output.cells[i];
    rep.clamped_cells += (o.clamped_low || o.clamped_high) ? 1 : 0;
    sum2 += o.residual_N * o.residual_N;
    worst = std::max(worst, std::fabs(o.residual_N));
  }
  rep.residual_norm_N = std::sqrt(sum2);
  rep.max_residual_N = worst;
}

// The largest demand of component valve k's cells.
double max_demand(const InverseTopology& topo, const Component& comp, CellMemory& memory,
                  std::size_t k) noexcept {
  double level = topo.t_min;
  for (std::uint32_t j = comp.inc_begin[k]; j < comp.inc_begin[k + 1]; ++j) {
    level = std::max(level, memory.demand_of(topo, comp.cells[comp.inc_row[j]]));
  }
  return level;
}

}  // namespace

Status CellInverse::Impl::solve(std::span<const CellImpedanceTarget> targets,
                                std::span<const CellState> states, double now_s) noexcept {
  changes.all_untouched = false;  // until examine finds it so
  changes.rest_unscanned = false;
  if (targets.size() != topo.graph.cells || states.size() != topo.graph.cells) {
    return output.fail(Status::out_of_range, 0);
  }
  if (!std::isfinite(now_s)) {
    return output.fail(Status::not_finite, 0);
  }
  if (const Verdict v = examine(topo, memory, changes, targets, states, now_s); v.status != Status::ok) {
    return output.fail(v.status, v.cell);
  }
  const Committed committed = commit(changes, memory, output, targets, states, now_s);
  changes.rest_unscanned = !changes.all_untouched;
  if (committed == Committed::roles) {
    partition.rebuild(topo.graph, memory.loaded);
    factors.reset(partition);
    memory.roles_rebuilt();
  }
  const std::uint64_t pass = ++changes.resolves;
  solver.now_s = now_s;
  if (committed != Committed::nothing) {
    resolve_dirty(pass);
  }
  // (The flag is tested here: most ticks have no search under way and pay no call.)
  const bool searched = factors.searching && continue_searches(pass);
  if (!searched && committed == Committed::nothing) {
    return Status::ok;  // the cached currents stand
  }
  summarise(memory.loaded_list, output);
  return Status::ok;
}

// What solve() does when examine would find every cell untouched, without examining them: the
// last solve left every cell at rest, the caller vouches that only the validity moved since, and
// an untouched cell's role does not depend on it. No cell is loaded, so no search is under way;
// the flag is tested all the same.
bool CellInverse::Impl::renew_at_rest(double valid_until_s, double now_s) noexcept {
  if (factors.searching || !std::isfinite(valid_until_s) || !std::isfinite(now_s)) {
    return false;
  }
  if (!changes.all_untouched) {
    if (!changes.rest_unscanned) {
      return false;
    }
    // The last solve examined some cell (the first call, a release): if it left every cell at
    // rest, the same inputs would now find each untouched. Once, not on every examined call.
    changes.rest_unscanned = false;
    for (const CellCache& cc : memory.cache) {
      if (!cc.valid || cc.role != CellRole::no_contact || cc.raw_state.indentation_m > 0.0) {
        return false;
      }
    }
    changes.all_untouched = true;
  }
  ++changes.resolves;
  solver.now_s = now_s;
  output.begin_report(0);
  output.rep.from_cache = true;
  return true;
}

inline void CellInverse::Impl::solve_component(std::size_t c, std::uint64_t pass) noexcept {
  changes.solved[c] = pass;
  const Component& comp = partition.components[c];
  ++output.rep.components_solved;
  solver.solve(topo, comp, memory, factors, levels, output);
  levels.write(topo, comp.valves);
  output.rep.valve_updates += comp.valves.size();
}

// A search spread over ticks (InverseSolver::search) goes on whether or not its inputs changed:
// held still, a compromise would otherwise keep the levels of a stalled start. True when it
// solved some component.
bool CellInverse::Impl::continue_searches(std::uint64_t pass) noexcept {
  bool any = false;
  bool left = false;
  for (std::size_t c = 0; c < partition.count; ++c) {
    if (factors.search_stage[c] != kSearchIdle && changes.solved[c] != pass) {
      if (!any && output.rep.from_cache) {
        output.reopen();
      }
      any = true;
      solve_component(c, pass);
    }
    left = left || factors.search_stage[c] != kSearchIdle;
  }
  factors.searching = left;
  return any;
}

// Re-solves every component that holds a dirty cell or one of its valves; releases the valves of
// dirty cells that no loaded cell needs.
void CellInverse::Impl::resolve_dirty(std::uint64_t pass) noexcept {
  InverseReport& rep = output.rep;
  // The pass check stays out of the call: most dirty cells share a component already solved.
  for (const std::uint32_t i : changes.dirty) {
    if (memory.loaded[i] != 0) {
      if (const std::uint32_t c = partition.comp_of_cell[i]; changes.solved[c] != pass) {
        solve_component(c, pass);
      }
      continue;
    }
    const CellInfo& ci = topo.graph.info[i];
    for (std::uint32_t k = ci.valve_begin; k < ci.valve_end; ++k) {
      const std::uint32_t v = topo.graph.cell_valves[k];
      const std::int32_t c = partition.valve_comp[v];
      if (c < 0) {
        rep.valve_updates += levels.release(topo, v) ? 1 : 0;
      } else if (changes.solved[static_cast<std::size_t>(c)] != pass) {
        solve_component(static_cast<std::size_t>(c), pass);
      }
    }
  }
}

void ComponentPartition::rebuild(const ValveGraph& g, std::span<const unsigned char> loaded) noexcept {
  const std::uint64_t stamp = ++rebuilds;
  std::size_t nc = 0;
  std::uint32_t ncell = 0;
  std::uint32_t nval = 0;
  std::uint32_t ninc = 0;
  std::uint32_t nbeg = 0;
  cell_begin[0] = 0;
  valve_begin[0] = 0;
  for (std::size_t v = 0; v < g.valves; ++v) {
    valve_comp[v] = -1;
  }
  for (std::size_t seed = 0; seed < g.cells; ++seed) {
    if (loaded[seed] == 0 || visited[seed] == stamp) {
      continue;
    }
    const std::uint32_t first_cell = ncell;
    visited[seed] = stamp;
    row_of[seed] = 0;
    comp_of_cell[seed] = static_cast<std::uint32_t>(nc);
    cells[ncell++] = static_cast<std::uint32_t>(seed);
    const std::uint32_t first_valve = nval;
    inc_begin[nbeg++] = ninc;
    for (std::uint32_t head = first_cell; head < ncell; ++head) {
      const CellInfo& ci = g.info[cells[head]];
      for (std::uint32_t k = ci.valve_begin; k < ci.valve_end; ++k) {
        const std::uint32_t v = g.cell_valves[k];
        if (valve_comp[v] >= 0) {
          continue;
        }
        valve_comp[v] = static_cast<std::int32_t>(nc);
        local_of[v] = nval - first_valve;
        valves[nval++] = v;
        for (std::uint32_t j = g.valve_cell_begin[v]; j < g.valve_cell_begin[v + 1]; ++j) {
          const std::uint32_t other = g.valve_cells[j];
          if (loaded[other] == 0) {
            continue;
          }
          if (visited[other] != stamp) {
            visited[other] = stamp;
            row_of[other] = ncell - first_cell;
            comp_of_cell[other] = static_cast<std::uint32_t>(nc);
            cells[ncell++] = other;
          }
          inc_row[ninc] = row_of[other];
          inc_slot[ninc] = g.valve_cell_slot[j];
          ++ninc;
        }
        inc_begin[nbeg++] = ninc;
      }
    }
    ++nc;
    cell_begin[nc] = ncell;
    valve_begin[nc] = nval;
  }
  count = nc;
  for (std::size_t c = 0; c < count; ++c) {
    Component& k = components[c];
    k.id = c;
    k.first_cell = cell_begin[c];
    k.first_valve = valve_begin[c];
    k.cells = std::span<const std::uint32_t>(cells.data() + cell_begin[c], cell_begin[c + 1] - cell_begin[c]);
    k.valves =
        std::span<const std::uint32_t>(valves.data() + valve_begin[c], valve_begin[c + 1] - valve_begin[c]);
    k.inc_begin = inc_begin.data() + valve_begin[c] + c;
    k.inc_row = inc_row.data();
    k.inc_slot = inc_slot.data();
    k.local_of = local_of.data();
  }
}

void InverseSolver::solve(const InverseTopology& topo, const Component& comp, CellMemory& memory,
                          ChordFactors& factors, ValveLevels& levels, InverseOutput& output) noexcept {
  double* const t = levels.t.data();
  work = ComponentWork{};
  // Each valve takes the largest uniform demand of its loaded cells: exact when no cell has a
  // valve raised above its own demand. Otherwise Gauss-Newton, warm-started from the last solve
  // when every cell of the component was solved that way then.
  bool warm = true;
  for (const std::uint32_t cell : comp.cells) {
    warm = warm && memory.cache[cell].gn_last;
  }
  const bool conflict = warm || demands_conflict(topo, comp, memory);  // a warm component keeps tracking
  if (!conflict || !warm) {
    for (std::size_t k = 0; k < comp.valves.size(); ++k) {
      t[comp.valves[k]] = t1[k];
    }
  }
  for (const std::uint32_t cell : comp.cells) {
    output.cells[cell].residual_N = 0.0;
  }
  if (conflict) {
    solve_conflict(topo, comp, memory, factors, levels, output, warm);
  } else {
    factors.search_stage[comp.id] = kSearchIdle;  // the demands are exact: nothing to search for
  }
  for (const std::uint32_t cell : comp.cells) {
    memory.cache[cell].gn_last = conflict;
  }
  InverseReport& rep = output.rep;
  rep.cell_updates += work.rows;
  rep.iterations += work.iterations;
  rep.converged = rep.converged && work.converged;
  rep.residual_predicted = rep.residual_predicted || work.predicted;
}

// Every valve at its cells' largest demand (into t1): true when some cell then renders too much.
// A flowing cell with any valve raised does; a holding cell only when every valve is raised (its
// weakest branch sets its pressure).
bool InverseSolver::demands_conflict(const InverseTopology& topo, const Component& comp,
                                     CellMemory& memory) noexcept {
  for (std::size_t k = 0; k < comp.valves.size(); ++k) {
    t1[k] = max_demand(topo, comp, memory, k);
  }
  bool conflict = false;
  for (const std::uint32_t cell : comp.cells) {
    const CellInfo& ci = topo.graph.info[cell];
    const Derived& d = memory.cur(cell);
    bool any = false;
    bool all = true;
    for (std::uint32_t k = ci.valve_begin; k < ci.valve_end; ++k) {
      const bool raised = t1[comp.local_of[topo.graph.cell_valves[k]]] > memory.demand_of(topo, cell);
      any = any || raised;
      all = all && raised;
    }
    conflict = conflict || (d.flow_m3_per_s > 0.0 ? any : all && !d.one_sided);
  }
  return conflict;
}

// Gauss-Newton on a component whose demands conflict: tracking when warm and near, else the full
// solve, a cold restart when the warm one leads nowhere, and escapes from a symmetric stall.
void InverseSolver::solve_conflict(const InverseTopology& topo, const Component& comp, CellMemory& memory,
                                   ChordFactors& factors, ValveLevels& levels, InverseOutput& output,
                                   bool warm) noexcept {
  bool converged = false;
  bool tracked = false;
  // Warm: residuals only first (a chord step reuses the saved Jacobian).
  double merit = evaluate_rows(topo, comp, memory, levels, warm ? Rows::residuals : Rows::relinearised);
  // A search under way goes on before any tracking: tracking near a compromise would stop it.
  const unsigned char stage = factors.search_stage[comp.id];
  const bool searching = warm && stage != kSearchIdle && stage != kSearchStepping;
  if (warm && !searching && comp.cells.size() <= kDenseRows) {
    tracked = track(topo, comp, memory, factors, levels, converged);
  }
  if (!tracked) {
    if (warm) {
      merit = evaluate_rows(topo, comp, memory, levels);  // far from the aim: relinearise where needed
    }
    if (searching) {
      // The search's next stage stands in for this tick's warm solve (each of its trials is a
      // solve of its own) after kSearchTrackSteps steps that follow this tick's targets: the
      // stage keeps those levels when none of its trials does better.
      merit = gauss_newton(topo, comp, memory, factors, levels, kMinDamping, converged, merit, Run::solve,
                           kSearchTrackSteps);
      if (!converged) {
        merit = search(topo, comp, memory, factors, levels, merit, converged);
      }
    } else {
      const int steps_before = work.iterations;
      merit = gauss_newton(topo, comp, memory, factors, levels, warm ? kMinDamping : kStartDamping, converged,
                           merit, Run::solve);
      // A component stopped on its step cap is not stuck: it goes on next tick.
      factors.search_stage[comp.id] = step_capped ? kSearchStepping : kSearchIdle;
      factors.searching = factors.searching || step_capped;
      if (!converged && !step_capped) {
        plan_search(comp, factors, warm);
        // A warm solve that gave up within half its steps (a press turned into a hold stops
        // after about 5) leaves this tick room for the cold restart: the hold is met on the tick
        // it begins. A longer one leaves the restart to the next tick.
        if (factors.search_stage[comp.id] == kSearchRestart &&
            2 * (work.iterations - steps_before) <= topo.opt.max_iterations) {
          merit = search(topo, comp, memory, factors, levels, merit, converged);
        }
      }
    }
  }
  if (converged) {
    factors.search_stage[comp.id] = kSearchIdle;  // nothing left to search for
  }
  double worst = 0.0;
  for (std::size_t r = 0; r < comp.cells.size(); ++r) {
    const double er = one_sided[r] != 0 && e[r] > 0.0 ? 0.0 : e[r];
    output.cells[comp.cells[r]].residual_N = topo.area_m2 * er;
    worst = std::max(worst, std::fabs(er));
  }
  work.converged = converged || worst <= topo.tol_Pa;
}

// A solve that did not converge plans a search for better levels, spread over the next ticks so
// that no tick pays for more than one Gauss-Newton (about 12 steps): a cold restart from the
// demands first (a press turned into a hold, where the weakest valve rules), then the stall
// escapes from the best levels so far, kEscapesPerSolve a tick until each was tried. A cold solve
// that stalled goes straight to the escapes. Its inputs held or not, the search goes on
// (CellInverse::Impl::continue_searches). A search whose stages lowered the merit by less than
// kSearchGain found the compromise of aims no levels meet: the component tracks it for
// kSearchWait_s (on the tick's clock, whatever the rate) before searching again.
void InverseSolver::plan_search(const Component& comp, ChordFactors& factors, bool warm) const noexcept {
  // (A clock that went back more than the wait, a restarted session's, ends the wait.)
  const double after_s = factors.search_after_s[comp.id];
  if (warm && now_s < after_s && after_s - now_s <= kSearchWait_s) {
    return;
  }
  factors.searching = true;
  factors.search_stage[comp.id] = warm ? kSearchRestart : kSearchEscapes;
  factors.search_gained[comp.id] = 0;
  factors.escape_next[comp.id] = 0;
}

// One stage of the search planned; returns the merit of the levels it leaves.
double InverseSolver::search(const InverseTopology& topo, const Component& comp, CellMemory& memory,
                             ChordFactors& factors, ValveLevels& levels, double merit,
                             bool& converged) noexcept {
  unsigned char& stage = factors.search_stage[comp.id];
  unsigned char& gained = factors.search_gained[comp.id];
  const double tracked = merit;
  const bool restart = stage == kSearchRestart;
  merit = restart ? restart_cold(topo, comp, memory, factors, levels, merit, converged)
                  : escape_stall(topo, comp, memory, factors, levels, merit, converged);
  gained = gained != 0 || converged || merit < (1.0 - kSearchGain) * tracked ? 1 : 0;
  if (restart) {
    stage = kSearchEscapes;  // from the first escape (plan_search set escape_next)
    return merit;
  }
  if (factors.escape_next[comp.id] != 0 && !converged) {
    return merit;  // escapes left for the next tick
  }
  stage = kSearchIdle;
  factors.search_after_s[comp.id] =
      gained != 0 ? -std::numeric_limits<double>::infinity() : now_s + kSearchWait_s;
  gained = 0;
  return merit;
}

// Tracking: the last solve's levels with this tick's targets. A small error takes one damped
// step, unverified: its residuals are the linear model's prediction, and the next tick's rows
// check it. False when the error is too large to track. Inline into its one caller: the warm
// path pays no call passing the parts.
inline bool InverseSolver::track(const InverseTopology& topo, const Component& comp, const CellMemory& memory,
                                 ChordFactors& factors, ValveLevels& levels, bool& converged) noexcept {
  double* const t = levels.t.data();
  const std::size_t nr = comp.cells.size();
  double worst = 0.0;
  bool near = true;
  for (std::size_t r = 0; r < nr; ++r) {
    const double er = one_sided[r] != 0 && e[r] > 0.0 ? 0.0 : std::fabs(e[r]);
    worst = std::max(worst, er);
    near = near && er <= kTrackReach * (aim_row[r] + topo.tol_Pa);
  }
  if (worst <= topo.tol_Pa) {
    converged = true;
    return true;
  }
  if (!near) {
    return false;
  }
  // A small correction reuses the last factorisation (a chord step: J frozen); a larger one, an
  // old factor or a changed active set refactorises.
  const int age = factors.age[comp.id];
  bool chord = age >= 0 && age < kChordAge;
  for (std::size_t r = 0; r < nr && chord; ++r) {
    chord = std::fabs(e[r]) <= kChordReach * aim_row[r] + topo.chord_floor_Pa;
  }
  if (!chord || !chord_step(topo, comp, levels, factors)) {
    evaluate_rows(topo, comp, memory, levels, Rows::at_aim);
    bounded_step(topo, comp, levels, kMinDamping, factors);
  }
  ++work.iterations;
  double worst_pred = 0.0;
  for (std::size_t k = 0; k < comp.valves.size(); ++k) {
    t[comp.valves[k]] = t1[k];
  }
  for (std::size_t r = 0; r < nr; ++r) {
    e[r] = predicted[r];
    worst_pred = std::max(worst_pred, one_sided[r] != 0 && e[r] > 0.0 ? 0.0 : std::fabs(e[r]));
  }
  converged = worst_pred <= topo.tol_Pa;
  work.predicted = true;
  return true;
}

// The last solve's levels led nowhere (e.g. a press turned into a hold, where the weakest valve
// rules): starts again from the demands, as a cold solve would, and keeps the better of the two.
double InverseSolver::restart_cold(const InverseTopology& topo, const Component& comp, CellMemory& memory,
                                   ChordFactors& factors, ValveLevels& levels, double merit,
                                   bool& converged) noexcept {
  double* const t = levels.t.data();
  for (std::size_t k = 0; k < comp.valves.size(); ++k) {
    const double level = max_demand(topo, comp, memory, k);
    best[k] = t[comp.valves[k]];
    t[comp.valves[k]] = level;
  }
  bool cold_converged = false;
  const double cold = gauss_newton(topo, comp, memory, factors, levels, kStartDamping, cold_converged,
                                   evaluate_rows(topo, comp, memory, levels), Run::trial);
  if (cold < merit) {
    converged = cold_converged;
    return cold;
  }
  for (std::size_t k = 0; k < comp.valves.size(); ++k) {
    t[comp.valves[k]] = best[k];
  }
  return evaluate_rows(topo, comp, memory, levels);
}

// A cold start can stall where two cells pull a shared valve both ways and symmetry keeps the
// valves together (e.g. a corner cell that must flow through one of its two valves while its
// neighbour needs both high). Tries opening or shutting such valves, kEscapesPerSolve trials a
// call, the next call going on from where this one stopped (escape_next, 0 once each was tried);
// keeps the best levels.
double InverseSolver::escape_stall(const InverseTopology& topo, const Component& comp,
                                   const CellMemory& memory, ChordFactors& factors, ValveLevels& levels,
                                   double merit, bool& converged) noexcept {
  double* const t = levels.t.data();
  const std::span<const std::uint32_t> valves = comp.valves;
  std::uint32_t& next = factors.escape_next[comp.id];
  std::uint32_t* const listed = factors.escape_valves.data() + comp.id * (kMaxEscapes / 2);
  std::size_t candidates = next == 0 ? 0 : factors.escape_count[comp.id];
  for (std::size_t k = 0; k < valves.size(); ++k) {
    best[k] = t[valves[k]];
    if (next != 0) {
      continue;  // a search under way goes down the list its first trial made
    }
    bool high = false;
    bool low = false;
    for (std::uint32_t j = comp.inc_begin[k]; j < comp.inc_begin[k + 1]; ++j) {
      const std::uint32_t r = comp.inc_row[j];
      high = high || (e[r] > topo.tol_Pa && one_sided[r] == 0);
      low = low || e[r] < -topo.tol_Pa;
    }
    if (high && low && candidates < kMaxEscapes / 2) {
      listed[candidates++] = static_cast<std::uint32_t>(k);
    }
  }
  factors.escape_count[comp.id] = static_cast<unsigned char>(candidates);
  double best_merit = merit;
  const std::size_t trials = 2 * candidates;
  const std::size_t first = next;
  for (std::size_t i = first; i < trials && i < first + kEscapesPerSolve && !converged; ++i) {
    for (std::size_t k = 0; k < valves.size(); ++k) {
      t[valves[k]] = best[k];
    }
    t[valves[listed[i / 2]]] = i % 2 == 0 ? topo.t_min : topo.t_max;
    bool conv_i = false;
    const double merit_i = gauss_newton(topo, comp, memory, factors, levels, kStartDamping, conv_i,
                                        evaluate_rows(topo, comp, memory, levels), Run::trial);
    if (merit_i < best_merit) {
      best_merit = merit_i;
      converged = conv_i;
      for (std::size_t k = 0; k < valves.size(); ++k) {
        best[k] = t[valves[k]];
      }
    }
  }
  next = first + kEscapesPerSolve < trials && !converged
             ? static_cast<std::uint32_t>(first + kEscapesPerSolve)
             : 0;
  if (candidates > 0) {
    for (std::size_t k = 0; k < valves.size(); ++k) {
      t[valves[k]] = best[k];
    }
    return evaluate_rows(topo, comp, memory, levels);
  }
  return merit;
}

// Damped Gauss-Newton (Levenberg-Marquardt with backtracking) from the current levels of the
// component; leaves the rows evaluated at the final levels. Returns the merit.
double InverseSolver::gauss_newton(const InverseTopology& topo, const Component& comp,
                                   const CellMemory& memory, ChordFactors& factors, ValveLevels& levels,
                                   double start_damping, bool& converged, double merit, Run run,
                                   int max_steps) noexcept {
  double* const t = levels.t.data();
  const std::span<const std::uint32_t> valves = comp.valves;
  int steps = max_steps >= 0 ? max_steps : topo.opt.max_iterations;
  // A capped component goes on from these levels next tick (large_ or small_component_steps).
  int cap = steps;
  if (comp.cells.size() > kDenseRows) {
    cap = topo.opt.large_component_steps > 0 ? topo.opt.large_component_steps : steps;
  } else if (topo.opt.small_component_steps > 0) {
    cap = run == Run::solve ? topo.opt.small_component_steps
                            : kTrialStepsPerStep * topo.opt.small_component_steps;
  }
  const bool capping = cap < steps;
  steps = std::min(steps, cap);
  double damping = start_damping;
  converged = false;
  step_capped = false;
  for (int it = 0;; ++it) {
    double worst = 0.0;
    for (std::size_t r = 0; r < comp.cells.size(); ++r) {
      worst = std::max(worst, one_sided[r] != 0 && e[r] > 0.0 ? 0.0 : std::fabs(e[r]));
    }
    if (worst <= topo.tol_Pa) {
      converged = true;
      break;
    }
    if (it >= steps) {
      step_capped = capping;
      break;
    }
    ++work.iterations;
    for (std::size_t k = 0; k < valves.size(); ++k) {
      t0[k] = t[valves[k]];
    }
    if (comp.cells.size() <= kDenseRows) {
      bounded_step(topo, comp, levels, damping, factors);
    } else {
      fallback_step(topo, comp, levels, damping);
    }
    // Backtrack on the merit (the rows are piecewise smooth: holding cells take a minimum).
    double trial = 1.0;
    double merit_new = merit;
    for (int bt = 0; bt <= kMaxBacktracks; ++bt) {
      for (std::size_t k = 0; k < valves.size(); ++k) {
        t[valves[k]] = t0[k] + trial * (t1[k] - t0[k]);
      }
      merit_new = evaluate_rows(topo, comp, memory, levels);
      if (merit_new <= merit) {
        break;
      }
      trial *= 0.5;
    }
    damping = trial < 1.0 ? damping * 8.0 : std::max(damping * 0.25, kMinDamping);
    if (!(merit_new <= merit)) {
      for (std::size_t k = 0; k < valves.size(); ++k) {
        t[valves[k]] = t0[k];
      }
      merit = evaluate_rows(topo, comp, memory, levels);
      break;  // no descent left at this linearisation: stop here
    }
    const bool stalled = merit - merit_new <= kStationaryDecrease * merit;
    merit = merit_new;
    if (stalled) {
      break;
    }
  }
  return merit;
}

}  // namespace mrskin::model
