// CellObserver's network force model: the whole network, stepped in phases over the ticks
// of ObserverOptions::network_step_s, and each touched cell's undrained law between steps.
#include <algorithm>
#include <cmath>
#include <span>
#include <vector>

#include "mrskin/driver/model/observer.hpp"
#include "observer_impl.hpp"

namespace mrskin::model {

// The whole network, stepped unless its inputs are unchanged and it has settled; a step covers
// network_step_s in ticks (more when untouched: below) and is spread over them.
Status CellObserver::Impl::network_force(double dt_s, bool yields_changed) noexcept {
  const std::size_t cells = depth_m.size();
  bool depths_changed = false;
  for (std::size_t c = 0; c < cells; ++c) {
    const double d = depth_m[c] > options.contact_threshold_m ? depth_m[c] : 0.0;
    depths_changed = depths_changed || d != contact_depth_m[c];
    contact_depth_m[c] = d;
  }
  if (depths_changed) {  // else as last tick
    network_contact =
        std::any_of(contact_depth_m.begin(), contact_depth_m.end(), [](double d) { return d > 0.0; });
  }
  network_inputs_changed = network_inputs_changed || yields_changed || depths_changed;
  state_age_s += dt_s;  // set afresh by a step that ends on this tick, or a settled network
  if (step_phases > 0 && dt_s == step_dt_s) {
    return advance_network(dt_s);  // this tick's inputs wait for the next step
  }
  if (step_phases > 0) {
    // The tick's length changed (a retune) under a step spread over ticks: the ticks it ran
    // are one whole step at the old length, and this tick begins anew.
    step_phases = 0;
    if (const Result<StepReport> r = network->step(step_dt_s * step_tick); !r.ok()) {
      network_inputs_changed = true;
      return r.status;
    }
    step_ticks = step_tick;
    finish_network_step(step_tick, step_dt_s);
  }
  const bool same_inputs = network_primed && !network_inputs_changed;
  if (options.skip_settled_network && same_inputs && network_settled) {
    state_age_s = 0.0;  // nothing flows: its state is this tick's
    restart_gain();
    return Status::ok;  // at rest on the same inputs: the same forces
  }
  // (Depths unchanged: touched only while a finger holds bitwise still, so the test is rare.)
  const bool untouched = same_inputs && std::all_of(contact_depth_m.begin(), contact_depth_m.end(),
                                                    [](double d) { return d == 0.0; });
  // A released skin's slow tail (docs/bridge.md, "Cost per tick"): untouched, no force depends on
  // it, and the network's last step already ran ahead of this tick.
  if (untouched && network_ahead_s >= 0.5 * dt_s) {
    network_ahead_s -= dt_s;
    return Status::ok;
  }
  // The first step after a reset is whole, on its tick: there is no earlier state to show.
  const int spread = network_primed ? step_spread_for(dt_s) : 1;
  int ticks = spread;
  if (options.skip_settled_network && untouched) {
    const double ahead_s = kAheadVolume_m3 / std::max(network_flow_m3_per_s, 1e-300);
    ticks = static_cast<int>(std::clamp(std::floor(ahead_s / dt_s) + 1.0, static_cast<double>(spread),
                                        static_cast<double>(std::max(spread, kMaxAheadTicks))));
  }
  network_ahead_s = 0.0;
  Status s = network->set_valve_yield_stress_Pa(yield_Pa);
  if (s == Status::ok) {
    s = network->set_cell_indentation_m(step_depths(dt_s, spread));
  }
  if (s != Status::ok) {
    return s;
  }
  network_inputs_changed = false;
  const std::span<const double> f = network->cell_force_N();
  std::copy(f.begin(), f.end(), last_force.begin());
  step_ticks = ticks;
  step_spread = spread;
  step_dt_s = dt_s;
  step_tick = 0;
  step_phases = 0;
  const Result<bool> begun = network->begin_step(dt_s * ticks);
  if (!begun.ok()) {
    return recover_network(begun.status, dt_s, 1);
  }
  if (begun.value) {
    finish_network_step(1, dt_s);
    return Status::ok;
  }
  step_phases = 1;
  return advance_network(dt_s);
}

// The ticks of network_step_s at this tick length, 1 to 64 (1 for a stepper not split).
int CellObserver::Impl::step_spread_for(double dt_s) const noexcept {
  if (options.force_stepper != Stepper::linearly_implicit_regularised) {
    return 1;  // a stepper that begin_step does not split takes its step whole, a tick's
  }
  const double ticks = std::floor(options.network_step_s / dt_s + 1e-6);
  return static_cast<int>(std::clamp(ticks, 1.0, double{kMaxSpreadTicks}));
}

// The depths a step spread over `spread` ticks is given: each touched cell's depth carried on at
// its rate to the step's last tick, so that the step's end (implicit Euler) sees the finger where
// it is then, as a whole step each tick sees it one tick behind.
std::span<const double> CellObserver::Impl::step_depths(double dt_s, int spread) noexcept {
  if (spread <= 1) {
    return contact_depth_m;
  }
  const double ahead_s = (spread - 1) * dt_s;
  const double deepest = 0.99 * model.profile().cell_depth_m;
  for (std::size_t c = 0; c < contact_depth_m.size(); ++c) {
    const double d = contact_depth_m[c];
    step_depth_m[c] =
        d > 0.0 ? std::clamp(d + velocity[c] * ahead_s, options.contact_threshold_m, deepest) : 0.0;
  }
  return step_depth_m;
}

// This tick's share of the step in progress: its phases done by the end of the k-th of the
// `spread` ticks are floor(k x phases / spread), at least the first: the last on the last tick,
// so that the state is never committed ahead of the ticks it covers (a commit earlier, and the
// next step begun at once, ran the network faster than the clock: at 10 kHz, 40 ticks a step,
// the demo rendered 0.044 N RMS).
Status CellObserver::Impl::advance_network(double dt_s) noexcept {
  const int spread = step_spread;
  constexpr int kPhases = NetworkSimulation::kStepPhases;
  const int tick = ++step_tick;  // 1 on the tick the step began
  const int due = std::clamp(tick * kPhases / spread, 1, kPhases);
  while (step_phases < due) {
    const Result<bool> r = network->advance_step();
    if (!r.ok()) {
      return recover_network(r.status, dt_s, tick);
    }
    ++step_phases;
    if (r.value) {
      step_phases = 0;
      finish_network_step(tick, dt_s);
      return Status::ok;
    }
  }
  return Status::ok;
}

// A step the stepper's linearisation refused (too long: stiff cells, a jump in the inputs). Rare,
// and dear on the tick it happens.
Status CellObserver::Impl::recover_network(Status failed, double dt_s, int ticks) noexcept {
  ++network_refusals;
  step_phases = 0;                // the network abandoned the step
  network_inputs_changed = true;  // its inputs were not stepped: the next tick steps them
  // The step's check is among its last phases, so a refusal mostly comes on its last tick: the
  // ticks before this one are then the shorter step, and this tick's time is lost, as a whole
  // step's refused tick loses its own (the network's state is a tick older than the tick).
  const bool last_tick = step_ticks <= ticks;
  const int shorter = last_tick ? ticks - 1 : ticks;
  // Nothing is shorter than the tick's own step, whose failure is reported (the estimate of the
  // last good tick stands).
  if (shorter < 1) {
    return failed;
  }
  // The shorter step whole: at most a refused phase and a whole step in this tick, as a refused
  // step and the tick's own did before the phases.
  if (const Result<StepReport> r = network->step(dt_s * shorter); !r.ok()) {
    return r.status;
  }
  network_inputs_changed = last_tick;  // (this tick's inputs wait for the next step)
  step_ticks = shorter;
  finish_network_step(shorter, dt_s);
  if (last_tick) {
    state_age_s = dt_s;  // the state ends a tick before this one
  }
  return Status::ok;
}

// The forces of this tick: each cell's undrained law at its contact depth now, on the fluid the
// network's last step left (between steps the finger moves, the fluid barely does: a step spread
// over 4 ticks gave the forces 3 ticks late without it, demo 0.0113 -> 0.0128 N RMS).
void CellObserver::Impl::network_cell_forces(double dt_s) noexcept {
  if (!network_contact && force_zero) {
    return;
  }
  // The touched cells' fluid moved on since the state (older than this tick once a step is
  // spread over ticks), through their valves as they are now.
  std::span<const double> gain;
  if (state_age_s > 0.0 && network_contact) {
    (void)network->advance_cell_gain(contact_depth_m, yield_Pa, dt_s, gain_m3);  // sized at construction
    gain_moved = true;
    gain = gain_m3;
  }
  (void)network->cell_force_at_depth_N(contact_depth_m, gain, force);  // sized at construction
  force_zero = !network_contact;
}

// A step committed on its tick-th tick: what it moved, and how far it runs ahead of the ticks.
void CellObserver::Impl::finish_network_step(int tick, double dt_s) noexcept {
  const std::size_t cells = depth_m.size();
  network_ahead_s = (step_ticks - tick) * dt_s;
  // The state is the end of the step: one tick ahead of the tick it ends on, as a whole step's is
  // of its own tick (age 0 by that convention); steps that run ahead are untouched (no forces).
  state_age_s = std::min(0.0, static_cast<double>(tick - step_ticks) * dt_s);
  restart_gain();
  // Settled: no force moved more than a micronewton in the step. (The network double-buffers
  // its state: read the forces again after the step.)
  const std::span<const double> after = network->cell_force_N();
  double moved = 0.0;
  for (std::size_t c = 0; c < cells; ++c) {
    moved = std::max(moved, std::abs(after[c] - last_force[c]));
  }
  // And nothing flows: a released skin still refills with no contact force to show it.
  double flow_m3_per_s = 0.0;
  std::fill(outflow.begin(), outflow.end(), 0.0);
  const std::span<const double> q = network->link_flow_m3_per_s();
  const std::vector<HydraulicLink>& links = model.profile().links;
  for (std::size_t l = 0; l < q.size() && l < links.size(); ++l) {
    flow_m3_per_s = std::max(flow_m3_per_s, std::abs(q[l]));
    if (links[l].a.kind == NodeKind::fluid_cell) {
      outflow[links[l].a.index] += q[l];
    }
    if (links[l].b.kind == NodeKind::fluid_cell) {
      outflow[links[l].b.index] -= q[l];
    }
  }
  network_settled = moved <= 1e-6 && flow_m3_per_s <= kSettledFlow_m3_per_s;
  network_flow_m3_per_s = flow_m3_per_s;
  network_primed = true;
}

}  // namespace mrskin::model
