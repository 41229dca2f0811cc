// The skin's hydraulic network in time: see mrskin/driver/model/network.hpp and
// docs/model.md (Part II). Everything after the constructor is noexcept and allocation-free:
// the state, the Newton workspaces and the sparse factorisation are sized once.
#include "mrskin/driver/model/network.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <string>
#include <utility>
#include <vector>

#include "mrskin/driver/errors.hpp"
#include "network_impl.hpp"
#include "network_ldl.hpp"

namespace mrskin::model {

const char* to_string(Stepper s) noexcept {
  switch (s) {
    case Stepper::implicit_exact:
      return "implicit_exact";
    case Stepper::implicit_regularised:
      return "implicit_regularised";
    case Stepper::linearly_implicit_regularised:
      return "linearly_implicit_regularised";
    case Stepper::explicit_euler:
      return "explicit_euler";
  }
  return "unknown";
}

Status NetworkSimulation::Impl::link_law(std::size_t l, double x, bool regularised, double& flow,
                                         double& cond) const noexcept {
  const Link& k = links[l];
  const double tau = k.valve < 0 ? 0.0 : valve_tau[static_cast<std::size_t>(k.valve)];
  // A passage without yield (its coil off: nine in ten on the 16x16 demo) below the critical
  // flow is Newtonian: flow_point's bits (its factored form at zeta = 0) without its call.
  const double q_laminar = newtonian_conductance * std::fabs(x);
  if (tau == 0.0 && x != 0.0 && q_laminar <= critical_flow) {
    flow = std::copysign(q_laminar, x);
    cond = newtonian_conductance;
  } else {
    const Result<FlowPoint> f = model.valve_law().flow_point(x, tau);
    if (!f.ok()) {
      return f.status == Status::overflow || f.status == Status::not_finite ? Status::not_finite : f.status;
    }
    flow = f.value.flow_m3_per_s;
    cond = f.value.conductance_m3_per_s_Pa;
  }
  if (regularised) {
    // A Newtonian floor 1/factor of the open passage's: smooth, strictly monotone, and inside
    // the yield band the slow creep of a "nearly locked" valve.
    flow += floor_conductance * x;
    cond += floor_conductance;
  }
  return Status::ok;
}

// Pad depth, pressure and compliance of cell i at gain e1. The finger is a one-sided obstacle:
// the pad sits at the contact depth while the finger pushes (force >= 0), and deeper, where its
// force vanishes, when the membrane is sucked in faster than the finger retreats.
Status NetworkSimulation::Impl::resolve_cell(std::size_t i, double e1, bool dg, Eval& ev) const noexcept {
  const double d0 = d[i];
  const double s0 = s_of(d0, e[i]);
  const double lo = dc[i];
  auto force_at = [&](double depth) {
    return pad.value(d0, depth, dg) + area * bulge.value(s0, s_of(depth, e1), dg);
  };
  auto force_slope = [&](double depth) {
    return pad.slope(d0, depth, dg) + area * area * bulge.slope(s0, s_of(depth, e1), dg);
  };
  double depth = lo;
  bool pinned = true;
  if (const double f_lo = force_at(lo); f_lo < 0.0) {
    pinned = false;
    // Bracket the free depth (the force rises with depth), then safeguarded Newton.
    double a = lo;
    double f_a = f_lo;
    double step = std::max(std::fabs(d0 - lo), 1e-3 * cell_depth);
    double b = lo + step;
    double f_b = force_at(b);
    int n = 0;
    while (f_b < 0.0) {
      a = b;
      f_a = f_b;
      step *= 2.0;
      b = lo + step;
      if (++n > kScalarIterations || !std::isfinite(b)) {
        return Status::no_convergence;
      }
      f_b = force_at(b);
    }
    // Newton from the first probe when it brackets the root (the step's start depth, near it);
    // after an expansion from the last probe below the root, which lies just past it: from the
    // far end Newton crawled down the stiff force curve about 15 % a step (16x16: 8.8 iterations
    // a search that expanded, 3.0 from below). The force there is known: not evaluated again.
    const bool expanded = n > 0;
    depth = expanded ? a : b;
    double f = expanded ? f_a : f_b;
    bool done = false;
    ++pad_searches;
    for (int it = 0; it < kScalarIterations && !done; ++it) {
      ++pad_search_iterations;
      if (it > 0) {
        f = force_at(depth);
      }
      if (!std::isfinite(f)) {
        return Status::not_finite;
      }
      if (f == 0.0) {
        done = true;
        break;
      }
      (f > 0.0 ? b : a) = depth;
      double next = depth - f / force_slope(depth);
      // A Newton step within round-off has converged, also when it lands on an end of the
      // bracket (the depth itself, whose force rounded to the wrong side of zero). Bisecting
      // then threw the root away and took 30-40 iterations to find it again: a third of the
      // 16x16 plant's pad solves did.
      const bool converged = std::fabs(next - depth) <= 1e-15 * depth;
      if (!converged && !(next > a && next < b)) {
        next = 0.5 * (a + b);
      }
      done = converged || std::fabs(next - depth) <= 1e-15 * depth || b - a <= 1e-15 * b;
      depth = next;
    }
    if (!done) {
      return Status::no_convergence;
    }
  }
  const double s1 = s_of(depth, e1);
  const double b_s = bulge.slope(s0, s1, dg);
  ev.d[i] = depth;
  ev.in_contact[i] = pinned ? 1 : 0;
  ev.p[i] = bulge.value(s0, s1, dg);
  if (pinned) {
    ev.c[i] = 1.0 / b_s;
  } else {
    // The pad follows the fluid: pad and bulge stiffnesses in series.
    const double a_d = pad.slope(d0, depth, dg);
    ev.c[i] = (a_d + area * area * b_s) / (a_d * b_s);
  }
  return Status::ok;
}

Status NetworkSimulation::Impl::evaluate(Eval& ev, double dt, bool dg, bool regularised) const noexcept {
  if (const Status s = evaluate_nodes(ev, dg); s != Status::ok) {
    return s;
  }
  if (const Status s = evaluate_links(ev, 0, links.size(), dt, regularised); s != Status::ok) {
    return s;
  }
  return evaluate_norms(ev);
}

// evaluate()'s parts (the phases of a step in phases run them apart): the cells and nodes...
Status NetworkSimulation::Impl::evaluate_nodes(Eval& ev, bool dg) const noexcept {
  ++balance_evaluations;
  for (std::size_t i = 0; i < cells; ++i) {
    if (const Status s = resolve_cell(i, ev.e[i], dg, ev); s != Status::ok) {
      return s;
    }
  }
  for (std::size_t n = cells; n < nodes; ++n) {
    const double cn = node_compliance[n];
    ev.p[n] = p0 + (dg ? 0.5 * (e[n] + ev.e[n]) : ev.e[n]) / cn;
    ev.c[n] = dg ? 2.0 * cn : cn;
  }
  for (std::size_t n = 0; n < nodes; ++n) {
    ev.r[n] = ev.e[n] - e[n];
  }
  return Status::ok;
}

// ... the links [first, last), in link order ...
Status NetworkSimulation::Impl::evaluate_links(Eval& ev, std::size_t first, std::size_t last, double dt,
                                               bool regularised) const noexcept {
  // The laws first, then the sums in the same order (the same bits): the laws of successive
  // links do not wait on each other's sums.
  for (std::size_t l = first; l < last; ++l) {
    const Link& k = links[l];
    const double x = ev.p[k.a] - ev.p[k.b];
    ev.x[l] = x;
    if (const Status s = link_law(l, x, regularised, ev.q[l], ev.g[l]); s != Status::ok) {
      return s;
    }
  }
  for (std::size_t l = first; l < last; ++l) {
    const Link& k = links[l];
    ev.r[k.a] += dt * ev.q[l];
    ev.r[k.b] -= dt * ev.q[l];
  }
  return Status::ok;
}

// ... and the residual's norms.
Status NetworkSimulation::Impl::evaluate_norms(Eval& ev) const noexcept {
  double n2 = 0.0;
  double ni = 0.0;
  for (std::size_t n = 0; n < nodes; ++n) {
    n2 += ev.r[n] * ev.r[n];
    ni = std::max(ni, std::fabs(ev.r[n]));
  }
  ev.norm2 = n2;
  ev.norm_inf = ni;
  return std::isfinite(n2) ? Status::ok : Status::not_finite;
}

// M = diag(c) + dt B^T G B: J = I + dt B^T G B diag(1/c) times diag(1/c), symmetric positive
// definite even with every passage locked (G = 0) because every node has a compliance.
bool NetworkSimulation::Impl::assemble_and_factorize(const Eval& ev, double dt) noexcept {
  assemble(ev, dt);
  return ldl.factorize();
}

void NetworkSimulation::Impl::assemble(const Eval& ev, double dt) noexcept {
  const std::span<double> a = ldl.values();
  std::fill(a.begin(), a.end(), 0.0);
  for (std::size_t n = 0; n < nodes; ++n) {
    a[ldl.diagonal_slot(n)] += ev.c[n];
  }
  for (std::size_t l = 0; l < links.size(); ++l) {
    const double w = dt * ev.g[l];
    a[ldl.diagonal_slot(links[l].a)] += w;
    a[ldl.diagonal_slot(links[l].b)] += w;
    a[ldl.pair_slot(l)] -= w;
  }
}

// Damped Newton on the discrete-gradient step: unknowns e1, J de = -R solved as M y = -R,
// de = c y (y: the pressure correction), backtracking on |R|.
Status NetworkSimulation::Impl::newton(double dt, bool regularised) noexcept {
  // Start from the last step's flows carried on (e0 + dt/dt_prev (e0 - e_prev)): while the
  // flows change smoothly that is within a Newton step or two of the answer.
  const double ratio = prev_dt > 0.0 ? std::min(dt / prev_dt, 4.0) : 0.0;
  for (std::size_t n = 0; n < nodes; ++n) {
    cur.e[n] = e[n] + ratio * (e[n] - prev_e[n]);
  }
  const bool dg = !opt.backward_euler;
  Status first = evaluate(cur, dt, dg, regularised);
  // After a jump in the inputs the start state may be the better guess: keep the smaller
  // residual. A carried-on start already within the volume tolerance is kept without the
  // comparison: on the 16x16 demo the committed state never beat one (half its steps, one
  // evaluation of every cell and link saved on each).
  const bool start_met = first == Status::ok && cur.norm_inf <= opt.volume_tolerance_m3;
  if (ratio > 0.0 && !start_met) {
    std::copy(e.begin(), e.end(), trial.e.begin());
    if (evaluate(trial, dt, dg, regularised) == Status::ok &&
        (first != Status::ok || trial.norm2 < cur.norm2)) {
      cur.swap(trial);
      first = Status::ok;
    }
  }
  if (first != Status::ok) {
    return first;
  }
  double last_update = std::numeric_limits<double>::infinity();
  double scale = 0.0;
  for (const double v : cur.e) {
    scale = std::max(scale, std::fabs(v));
  }
  const double round_off = 1e-14 * scale;
  int it = 0;
  bool converged = false;
  bool factorized = false;
  bool chorded = false;
  for (;; ++it) {
    const bool met = cur.norm_inf <= opt.volume_tolerance_m3;
    converged = met && (cur.norm_inf <= round_off || last_update <= opt.pressure_tolerance_Pa);
    if (converged || it >= opt.max_newton_iterations) {
      break;
    }
    // Once the residual is met, polish with the last factorisation (a chord step): the energy
    // balance wants round-off, the Jacobian barely changes.
    const bool chord = met && factorized && !chorded;
    // The exact law's locked passages conduct nothing: the factorisation skips their zeros (the
    // same non-zero bits; a 5 % press on palm-64x64: 3.4 times fewer instructions a substep).
    if (!chord) {
      assemble(cur, dt);
      if (!ldl.factorize_skipping_zeros()) {
        return Status::no_convergence;
      }
      factorized = true;
    }
    chorded = chord;
    for (std::size_t n = 0; n < nodes; ++n) {
      y[n] = -cur.r[n];
    }
    ldl.solve_skipping_zeros(y);
    double y_inf = 0.0;
    for (std::size_t n = 0; n < nodes; ++n) {
      de[n] = cur.c[n] * y[n];
      y_inf = std::max(y_inf, std::fabs(y[n]));
    }
    if (!std::isfinite(y_inf)) {
      return Status::not_finite;
    }
    double alpha = 1.0;
    for (;;) {
      for (std::size_t n = 0; n < nodes; ++n) {
        trial.e[n] = cur.e[n] + alpha * de[n];
      }
      const Status s = evaluate(trial, dt, dg, regularised);
      const bool ok = s == Status::ok;
      if (ok && trial.norm2 <= (1.0 - kArmijo * alpha) * cur.norm2) {
        break;
      }
      if (alpha <= kMinStep) {
        if (!ok) {
          return s;
        }
        break;  // no decrease along the direction: take the short step, the cap bounds the loop
      }
      alpha *= 0.5;
    }
    cur.swap(trial);
    last_update = alpha * y_inf;
  }
  report.iterations = it;
  report.volume_residual_m3 = cur.norm_inf;
  if (!converged && cur.norm_inf > opt.volume_tolerance_m3) {
    return Status::no_convergence;
  }
  finish_volumes(cur, dt);
  return Status::ok;
}

// Rosenbrock-Euler: one Newton step of implicit Euler from e0, point pressures, regularised law.
// Its parts, apart, are the phases of begin_step/advance_step too (network_phases.cpp).
Status NetworkSimulation::Impl::one_solve(double dt) noexcept {
  if (const Status s = one_solve_evaluate(dt); s != Status::ok) {
    return s;
  }
  if (!assemble_and_factorize(cur, dt)) {
    return Status::no_convergence;
  }
  one_solve_finish(dt);
  return Status::ok;
}

Status NetworkSimulation::Impl::one_solve_evaluate(double dt) noexcept {
  std::copy(e.begin(), e.end(), cur.e.begin());
  return evaluate(cur, dt, false, true);
}

void NetworkSimulation::Impl::one_solve_finish(double dt) noexcept {
  one_solve_pressures();
  one_solve_flows(dt);
}

// The pressure correction y of the one solve...
void NetworkSimulation::Impl::one_solve_pressures() noexcept {
  for (std::size_t n = 0; n < nodes; ++n) {
    y[n] = -cur.r[n];
  }
  ldl.solve(y);
}

// ... and the flows and volumes it gives.
void NetworkSimulation::Impl::one_solve_flows(double dt) noexcept {
  // Linearised flows at the predicted pressures.
  for (std::size_t l = 0; l < links.size(); ++l) {
    const double dx = y[links[l].a] - y[links[l].b];
    cur.q[l] += cur.g[l] * dx;
    cur.x[l] += dx;
  }
  report.iterations = 1;
  report.volume_residual_m3 = 0.0;
  finish_volumes(cur, dt);
}

// The one solve predicted the new pressures as p0 + y; the laws at the new volumes give new_p.
// Far apart, the step was too long for its linearisation (stiff cells, a jump in the inputs):
// say so rather than return a state the model does not support.
Status NetworkSimulation::Impl::check_linearisation() noexcept {
  double scale = 1.0;
  double worst = 0.0;
  for (std::size_t n = 0; n < nodes; ++n) {
    const double predicted = cur.p[n] + y[n];
    scale = std::max({scale, std::fabs(predicted), std::fabs(new_p[n])});
    worst = std::max(worst, std::fabs(new_p[n] - predicted));
  }
  for (const double t : valve_tau) {
    scale = std::max(scale, model.valve_law().yield_pressure_Pa(t));
  }
  report.linearisation_error = worst / scale;
  return report.linearisation_error <= opt.linearisation_tolerance ? Status::ok : Status::out_of_regime;
}

Status NetworkSimulation::Impl::forward_euler(double dt) noexcept {
  std::copy(e.begin(), e.end(), cur.e.begin());
  if (const Status s = evaluate(cur, dt, false, true); s != Status::ok) {
    return s;
  }
  report.iterations = 1;
  report.volume_residual_m3 = 0.0;
  finish_volumes(cur, dt);
  return Status::ok;
}

// The new volumes are e0 + dt * (inflow of the flows the stepper moved): volume is conserved to
// round-off whatever the stepper. Dissipation: each passage's flow times the pressure difference
// its law was evaluated at (for the one-solve steppers that is their energy error's source).
void NetworkSimulation::Impl::finish_volumes(const Eval& at, double dt) noexcept {
  std::copy(e.begin(), e.end(), new_e.begin());
  std::size_t locked = 0;
  double diss = 0.0;
  for (std::size_t l = 0; l < links.size(); ++l) {
    const Link& k = links[l];
    new_e[k.a] -= dt * at.q[l];
    new_e[k.b] += dt * at.q[l];
    new_q[l] = at.q[l];
    diss += dt * at.q[l] * at.x[l];
    const double tau = k.valve < 0 ? 0.0 : valve_tau[static_cast<std::size_t>(k.valve)];
    locked += std::fabs(at.x[l]) <= model.valve_law().yield_pressure_Pa(tau) ? 1U : 0U;
  }
  report.locked_links = locked;
  new_dissipated = diss;
}

// Pad depths from `depths`, then pressures and forces at the new volumes.
void NetworkSimulation::Impl::finish_state(const Eval& depths) noexcept {
  std::copy(depths.d.begin(), depths.d.end(), new_d.begin());
  std::copy(depths.in_contact.begin(), depths.in_contact.end(), new_in_contact.begin());
  new_contact_force.fill(0.0);
  for (std::size_t i = 0; i < cells; ++i) {
    new_p[i] = bulge.grad(s_of(new_d[i], new_e[i]));
    const bool touching = new_in_contact[i] != 0 && dc[i] > 0.0;
    // The finger only pushes.
    new_force[i] = touching ? std::max(0.0, pad.grad(new_d[i]) + area * new_p[i]) : 0.0;
    if (touching && owner[i] != kNone) {
      new_contact_force[static_cast<std::size_t>(owner[i])] += new_force[i];
    }
  }
  for (std::size_t n = cells; n < nodes; ++n) {
    new_p[n] = p0 + new_e[n] / node_compliance[n];
  }
}

Status NetworkSimulation::Impl::run_trial(double dt) noexcept {
  report = StepReport{};
  Status s = Status::ok;
  switch (opt.stepper) {
    case Stepper::implicit_exact:
    case Stepper::implicit_regularised:
      s = newton(dt, opt.stepper == Stepper::implicit_regularised);
      if (s == Status::ok) {
        finish_state(cur);
      }
      break;
    case Stepper::linearly_implicit_regularised:
    case Stepper::explicit_euler:
      s = opt.stepper == Stepper::explicit_euler ? forward_euler(dt) : one_solve(dt);
      if (s == Status::ok) {
        s = settle_one_step_cells();
      }
      break;
  }
  if (s != Status::ok) {
    return s;
  }
  return check_new_state();
}

// The one-solve steppers' pad depths were those of the start volumes: settle them at the new
// ones, and check the linearisation.
Status NetworkSimulation::Impl::settle_one_step_cells() noexcept {
  const Status s = settle_cells(0, cells);
  return s == Status::ok ? finish_settled_cells() : s;
}

// Cells [first, last) at their new volumes.
Status NetworkSimulation::Impl::settle_cells(std::size_t first, std::size_t last) noexcept {
  Status s = Status::ok;
  for (std::size_t i = first; i < last && s == Status::ok; ++i) {
    s = resolve_cell(i, new_e[i], false, trial);
  }
  return s;
}

// After each cell settled at its new volume: the state, and the linearisation's check.
Status NetworkSimulation::Impl::finish_settled_cells() noexcept {
  finish_state(trial);
  return opt.stepper == Stepper::linearly_implicit_regularised ? check_linearisation() : Status::ok;
}

Status NetworkSimulation::Impl::check_new_state() const noexcept {
  double check = new_dissipated;
  for (std::size_t n = 0; n < nodes; ++n) {
    check += new_e[n] + new_p[n];
  }
  for (std::size_t i = 0; i < cells; ++i) {
    check += new_d[i] + new_force[i];
  }
  return std::isfinite(check) ? Status::ok : Status::not_finite;
}

void NetworkSimulation::Impl::compute_depths() noexcept {
  if (direct_depths) {
    std::copy(direct_depth.begin(), direct_depth.end(), dc.begin());
    std::fill(owner.begin(), owner.end(), kNone);
    return;
  }
  for (std::size_t i = 0; i < cells; ++i) {
    double best = 0.0;
    std::int64_t who = kNone;
    for (std::size_t c = 0; c < contact_count; ++c) {
      const Contact& k = contacts[c];
      const double dx = cell_x[i] - k.x_m;
      const double dy = cell_y[i] - k.y_m;
      const double depth = contact_ind[c] - (dx * dx + dy * dy) / (2.0 * k.radius_m);
      if (depth > best) {
        best = depth;
        who = static_cast<std::int64_t>(c);
      }
    }
    dc[i] = best;
    owner[i] = who;
  }
}

// One force-mode contact: its indentation by a bracketed Illinois (regula falsi) search on the
// monotone force(indentation), every evaluation a full trial step.
Status NetworkSimulation::Impl::solve_one_contact(std::size_t c, double dt) noexcept {
  const Contact& k = contacts[c];
  auto eval = [&](double ind) {
    contact_ind[c] = ind;
    compute_depths();
    return run_trial(dt);
  };
  double touch = std::numeric_limits<double>::infinity();  // indentation at which it reaches a cell
  for (std::size_t i = 0; i < cells; ++i) {
    const double dx = cell_x[i] - k.x_m;
    const double dy = cell_y[i] - k.y_m;
    touch = std::min(touch, (dx * dx + dy * dy) / (2.0 * k.radius_m));
  }
  const double deepest = touch + cell_depth * (1.0 - 1e-9);
  const double tol = opt.force_tolerance_N;
  double lo = touch;
  double flo = -k.force_N;
  if (k.force_N <= tol) {
    return eval(lo);
  }
  double start = std::clamp(contact_ind[c], lo, deepest);
  double hi = start;
  double fhi = flo;
  if (start > lo) {
    const Status s = eval(start);
    if (s == Status::out_of_regime) {
      start = lo;  // a warm start too far for the linearised stepper: search up from the touch
    } else if (s != Status::ok) {
      return s;
    } else {
      fhi = contact_error(c);
      if (std::fabs(fhi) <= tol) {
        return Status::ok;
      }
      if (fhi < 0.0) {
        lo = start;
        flo = fhi;
      }
    }
  }
  double step = std::max(start - touch, 1e-3 * cell_depth);
  for (int n = 0; fhi < 0.0; ++n) {
    if (lo >= deepest || n > kScalarIterations) {
      return Status::out_of_range;  // the finger would reach the cell's floor first
    }
    hi = std::min(lo + step, deepest);
    const Status s = eval(hi);
    if (s == Status::out_of_regime && step > 1e-9 * cell_depth) {
      step *= 0.25;  // too long a stride for the linearised stepper's one solve
      fhi = -1.0;
      continue;
    }
    if (s != Status::ok) {
      return s;
    }
    fhi = contact_error(c);
    if (fhi < 0.0) {
      lo = hi;
      flo = fhi;
      step *= 2.0;
    }
  }
  int side = 0;
  for (int n = 0; n < kForceEvaluations; ++n) {
    if (hi - lo <= 1e-12 * cell_depth) {
      break;  // a jump in force (a cell touched at a pressure): the nearest force above the target
    }
    double x = hi - fhi * (hi - lo) / (fhi - flo);
    if (!(x > lo && x < hi)) {
      x = 0.5 * (lo + hi);
    }
    if (const Status s = eval(x); s != Status::ok) {
      return s;
    }
    const double f = contact_error(c);
    if (std::fabs(f) <= tol) {
      return Status::ok;
    }
    if (f > 0.0) {
      hi = x;
      fhi = f;
      flo *= side == 1 ? 0.5 : 1.0;
      side = 1;
    } else {
      lo = x;
      flo = f;
      fhi *= side == -1 ? 0.5 : 1.0;
      side = -1;
    }
  }
  return eval(hi);
}

// Several force-mode contacts: nonlinear Gauss-Seidel over them until their indentations settle.
Status NetworkSimulation::Impl::solve_force_contacts(double dt) noexcept {
  std::array<double, kMaxContacts> before{};
  for (int sweep = 0; sweep < kForceSweeps; ++sweep) {
    std::copy(contact_ind.begin(), contact_ind.end(), before.begin());
    std::size_t solved = 0;
    for (std::size_t c = 0; c < contact_count; ++c) {
      if (contacts[c].mode != Contact::Mode::force) {
        continue;
      }
      if (const Status s = solve_one_contact(c, dt); s != Status::ok) {
        return s;
      }
      ++solved;
    }
    if (solved <= 1) {
      return Status::ok;
    }
    bool settled = true;
    for (std::size_t c = 0; c < contact_count; ++c) {
      if (contacts[c].mode == Contact::Mode::force) {
        settled = settled && (std::fabs(contact_error(c)) <= opt.force_tolerance_N ||
                              std::fabs(contact_ind[c] - before[c]) <= 1e-12 * cell_depth);
      }
    }
    if (settled) {
      return Status::ok;
    }
  }
  return Status::no_convergence;
}

double NetworkSimulation::Impl::stored_energy() const noexcept {
  double u = 0.0;
  for (std::size_t i = 0; i < cells; ++i) {
    u += stored_energy_J(model.contact(), d[i], s_of(d[i], e[i])).value;
  }
  for (std::size_t n = cells; n < nodes; ++n) {
    u += e[n] * (p0 + 0.5 * e[n] / node_compliance[n]);
  }
  return u;
}

// Work: the discrete-gradient force between the two states times the pad's travel, so that
// work = stored change + dissipated exactly for the discrete-gradient steppers.
void NetworkSimulation::Impl::commit(double dt) noexcept {
  // Backward Euler pairs with the end-of-step force (then work - stored change - dissipated is
  // its numerical dissipation, >= 0 by convexity); the discrete gradient with its own.
  const bool end_force = opt.backward_euler && (opt.stepper == Stepper::implicit_exact ||
                                                opt.stepper == Stepper::implicit_regularised);
  for (std::size_t i = 0; i < cells; ++i) {
    const double d0 = d[i];
    const double d1 = new_d[i];
    const double s0 = s_of(d0, e[i]);
    const double s1 = s_of(d1, new_e[i]);
    const double f = end_force ? pad.grad(d1) + area * bulge.grad(s1)
                               : pad.discrete_grad(d0, d1) + area * bulge.discrete_grad(s0, s1);
    work += f * (d1 - d0);
    velocity[i] = (d1 - d0) / dt;
  }
  dissipated += new_dissipated;
  std::copy(e.begin(), e.end(), prev_e.begin());
  prev_dt = dt;
  // Copies, not swaps: spans handed out by the accessors keep pointing at the live state.
  std::copy(new_e.begin(), new_e.end(), e.begin());
  std::copy(new_d.begin(), new_d.end(), d.begin());
  std::copy(new_q.begin(), new_q.end(), q.begin());
  std::copy(new_p.begin(), new_p.end(), node_p.begin());
  std::copy(new_force.begin(), new_force.end(), force.begin());
  contact_force = new_contact_force;
  for (std::size_t v = 0; v < valves; ++v) {
    chamber_p[v] = chamber_node[v] == kNone ? 0.0 : node_p[static_cast<std::size_t>(chamber_node[v])];
  }
  // The stored energy is computed when asked (energy()), not per step: ~3k instructions of the
  // observer's tick on the 5x5 that nothing in the step reads.
}

void NetworkSimulation::Impl::reset() noexcept {
  phase = 0;
  std::fill(e.begin(), e.end(), 0.0);
  std::fill(prev_e.begin(), prev_e.end(), 0.0);
  prev_dt = 0.0;
  std::fill(d.begin(), d.end(), 0.0);
  std::fill(velocity.begin(), velocity.end(), 0.0);
  std::fill(force.begin(), force.end(), 0.0);
  std::fill(q.begin(), q.end(), 0.0);
  for (std::size_t i = 0; i < cells; ++i) {
    node_p[i] = bulge.grad(s_rest);
  }
  std::fill(node_p.begin() + static_cast<std::ptrdiff_t>(cells), node_p.end(), p0);
  for (std::size_t v = 0; v < valves; ++v) {
    chamber_p[v] = chamber_node[v] == kNone ? 0.0 : p0;
  }
  contact_count = 0;
  contact_ind.fill(0.0);
  contact_force.fill(0.0);
  direct_depths = true;
  std::fill(direct_depth.begin(), direct_depth.end(), 0.0);
  work = 0.0;
  dissipated = 0.0;
  stored_initial = stored_energy();
  pad_searches = 0;
  pad_search_iterations = 0;
  balance_evaluations = 0;
}

// ---- public interface ----

NetworkSimulation::NetworkSimulation(const DeviceModel& model, const NetworkOptions& options)
    : impl_(std::make_unique<Impl>(model, options)) {}
NetworkSimulation::~NetworkSimulation() = default;
NetworkSimulation::NetworkSimulation(NetworkSimulation&&) noexcept = default;
NetworkSimulation& NetworkSimulation::operator=(NetworkSimulation&&) noexcept = default;

const DeviceModel& NetworkSimulation::model() const noexcept { return impl_->model; }
const NetworkOptions& NetworkSimulation::options() const noexcept { return impl_->opt; }
std::size_t NetworkSimulation::fluid_cell_count() const noexcept { return impl_->cells; }
std::size_t NetworkSimulation::valve_count() const noexcept { return impl_->valves; }
std::size_t NetworkSimulation::link_count() const noexcept { return impl_->links.size(); }
std::size_t NetworkSimulation::sensor_count() const noexcept { return impl_->sensors.size(); }
std::size_t NetworkSimulation::node_count() const noexcept { return impl_->nodes; }
std::size_t NetworkSimulation::factor_nonzeros() const noexcept { return impl_->ldl.factor_nonzeros(); }
std::uint64_t NetworkSimulation::pad_searches() const noexcept { return impl_->pad_searches; }
std::uint64_t NetworkSimulation::pad_search_iterations() const noexcept {
  return impl_->pad_search_iterations;
}
std::uint64_t NetworkSimulation::balance_evaluations() const noexcept { return impl_->balance_evaluations; }

Status NetworkSimulation::set_valve_yield_stress_Pa(std::span<const double> yield_Pa) noexcept {
  Impl& m = *impl_;
  if (const Status s = check_inputs(yield_Pa, m.valves, std::numeric_limits<double>::infinity());
      s != Status::ok) {
    return s;
  }
  std::copy(yield_Pa.begin(), yield_Pa.end(), m.valve_tau.begin());
  m.phase = 0;
  return Status::ok;
}

Status NetworkSimulation::set_contacts(std::span<const Contact> contacts) noexcept {
  Impl& m = *impl_;
  if (contacts.size() > kMaxContacts) {
    return Status::out_of_range;
  }
  for (const Contact& c : contacts) {
    if (!std::isfinite(c.x_m) || !std::isfinite(c.y_m) || !std::isfinite(c.radius_m) ||
        !std::isfinite(c.indentation_m) || !std::isfinite(c.force_N)) {
      return Status::not_finite;
    }
    if (c.radius_m < 0.0 || c.force_N < 0.0) {
      return Status::negative;
    }
    if (c.radius_m == 0.0 || (c.mode == Contact::Mode::indentation && c.indentation_m >= m.cell_depth) ||
        (c.mode != Contact::Mode::indentation && c.mode != Contact::Mode::force)) {
      return Status::out_of_range;
    }
  }
  for (std::size_t c = 0; c < contacts.size(); ++c) {
    // A force-mode contact already in place starts its search from its last indentation.
    const bool keep = contacts[c].mode == Contact::Mode::force && c < m.contact_count && !m.direct_depths;
    if (!keep) {
      m.contact_ind[c] = contacts[c].indentation_m;
    }
    m.contacts[c] = contacts[c];
  }
  for (std::size_t c = contacts.size(); c < kMaxContacts; ++c) {
    m.contact_ind[c] = 0.0;
    m.contact_force[c] = 0.0;
  }
  m.contact_count = contacts.size();
  m.direct_depths = false;
  m.phase = 0;
  return Status::ok;
}

Status NetworkSimulation::set_cell_indentation_m(std::span<const double> depth_m) noexcept {
  Impl& m = *impl_;
  if (const Status s = check_inputs(depth_m, m.cells, m.cell_depth); s != Status::ok) {
    return s;
  }
  std::copy(depth_m.begin(), depth_m.end(), m.direct_depth.begin());
  m.direct_depths = true;
  m.contact_count = 0;
  m.contact_ind.fill(0.0);
  m.contact_force.fill(0.0);
  m.phase = 0;
  return Status::ok;
}

void NetworkSimulation::reset() noexcept { impl_->reset(); }

Result<StepReport> NetworkSimulation::step(double dt_s) noexcept {
  Impl& m = *impl_;
  m.phase = 0;
  if (!std::isfinite(dt_s)) {
    return failure<StepReport>(Status::not_finite);
  }
  if (!(dt_s > 0.0)) {
    return failure<StepReport>(Status::out_of_range);
  }
  bool force_mode = false;
  for (std::size_t c = 0; c < m.contact_count && !m.direct_depths; ++c) {
    force_mode = force_mode || m.contacts[c].mode == Contact::Mode::force;
  }
  const std::array<double, kMaxContacts> ind_before = m.contact_ind;
  Status s = Status::ok;
  if (force_mode) {
    s = m.solve_force_contacts(dt_s);
  } else {
    m.compute_depths();
    s = m.run_trial(dt_s);
  }
  if (s != Status::ok) {
    m.contact_ind = ind_before;  // the state and inputs stay as they were
    return failure<StepReport>(s);
  }
  m.commit(dt_s);
  return {m.report};
}

bool NetworkSimulation::step_in_progress() const noexcept { return impl_->phase != 0; }

std::span<const double> NetworkSimulation::cell_indentation_m() const noexcept { return impl_->d; }
std::span<const double> NetworkSimulation::cell_velocity_m_per_s() const noexcept { return impl_->velocity; }
std::span<const double> NetworkSimulation::cell_pressure_Pa() const noexcept {
  return std::span<const double>(impl_->node_p).first(impl_->cells);
}
std::span<const double> NetworkSimulation::cell_force_N() const noexcept { return impl_->force; }
Status NetworkSimulation::cell_force_at_depth_N(std::span<const double> depth_m,
                                                std::span<const double> gain_m3,
                                                std::span<double> force_N) const noexcept {
  const Impl& m = *impl_;
  if (depth_m.size() != m.cells || force_N.size() != m.cells ||
      (!gain_m3.empty() && gain_m3.size() != m.cells)) {
    return Status::out_of_range;
  }
  const bool gained = !gain_m3.empty();
  for (std::size_t i = 0; i < m.cells; ++i) {
    const double d = depth_m[i];
    const double e = gained ? m.e[i] + gain_m3[i] : m.e[i];
    // As finish_state: the pressure at the new volume, then the pad's push with it.
    force_N[i] = d > 0.0 ? std::max(0.0, m.pad.grad(d) + m.area * m.bulge.grad(m.s_of(d, e))) : 0.0;
  }
  return Status::ok;
}

Status NetworkSimulation::advance_cell_gain(std::span<const double> depth_m, std::span<const double> yield_Pa,
                                            double dt_s, std::span<double> gain_m3) noexcept {
  Impl& m = *impl_;
  if (depth_m.size() != m.cells || gain_m3.size() != m.cells || yield_Pa.size() != m.valves) {
    return Status::out_of_range;
  }
  if (!std::isfinite(dt_s) || !(dt_s > 0.0)) {
    return Status::out_of_range;
  }
  // Every touched cell's pressure first, so that no flow sees another's move; then each touched
  // cell's passages in link order (a passage between two touched cells is evaluated from each
  // side, the same arithmetic: each side's sum is what one pass over the links gives it).
  std::vector<double>& p = m.between_p;
  for (std::size_t i = 0; i < m.cells; ++i) {
    if (depth_m[i] > 0.0) {
      p[i] = m.bulge.grad(m.s_of(depth_m[i], m.e[i] + gain_m3[i]));
    }
  }
  const auto pressure = [&](std::uint32_t n) { return n < m.cells && depth_m[n] > 0.0 ? p[n] : m.node_p[n]; };
  for (std::size_t i = 0; i < m.cells; ++i) {
    if (!(depth_m[i] > 0.0)) {
      continue;
    }
    for (std::uint32_t j = m.cell_links_begin[i]; j < m.cell_links_begin[i + 1]; ++j) {
      const Link& k = m.links[m.cell_links[j]];
      const double x = pressure(k.a) - pressure(k.b);
      const double tau = k.valve < 0 ? 0.0 : yield_Pa[static_cast<std::size_t>(k.valve)];
      const Result<FlowPoint> f = m.model.valve_law().flow_point(x, tau);
      const double q = (f.ok() ? f.value.flow_m3_per_s : 0.0) + m.floor_conductance * x;
      gain_m3[i] += k.a == i ? -(dt_s * q) : dt_s * q;
    }
  }
  return Status::ok;
}

std::span<const double> NetworkSimulation::chamber_pressure_Pa() const noexcept { return impl_->chamber_p; }
double NetworkSimulation::reservoir_pressure_Pa() const noexcept {
  const Impl& m = *impl_;
  return m.reservoir_node == kNone ? m.p0 : m.node_p[static_cast<std::size_t>(m.reservoir_node)];
}
std::span<const double> NetworkSimulation::link_flow_m3_per_s() const noexcept { return impl_->q; }
double NetworkSimulation::total_fluid_volume_change_m3() const noexcept {
  double v = 0.0;
  for (const double x : impl_->e) {
    v += x;
  }
  return v;
}
NetworkEnergy NetworkSimulation::energy() const noexcept {
  const Impl& m = *impl_;
  return NetworkEnergy{m.work, m.stored_energy(), m.dissipated, m.stored_initial};
}
std::span<const double> NetworkSimulation::contact_force_N() const noexcept {
  return std::span<const double>(impl_->contact_force).first(impl_->contact_count);
}
std::span<const double> NetworkSimulation::contact_indentation_m() const noexcept {
  return std::span<const double>(impl_->contact_ind).first(impl_->contact_count);
}

void NetworkSimulation::read_sensors(std::span<double> out) const noexcept {
  const Impl& m = *impl_;
  const std::size_t n = std::min(out.size(), m.sensors.size());
  for (std::size_t k = 0; k < n; ++k) {
    const SensorPlan& s = m.sensors[k];
    double v = 0.0;
    if (s.quantity == SensorQuantity::pressure) {
      if (s.place == PlaceKind::fluid_cell) {
        v = m.node_p[s.index];
      } else if (s.place == PlaceKind::valve) {
        v = m.chamber_p[s.index];
      } else {
        v = reservoir_pressure_Pa();
      }
    } else {
      const std::vector<double>& per_cell = s.quantity == SensorQuantity::displacement ? m.d : m.force;
      if (s.place == PlaceKind::fluid_cell) {
        v = per_cell[s.index];
      } else if (s.cells_end > s.cells_begin) {
        for (std::uint32_t j = s.cells_begin; j < s.cells_end; ++j) {
          v += per_cell[m.sensor_cells[j]];
        }
        v /= static_cast<double>(s.cells_end - s.cells_begin);
      }
    }
    out[k] = v;
  }
}

}  // namespace mrskin::model
