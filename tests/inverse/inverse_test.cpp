// CellInverse: the fast model against DeviceModel, accuracy of the rendered force (evaluated
// with the exact quasi-static model), clamping, release, errors, incremental work, tracking.
// Nothing here is timed; instruction counts are gated by InverseCallgrind.
#include "mrskin/driver/model/inverse.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <limits>
#include <regex>
#include <sstream>
#include <string>
#include <vector>

#include "inverse_cases.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/model/cell.hpp"
#include "mrskin/driver/model/exact_inverse.hpp"

namespace {

using namespace mrskin::model;
using mrskin::test::CaseGenerator;
using mrskin::test::default_model;
using mrskin::test::InverseCase;
using mrskin::test::law_for_force;

std::vector<double> exact_forces(const DeviceModel& m, const InverseCase& c,
                                 std::span<const double> currents) {
  std::vector<double> f(m.layout().fluid_cell_count());
  EXPECT_EQ(exact_rendered_forces_N(m, c.targets, c.states, c.now_s, currents, f), Status::ok);
  return f;
}

std::vector<double> copy(std::span<const double> s) { return {s.begin(), s.end()}; }

std::string read_profile(const std::string& name) {
  std::ifstream in(std::string(MRSKIN_TEST_PROFILE_DIR) + "/" + name + ".toml");
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

// The default 5 x 5, its inverse, and an empty case (no contact anywhere).
class InverseBase : public ::testing::Test {
 protected:
  [[nodiscard]] InverseCase blank(double now_s = 0.0) const {
    return {std::vector<CellImpedanceTarget>(n), std::vector<CellState>(n), now_s};
  }
  // A cell at (d, v) whose law asks for a force `share` of the way up its exact envelope.
  void within_envelope(InverseCase& c, std::size_t cell, double d, double v, double share) const {
    c.states[cell] = {d, v};
    const CellEnvelope e = m.envelope(cell, d, v).value;
    c.targets[cell] = law_for_force(e.force_min_N + share * (e.force_max_N - e.force_min_N), d);
  }
  const DeviceModel m = default_model();
  CellInverse inv{m};
  const std::size_t n{m.layout().fluid_cell_count()};
};
class InverseModel : public InverseBase {};
class InverseSolve : public InverseBase {};
class InverseErrors : public InverseBase {};
class InverseIncremental : public InverseBase {};
class InverseTracking : public InverseBase {};

// ---- the fast model ---------------------------------------------------------------------------

TEST_F(InverseModel, ForwardPressureMatchesDeviceModel) {
  CaseGenerator g(n, 1);
  double worst = 0.0;
  for (int k = 0; k < 3000; ++k) {
    std::vector<double> tau(m.layout().valve_count());
    for (double& x : tau) {
      x = g.u(0.0, 60.0);
    }
    const std::size_t cell = g.rng()() % n;
    const double q = k % 10 == 0 ? 0.0 : std::pow(10.0, g.u(-10.0, -4.0));
    const double exact = m.valve_network_pressure_Pa(cell, q, tau).value;
    const Result<double> fast = inv.valve_pressure_Pa(cell, q, tau);
    ASSERT_TRUE(fast.ok());
    worst = std::max(worst, std::fabs(fast.value - exact) / exact);
  }
  std::printf("fast network pressure: max relative error %.3g over 3000 cases\n", worst);
  EXPECT_LT(worst, 1e-7);
}

// The inverse's law of a cell's valves against DeviceModel's exact law over 2,000 random cases on
// a built-in profile: the worst relative pressure error and the worst force error, as a fraction
// of the design force (a force near 0, a refilling cell, has no relative error). per_valve: a
// yield per valve (30 % of them at 0 Pa), else one yield on every valve.
struct LawErrors {
  double pressure = 0.0;
  double force = 0.0;
};

LawErrors valve_law_errors(const char* name, bool per_valve, unsigned seed) {
  const DeviceModel m(load_profile(std::string(MRSKIN_TEST_PROFILE_DIR) + "/" + name + ".toml"));
  const CellInverse inv(m);
  const std::size_t n = m.layout().fluid_cell_count();
  const double depth = m.profile().design.indentation_m;
  const double area = m.contact().effective_area_m2;
  CaseGenerator g(n, seed);
  std::vector<double> taus(m.layout().valve_count());
  LawErrors worst;
  for (int k = 0; k < 2000; ++k) {
    double tau = 0.0;
    if (per_valve) {
      for (double& x : taus) {
        x = g.u(0.0, 1.0) < 0.3 ? 0.0 : g.u(0.0, 60.0);
      }
    }
    const std::size_t cell = g.rng()() % n;
    if (!per_valve) {
      tau = k % 7 == 0 ? 0.0 : g.u(0.0, 60.0);
    }
    const double rate = k % 5 == 0 ? 0.0 : (k % 2 == 0 ? 1.0 : -1.0) * std::pow(10.0, g.u(-6.0, -1.5));
    const double d = g.u(0.05, 1.0) * depth;
    const double q = std::fabs(area * rate);
    const Result<double> exact = per_valve ? m.valve_network_pressure_Pa(cell, q, taus)
                                           : m.valve_network_pressure_uniform_Pa(cell, q, tau);
    const Result<double> fast =
        per_valve ? inv.valve_pressure_Pa(cell, q, taus) : inv.uniform_valve_pressure_Pa(cell, q, tau);
    EXPECT_TRUE(exact.ok() && fast.ok()) << name;
    if (exact.value > 0.0) {
      worst.pressure = std::max(worst.pressure, std::fabs(fast.value - exact.value) / exact.value);
    } else {
      EXPECT_EQ(fast.value, 0.0) << name;
    }
    const Result<CellLoad> by_law = per_valve ? m.cell_force_at_valve_pressure(cell, d, rate, exact.value)
                                              : m.cell_force_at_yield(cell, d, rate, tau);
    const Result<CellLoad> by_table = m.cell_force_at_valve_pressure(cell, d, rate, fast.value);
    EXPECT_TRUE(by_law.ok() && by_table.ok()) << name;
    EXPECT_EQ(by_law.value.mode, by_table.value.mode) << name << " cell " << cell;
    worst.force = std::max(worst.force, std::fabs(by_table.value.force_N - by_law.value.force_N) /
                                            m.profile().design.force_range_N);
  }
  std::printf("%s, %s: valve pressure max relative error %.3g, cell force %.3g\n", name,
              per_valve ? "a yield per valve" : "one yield", worst.pressure, worst.force);
  return worst;
}

constexpr const char* kBuiltInProfiles[] = {"mr-skin-5x5", "fingertip-16x16", "palm-64x64", "paper-table4"};

// The observer's local force model holds each valve at its own yield (a current on a valve shared
// with a pressed neighbour is not the cell's hold): the same law as the exact one on every
// built-in profile, the zero flow (a cell at rest held by its weakest valve) among the cases.
// Measured: at most 5.0e-8 (paper-table4) and 1.1e-8 of the design force (the 5x5).
TEST(InverseValveLaw, MatchesTheExactLawWithEachValveAtItsOwnYieldOnEveryProfile) {
  for (const char* name : kBuiltInProfiles) {
    const LawErrors worst = valve_law_errors(name, true, 12);
    EXPECT_LT(worst.pressure, 1e-6) << name;
    EXPECT_LT(worst.force, 1e-7) << name;
  }
}

// The tables at one yield stress: the same force as DeviceModel's exact law, on every built-in
// profile. Measured: at most 3.0e-7 (fingertip-16x16) and 5.6e-8 of the design force (palm-64x64).
TEST(InverseUniformLaw, MatchesTheExactLawOnEveryProfile) {
  for (const char* name : kBuiltInProfiles) {
    const LawErrors worst = valve_law_errors(name, false, 11);
    EXPECT_LT(worst.pressure, 1e-6) << name;
    EXPECT_LT(worst.force, 1e-7) << name;
  }
  const DeviceModel m = default_model();
  const CellInverse inv(m);
  EXPECT_EQ(inv.uniform_valve_pressure_Pa(m.layout().fluid_cell_count(), 1e-9, 1.0).status,
            Status::out_of_range);
  EXPECT_EQ(inv.uniform_valve_pressure_Pa(0, -1e-9, 1.0).status, Status::negative);
  EXPECT_EQ(inv.uniform_valve_pressure_Pa(0, 1e-9, std::nan("")).status, Status::not_finite);
  EXPECT_EQ(m.cell_force_at_valve_pressure(0, 1e-3, 0.0, -1.0).status, Status::negative);
  EXPECT_EQ(m.cell_force_at_valve_pressure(0, 0.0, 0.0, 10.0).value.mode, CellMode::released);
}

TEST_F(InverseModel, TablesAreAccurate) {
  std::printf("tables: branch flow max relative error %.3g, current inverse max error %.3g Pa\n",
              inv.branch_table_max_relative_error(), inv.current_table_max_error_Pa());
  EXPECT_LT(inv.branch_table_max_relative_error(), 1e-4);
  // The current inverse round-trips through the model's own yield table.
  EXPECT_LT(inv.current_table_max_error_Pa(), 1e-6);
  const double imax = m.profile().coil.max_current_A;
  for (int k = 0; k <= 100; ++k) {
    const double i = imax * k / 100.0;
    const double tau = m.yield_stress_at_current_Pa(i).value;
    EXPECT_NEAR(inv.current_for_yield_stress_A(tau).value, i, 1e-6 * imax);
  }
  EXPECT_EQ(inv.current_for_yield_stress_A(-1.0).status, Status::negative);
  EXPECT_EQ(inv.current_for_yield_stress_A(1e9).status, Status::out_of_range);
}

TEST_F(InverseModel, EnvelopeMatchesDeviceModel) {
  CaseGenerator g(n, 2);
  for (int k = 0; k < 200; ++k) {
    InverseCase c = blank();
    const std::size_t cell = g.rng()() % n;
    c.states[cell] = {g.u(0.2e-3, 6e-3), k % 5 == 0 ? 0.0 : g.u(0.0, 0.02)};
    c.targets[cell] = g.law();
    ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
    const double v = c.states[cell].rate_m_per_s > 1e-4 ? c.states[cell].rate_m_per_s : 0.0;
    const CellEnvelope e = m.envelope(cell, c.states[cell].indentation_m, v).value;
    const CellSolution& o = inv.cells()[cell];
    EXPECT_NEAR(o.force_min_N, e.force_min_N, 1e-6 * (1.0 + e.force_min_N));
    EXPECT_NEAR(o.force_max_N, e.force_max_N, 1e-4 * (1.0 + e.force_max_N));
  }
}

// ---- accuracy against the exact quasi-static model ----------------------------------------------

// Every target inside its cell's envelope, one cell at a time (corner, edge, inner cells).
TEST_F(InverseSolve, SingleCellTargetsAreMet) {
  CaseGenerator g(n, 3);
  double worst = 0.0;
  for (int k = 0; k < 400; ++k) {
    InverseCase c = blank();
    const std::size_t cell = g.rng()() % n;
    // One draw per statement: a function's arguments are evaluated in an order the compiler picks
    // (g++ right to left, clang left to right), and both must draw the same cases.
    const double depth_m = g.u(0.5e-3, 5e-3);
    const double rate_m_s = k % 4 == 0 ? 0.0 : g.u(2e-4, 0.01);
    const double share = g.u(0.0, 1.0);
    within_envelope(c, cell, depth_m, rate_m_s, share);
    inv.invalidate();
    ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
    const std::vector<double> f = exact_forces(m, c, inv.currents_A());
    worst = std::max(worst, std::fabs(f[cell] - inv.cells()[cell].target_force_N));
    EXPECT_FALSE(inv.report().residual_predicted);
  }
  std::printf("single cell: max |exact force - target| %.3g N over 400 cases\n", worst);
  EXPECT_LT(worst, 2e-5);
}

// Targets made by the exact model from random per-valve currents, on 1-3 cells (neighbours
// included): a solution exists; the inverse must find one.
TEST_F(InverseSolve, JointlyFeasibleTargetsAreMet) {
  CaseGenerator g(n, 4);
  const double imax = m.profile().coil.max_current_A;
  double worst = 0.0;
  double sum2 = 0.0;
  int count = 0;
  for (int k = 0; k < 600; ++k) {
    InverseCase c = blank();
    std::vector<double> truth(m.layout().valve_count());
    for (double& x : truth) {
      x = g.u(0.0, imax);
    }
    const std::size_t contacts = 1 + g.rng()() % 3;
    for (std::size_t j = 0; j < contacts; ++j) {
      c.states[g.rng()() % n] = {g.u(0.5e-3, 5e-3), k % 4 == 0 ? 0.0 : g.u(2e-4, 0.01)};
    }
    const std::vector<double> f = exact_forces(m, c, truth);
    for (std::size_t i = 0; i < n; ++i) {
      if (c.states[i].indentation_m > 0.0) {
        c.targets[i] = law_for_force(f[i], c.states[i].indentation_m);
      }
    }
    inv.invalidate();
    ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
    const std::vector<double> got = exact_forces(m, c, inv.currents_A());
    for (std::size_t i = 0; i < n; ++i) {
      if (c.states[i].indentation_m > 0.0) {
        const double err = std::fabs(got[i] - inv.cells()[i].target_force_N);
        worst = std::max(worst, err);
        sum2 += err * err;
        ++count;
      }
    }
  }
  std::printf("jointly feasible targets, 1-3 cells: max error %.3g N, rms %.3g N over %d cells\n", worst,
              std::sqrt(sum2 / count), count);
  EXPECT_LT(worst, 5e-5);
}

// Independent targets on neighbouring cells may conflict through shared valves: the fast
// allocation is then compared with the slow exact solve of the same objective.
TEST_F(InverseSolve, ConflictingTargetsMatchTheSlowExactSolve) {
  CaseGenerator g(n, 5);
  const std::size_t pair[2] = {m.fluid_cell_index(1, 1).value, m.fluid_cell_index(2, 2).value};
  for (int k = 0; k < 6; ++k) {
    InverseCase c = blank();
    for (const std::size_t cell : pair) {
      const double depth_m = g.u(1.5e-3, 5e-3);
      const double rate_m_s = k % 2 == 0 ? 0.0 : g.u(1e-3, 0.01);
      const double share = g.u(0.0, 1.0);
      within_envelope(c, cell, depth_m, rate_m_s, share);
    }
    inv.invalidate();
    // A cold solve that stalls tries its escapes on the ticks after it, one a tick, the inputs
    // held or not: 8 ticks cover the 8 trials at most. (Conflict 5 stalls at 0.254 N on the
    // first tick, and an escape finds 0.246 N.)
    for (int tick = 0; tick < 8; ++tick) {
      ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
    }
    const std::vector<double> fast = exact_forces(m, c, inv.currents_A());
    double fast2 = 0.0;
    for (const std::size_t cell : pair) {
      const double d = fast[cell] - inv.cells()[cell].target_force_N;
      fast2 += d * d;
    }
    const ExactInverseResult slow =
        solve_inverse_exact(m, c.targets, c.states, c.now_s, inv.currents_A(), {}, 20);
    ASSERT_EQ(slow.status, Status::ok);
    std::printf("conflict %d: fast residual %.3g N, slow exact %.3g N\n", k, std::sqrt(fast2),
                slow.residual_norm_N);
    // Where the targets truly conflict the objective has several minima: the fast allocation may
    // settle a few per cent above the best one the slow search finds.
    EXPECT_LE(std::sqrt(fast2), 1.05 * slow.residual_norm_N + 2e-3);
  }
}

// Every cell of the 5 x 5 pressed, each with its own target: 13 rows on 12 valves, so no levels
// meet every aim and Gauss-Newton never converges. Each tick used to search again (a cold
// restart and up to 8 escapes, 30-100 steps, up to 6.4M instructions a tick on the demo's mock).
// A warm solve now stops at the compromise and searches again only after kSearchWait_s when
// a search found nothing better: a few steps a tick, the residual as a fresh solve's. No tick
// runs more than a Gauss-Newton and a half (max_iterations 12): a search stage stands in for
// the warm solve, except a restart after a warm solve that gave up within 6 steps.
TEST_F(InverseSolve, AnInfeasibleFullPressTracksItsCompromiseWithoutSearchingEveryTick) {
  CaseGenerator g(n, 11);
  InverseCase c = blank();
  std::vector<double> share(n);
  std::vector<double> depth(n);
  for (std::size_t cell = 0; cell < n; ++cell) {
    depth[cell] = g.u(2.5e-3, 3.5e-3);
    share[cell] = g.u(0.1, 0.9);
    within_envelope(c, cell, depth[cell], 0.0, share[cell]);
  }
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
  ASSERT_FALSE(inv.report().converged) << "the case must be infeasible to test what it says";
  long steps = 0;
  int max_steps = 0;
  constexpr int kTicks = 200;
  for (int tick = 1; tick <= kTicks; ++tick) {
    for (std::size_t cell = 0; cell < n; ++cell) {
      c.states[cell].indentation_m = depth[cell] + g.u(-2e-6, 2e-6);  // the observer's noise
    }
    c.now_s = 1e-3 * tick;  // 1 kHz: the wait after a fruitless search ends
    ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
    steps += inv.report().iterations;
    max_steps = std::max(max_steps, inv.report().iterations);
  }
  const double tracked_N = inv.report().residual_norm_N;
  inv.invalidate();
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
  const double fresh_N = inv.report().residual_norm_N;
  const double mean_steps = static_cast<double>(steps) / kTicks;
  std::printf("full press: %.1f steps a tick (max %d); residual tracked %.4f N, fresh %.4f N\n", mean_steps,
              max_steps, tracked_N, fresh_N);
  EXPECT_LE(mean_steps, 6.0);
  EXPECT_LE(max_steps, 18);
  EXPECT_LE(tracked_N, 1.05 * fresh_N + 2e-3);
}

// The wait after a search that found nothing is on the tick's clock, not a count of ticks: the
// same full press searches about as often in a second at 10 kHz as at 1 kHz (with a wait of 64
// ticks it searched ten times as often at 10 kHz). A tick that searches runs more than one step.
TEST_F(InverseSolve, AnInfeasibleFullPressSearchesAsOftenAtAnyTickRate) {
  const auto search_ticks = [&](double rate_Hz) {
    CellInverse fresh(m);
    CaseGenerator g(n, 11);
    InverseCase c = blank();
    std::vector<double> depth(n);
    for (std::size_t cell = 0; cell < n; ++cell) {
      depth[cell] = g.u(2.5e-3, 3.5e-3);
      const double share = g.u(0.1, 0.9);
      within_envelope(c, cell, depth[cell], 0.0, share);
    }
    int searching = 0;
    const int ticks = static_cast<int>(0.5 * rate_Hz);  // half a second
    for (int tick = 0; tick < ticks; ++tick) {
      c.now_s = tick / rate_Hz;
      for (std::size_t cell = 0; cell < n; ++cell) {
        c.states[cell].indentation_m = depth[cell] + g.u(-2e-6, 2e-6);  // the observer's noise
      }
      EXPECT_EQ(fresh.solve(c.targets, c.states, c.now_s), Status::ok);
      searching += fresh.report().iterations > 1 ? 1 : 0;
    }
    return searching;
  };
  const int at_1kHz = search_ticks(1e3);
  const int at_10kHz = search_ticks(1e4);
  std::printf("full press, half a second: %d ticks searching at 1 kHz, %d at 10 kHz\n", at_1kHz, at_10kHz);
  EXPECT_GT(at_1kHz, 0);
  EXPECT_LE(at_10kHz, 2 * at_1kHz + 10);
}

// ---- envelope, semi-activity, staleness ------------------------------------------------------

TEST_F(InverseSolve, TargetsOutsideTheEnvelopeAreClampedAndFlagged) {
  const std::size_t hi = m.fluid_cell_index(2, 2).value;
  const std::size_t lo = m.fluid_cell_index(4, 4).value;
  InverseCase c = blank();
  c.states[hi] = {5e-3, 5e-3};                // deep enough that the valves, not the bulge lock, set F_max
  c.targets[hi] = law_for_force(50.0, 5e-3);  // far above F_max
  c.states[lo] = {4e-3, 5e-3};
  c.targets[lo] = law_for_force(0.0, 4e-3);  // below the viscous floor
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
  const CellSolution& h = inv.cells()[hi];
  const CellSolution& l = inv.cells()[lo];
  EXPECT_TRUE(h.clamped_high);
  EXPECT_FALSE(h.clamped_low);
  EXPECT_TRUE(l.clamped_low);
  EXPECT_EQ(inv.report().clamped_cells, 2u);
  EXPECT_DOUBLE_EQ(h.target_force_N, h.force_max_N);
  EXPECT_DOUBLE_EQ(l.target_force_N, l.force_min_N);
  const double imax = m.profile().coil.max_current_A;
  for (const std::size_t v : m.layout().valves_of_cell(hi)) {
    EXPECT_NEAR(inv.currents_A()[v], imax, 1e-9);
  }
  for (const std::size_t v : m.layout().valves_of_cell(lo)) {
    EXPECT_EQ(inv.currents_A()[v], 0.0);
  }
  const std::vector<double> f = exact_forces(m, c, inv.currents_A());
  EXPECT_NEAR(f[hi], h.force_max_N, 1e-4);
  EXPECT_NEAR(f[lo], l.force_min_N, 1e-9);

  // Shallower, F_max is the bulge lock: the least current that reaches it.
  c.states[hi] = {3e-3, 5e-3};
  c.targets[hi] = law_for_force(50.0, 3e-3);
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
  EXPECT_TRUE(inv.cells()[hi].clamped_high);
  const std::vector<double> g = exact_forces(m, c, inv.currents_A());
  EXPECT_NEAR(g[hi], inv.cells()[hi].force_max_N, 1e-4);
  EXPECT_LT(inv.currents_A()[m.layout().valves_of_cell(hi)[0]], imax);
}

// The floor's parts (for the statistics' clamp causes): the pad membrane and p0 on the pad, as the
// device model has them; a press through open valves adds the drag of its flow on top.
TEST_F(InverseModel, FloorPartsAreTheMembraneAndP0WithTheDragOnTop) {
  const ContactPatch& patch = m.contact();
  EXPECT_EQ(inv.floor_parts(0.0).membrane_N, 0.0);
  for (const double d : {0.5e-3, 2e-3, 4e-3}) {
    const CellInverse::FloorParts parts = inv.floor_parts(d);
    EXPECT_NEAR(parts.membrane_N, pad_membrane_force_N(patch, d).value, 1e-9 * (1.0 + parts.membrane_N)) << d;
    EXPECT_DOUBLE_EQ(parts.preload_N, m.profile().reservoir.initial_pressure_Pa * patch.effective_area_m2);
  }
  const std::size_t cell = m.fluid_cell_index(2, 2).value;
  InverseCase c = blank();
  c.states[cell] = {3e-3, 10e-3};  // loading: flow through the open valves
  c.targets[cell] = law_for_force(0.0, 3e-3);
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
  const CellInverse::FloorParts parts = inv.floor_parts(3e-3);
  EXPECT_GT(inv.cells()[cell].force_min_N - parts.membrane_N - parts.preload_N, 0.0);
}

TEST_F(InverseSolve, UnloadingAndUntouchedCellsAreReleased) {
  const std::size_t centre = m.fluid_cell_index(2, 2).value;
  const std::size_t corner = m.fluid_cell_index(0, 0).value;
  const std::size_t next = m.fluid_cell_index(1, 1).value;  // shares two valves with the centre
  InverseCase c{std::vector<CellImpedanceTarget>(n, law_for_force(1.2, 4e-3)), std::vector<CellState>(n),
                0.0};
  c.states[centre] = {4e-3, 0.0};
  c.states[corner] = {4e-3, -5e-3};  // unloading, no loaded neighbour
  c.states[next] = {4e-3, -5e-3};    // unloading, next to the loaded centre
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
  EXPECT_EQ(inv.cells()[corner].role, CellRole::unloading);
  EXPECT_EQ(inv.cells()[centre].role, CellRole::holding);
  EXPECT_EQ(inv.report().loaded_cells, 1u);
  const auto& centre_valves = m.layout().valves_of_cell(centre);
  for (std::size_t v = 0; v < m.layout().valve_count(); ++v) {
    const bool needed = std::find(centre_valves.begin(), centre_valves.end(), v) != centre_valves.end();
    if (needed) {
      EXPECT_GT(inv.currents_A()[v], 0.0) << v;
    } else {
      EXPECT_EQ(inv.currents_A()[v], 0.0) << v;  // the corner's and the rest: released
    }
  }
  // Lifting the finger off the centre releases everything.
  c.states[centre] = {4e-3, -5e-3};
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
  for (const double i : inv.currents_A()) {
    EXPECT_EQ(i, 0.0);
  }
  // A hold within the observer's noise band stays a hold.
  c.states[centre] = {4e-3, -0.5e-4};
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
  EXPECT_EQ(inv.cells()[centre].role, CellRole::holding);
}

TEST_F(InverseSolve, StaleTargetsAreReleased) {
  const std::size_t centre = m.fluid_cell_index(2, 2).value;
  InverseCase c = blank(10.0);
  c.states[centre] = {4e-3, 0.0};
  c.targets[centre] = law_for_force(1.2, 4e-3);
  c.targets[centre].valid_until_s = 10.5;
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
  EXPECT_GT(inv.currents_A()[m.layout().valves_of_cell(centre)[0]], 0.0);
  // Same inputs, later clock: the target expires by itself.
  ASSERT_EQ(inv.solve(c.targets, c.states, 11.0), Status::ok);
  EXPECT_EQ(inv.cells()[centre].role, CellRole::expired);
  for (const double i : inv.currents_A()) {
    EXPECT_EQ(i, 0.0);
  }
}

TEST_F(InverseSolve, NoContactWantsNothing) {
  InverseCase c{std::vector<CellImpedanceTarget>(n, law_for_force(2.0, 1e-3)), std::vector<CellState>(n),
                0.0};
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
  EXPECT_EQ(inv.report().loaded_cells, 0u);
  EXPECT_EQ(inv.report().residual_norm_N, 0.0);
  for (const double i : inv.currents_A()) {
    EXPECT_EQ(i, 0.0);
  }
}

// ---- errors -----------------------------------------------------------------------------------

TEST_F(InverseErrors, BadInputsAreRefusedAndNothingChanges) {
  const std::size_t centre = m.fluid_cell_index(2, 2).value;
  InverseCase good{std::vector<CellImpedanceTarget>(n, law_for_force(1.0, 4e-3)), std::vector<CellState>(n),
                   0.0};
  good.states[centre] = {4e-3, 2e-3};
  ASSERT_EQ(inv.solve(good.targets, good.states, good.now_s), Status::ok);
  const std::vector<double> currents = copy(inv.currents_A());
  const std::vector<CellSolution> cells(inv.cells().begin(), inv.cells().end());
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const double inf = std::numeric_limits<double>::infinity();
  struct Bad {
    const char* what;
    void (*apply)(InverseCase&, std::size_t, double, double);
    Status expect;
  };
  const Bad bad[] = {
      {"NaN indentation",
       [](InverseCase& c, std::size_t i, double x, double) { c.states[i].indentation_m = x; },
       Status::not_finite},
      {"Inf rate", [](InverseCase& c, std::size_t i, double, double y) { c.states[i].rate_m_per_s = y; },
       Status::not_finite},
      {"NaN stiffness",
       [](InverseCase& c, std::size_t i, double x, double) { c.targets[i].stiffness_N_per_m = x; },
       Status::not_finite},
      {"Inf ceiling",
       [](InverseCase& c, std::size_t i, double, double y) { c.targets[i].force_ceiling_N = y; },
       Status::not_finite},
      {"NaN validity",
       [](InverseCase& c, std::size_t i, double x, double) { c.targets[i].valid_until_s = x; },
       Status::not_finite},
      {"negative stiffness",
       [](InverseCase& c, std::size_t i, double, double) { c.targets[i].stiffness_N_per_m = -1.0; },
       Status::negative},
      {"negative damping",
       [](InverseCase& c, std::size_t i, double, double) { c.targets[i].damping_N_s_per_m = -1e-9; },
       Status::negative},
      {"negative ceiling",
       [](InverseCase& c, std::size_t i, double, double) { c.targets[i].force_ceiling_N = -1.0; },
       Status::negative},
      {"exponent 0", [](InverseCase& c, std::size_t i, double, double) { c.targets[i].exponent = 0.0; },
       Status::out_of_range},
      {"exponent 9", [](InverseCase& c, std::size_t i, double, double) { c.targets[i].exponent = 9.0; },
       Status::out_of_range},
      {"through the floor",
       [](InverseCase& c, std::size_t i, double, double) { c.states[i].indentation_m = 0.04; },
       Status::out_of_range},
      {"rate 20 m/s", [](InverseCase& c, std::size_t i, double, double) { c.states[i].rate_m_per_s = 20.0; },
       Status::out_of_range},
  };
  for (const Bad& b : bad) {
    for (const std::size_t cell : {centre, std::size_t{0}, n - 1}) {
      InverseCase c = good;
      b.apply(c, cell, nan, inf);
      EXPECT_EQ(inv.solve(c.targets, c.states, 0.0), b.expect) << b.what << " at cell " << cell;
      EXPECT_EQ(inv.report().status, b.expect);
      EXPECT_EQ(inv.report().error_cell, cell) << b.what;
      EXPECT_EQ(copy(inv.currents_A()), currents) << b.what;
      EXPECT_EQ(std::memcmp(inv.cells().data(), cells.data(), n * sizeof(CellSolution)), 0) << b.what;
    }
  }
  EXPECT_EQ(inv.solve(good.targets, good.states, nan), Status::not_finite);
  EXPECT_EQ(inv.solve(std::span(good.targets).first(n - 1), good.states, 0.0), Status::out_of_range);
  EXPECT_EQ(inv.solve(good.targets, std::span(good.states).first(1), 0.0), Status::out_of_range);
  EXPECT_EQ(copy(inv.currents_A()), currents);
  // Valid again: the same answer as before the bad calls.
  ASSERT_EQ(inv.solve(good.targets, good.states, good.now_s), Status::ok);
  EXPECT_EQ(copy(inv.currents_A()), currents);
  static_assert(noexcept(inv.solve(good.targets, good.states, 0.0)));
}

TEST(InverseConstruction, RejectsBadOptionsAndUnsupportedGraphs) {
  const DeviceModel m = default_model();
  InverseOptions o;
  o.force_tolerance_N = 0.0;
  EXPECT_THROW(CellInverse(m, o), mrskin::InvalidArgument);
  o = {};
  o.hold_rate_tolerance_m_per_s = std::numeric_limits<double>::quiet_NaN();
  EXPECT_THROW(CellInverse(m, o), mrskin::InvalidArgument);
  // A chamber whose passages are on different coils.
  std::string t = read_profile("mr-skin-5x5");
  t = std::regex_replace(t, std::regex("rows = 5"), "rows = 1");
  t = std::regex_replace(t, std::regex("cols = 5"), "cols = 3");
  t = std::regex_replace(t, std::regex("topology = \"chamber\""), "topology = \"explicit\"");
  t = std::regex_replace(t, std::regex("reservoir = \"edge_valves\""), "reservoir = \"none\"");
  t = std::regex_replace(t, std::regex("cell = \"2,2\""), "cell = \"0,0\"");
  t += "\n[[hydraulics.link]]\nfrom = \"cell 0,0\"\nto = \"chamber 0,1\"\nvalve = \"0,1\"\n"
       "[[hydraulics.link]]\nfrom = \"chamber 0,1\"\nto = \"cell 0,2\"\nvalve = \"none\"\n";
  const DeviceModel mixed(parse_profile(t, "mixed.toml"));
  try {
    const CellInverse inv(mixed);
    ADD_FAILURE() << "a chamber on two coils was accepted";
  } catch (const mrskin::InvalidArgument& e) {
    EXPECT_NE(std::string(e.what()).find("same valve"), std::string::npos) << e.what();
  }
}

// ---- incremental work ---------------------------------------------------------------------------

// A search spread over ticks ends with its conflict: after invalidate() and targets whose demands
// no longer conflict, held inputs cost nothing again (a search left under way re-solved its
// component every tick). The pair conflict is ConflictingTargetsMatchTheSlowExactSolve's last.
TEST_F(InverseIncremental, ASearchEndsWithItsConflict) {
  CaseGenerator g(n, 5);
  const std::size_t pair[2] = {m.fluid_cell_index(1, 1).value, m.fluid_cell_index(2, 2).value};
  InverseCase c = blank();
  for (int k = 0; k < 6; ++k) {
    c = blank();
    for (const std::size_t cell : pair) {
      const double depth_m = g.u(1.5e-3, 5e-3);
      const double rate_m_s = k % 2 == 0 ? 0.0 : g.u(1e-3, 0.01);
      const double share = g.u(0.0, 1.0);
      within_envelope(c, cell, depth_m, rate_m_s, share);
    }
  }
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
  ASSERT_FALSE(inv.report().converged) << "the case must stall to test what it says";
  inv.invalidate();
  for (const std::size_t cell : pair) {
    within_envelope(c, cell, 3e-3, 0.0, 0.5);  // the same demand: no valve above its cell's
  }
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
  ASSERT_EQ(inv.report().iterations, 0) << "the new demands must not conflict";
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
  EXPECT_TRUE(inv.report().from_cache);
  EXPECT_EQ(inv.report().components_solved, 0u);
}

// loaded_cells() is what a caller walks instead of every cell's role: it must be exactly the
// cells holding or loading after each solve, ascending, and keep its last list on a refused call.
TEST_F(InverseIncremental, LoadedCellsAreTheHoldingAndLoadingCellsInOrder) {
  const auto loaded_by_role = [&] {
    std::vector<std::uint32_t> out;
    for (std::size_t i = 0; i < n; ++i) {
      const CellRole r = inv.cells()[i].role;
      if (r == CellRole::holding || r == CellRole::loading) {
        out.push_back(static_cast<std::uint32_t>(i));
      }
    }
    return out;
  };
  const auto listed = [&] {
    return std::vector<std::uint32_t>(inv.loaded_cells().begin(), inv.loaded_cells().end());
  };
  EXPECT_TRUE(inv.loaded_cells().empty());
  const std::size_t a = m.fluid_cell_index(1, 1).value;
  const std::size_t b = m.fluid_cell_index(3, 3).value;
  InverseCase c = blank();
  within_envelope(c, b, 3e-3, 2e-3, 0.5);  // loading
  within_envelope(c, a, 3e-3, 0.0, 0.5);   // holding
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
  EXPECT_EQ(listed(), (std::vector<std::uint32_t>{static_cast<std::uint32_t>(std::min(a, b)),
                                                  static_cast<std::uint32_t>(std::max(a, b))}));
  EXPECT_EQ(listed(), loaded_by_role());
  // A refused call (a NaN depth) changes nothing.
  InverseCase bad = c;
  bad.states[a].indentation_m = std::numeric_limits<double>::quiet_NaN();
  ASSERT_NE(inv.solve(bad.targets, bad.states, bad.now_s), Status::ok);
  EXPECT_EQ(listed(), loaded_by_role());
  EXPECT_EQ(listed().size(), 2U);
  // The finger leaves a: only b stays loaded; then nothing is.
  c.states[a] = CellState{};
  c.targets[a] = CellImpedanceTarget{};
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s + 1e-3), Status::ok);
  EXPECT_EQ(listed(), std::vector<std::uint32_t>{static_cast<std::uint32_t>(b)});
  EXPECT_EQ(listed(), loaded_by_role());
  ASSERT_EQ(inv.solve(blank(2e-3).targets, blank(2e-3).states, 2e-3), Status::ok);
  EXPECT_TRUE(inv.loaded_cells().empty());
  EXPECT_EQ(listed(), loaded_by_role());
}

// renew_at_rest() is solve() without the per-cell check, for a caller that vouches only the
// validity moved: it may stand only on a successful last solve that left every cell at rest (no
// contact, no indentation; the first solve and a release included), and then gives what solve()
// gives on the same inputs.
TEST_F(InverseIncremental, RenewAtRestStandsOnlyOnASolveThatLeftEveryCellAtRest) {
  EXPECT_FALSE(inv.renew_at_rest(1.0, 0.0));  // nothing solved yet
  InverseCase rest = blank();
  for (CellImpedanceTarget& t : rest.targets) {
    t = law_for_force(1.0, 4e-3);
    t.valid_until_s = 0.5;
  }
  ASSERT_EQ(inv.solve(rest.targets, rest.states, rest.now_s), Status::ok);
  const std::vector<double> first_A(inv.currents_A().begin(), inv.currents_A().end());
  // That solve computed every cell and left each at rest: the same inputs would find them untouched.
  ASSERT_TRUE(inv.renew_at_rest(0.6, 0.0));
  EXPECT_TRUE(inv.report().from_cache);
  EXPECT_EQ(std::vector<double>(inv.currents_A().begin(), inv.currents_A().end()), first_A);
  ASSERT_EQ(inv.solve(rest.targets, rest.states, rest.now_s), Status::ok);
  EXPECT_TRUE(inv.report().from_cache);
  const std::vector<double> at_rest_A(inv.currents_A().begin(), inv.currents_A().end());
  EXPECT_EQ(at_rest_A, first_A);
  ASSERT_TRUE(inv.renew_at_rest(0.6, 1e-3));
  EXPECT_TRUE(inv.report().from_cache);
  EXPECT_EQ(inv.report().status, Status::ok);
  EXPECT_EQ(inv.report().dirty_cells, 0U);
  EXPECT_EQ(std::vector<double>(inv.currents_A().begin(), inv.currents_A().end()), at_rest_A);
  EXPECT_FALSE(inv.renew_at_rest(std::numeric_limits<double>::infinity(), 2e-3));
  EXPECT_FALSE(inv.renew_at_rest(0.7, std::numeric_limits<double>::quiet_NaN()));
  // solve() on the same inputs past their validity agrees: an untouched cell's role has no clock.
  ASSERT_EQ(inv.solve(rest.targets, rest.states, 2.0), Status::ok);
  EXPECT_TRUE(inv.report().from_cache);
  EXPECT_EQ(std::vector<double>(inv.currents_A().begin(), inv.currents_A().end()), at_rest_A);
  ASSERT_TRUE(inv.renew_at_rest(0.7, 2e-3));

  // One cell pressed: the last solve did not leave every cell untouched.
  const std::size_t a = m.fluid_cell_index(2, 2).value;
  InverseCase pressed = rest;
  within_envelope(pressed, a, 3e-3, 0.0, 0.5);
  pressed.targets[a].valid_until_s = 0.5;
  ASSERT_EQ(inv.solve(pressed.targets, pressed.states, 3e-3), Status::ok);
  ASSERT_FALSE(inv.loaded_cells().empty());
  EXPECT_FALSE(inv.renew_at_rest(0.7, 4e-3));
  // Released: the solve that releases the cell touches it and leaves every cell at rest.
  ASSERT_EQ(inv.solve(rest.targets, rest.states, 5e-3), Status::ok);
  EXPECT_FALSE(inv.report().from_cache);
  ASSERT_TRUE(inv.renew_at_rest(0.7, 5e-3));
  EXPECT_EQ(std::vector<double>(inv.currents_A().begin(), inv.currents_A().end()), at_rest_A);
  ASSERT_EQ(inv.solve(rest.targets, rest.states, 5e-3), Status::ok);
  EXPECT_TRUE(inv.report().from_cache);
  EXPECT_TRUE(inv.renew_at_rest(0.7, 6e-3));
  EXPECT_EQ(std::vector<double>(inv.currents_A().begin(), inv.currents_A().end()), at_rest_A);
  // A solve that leaves a cell indented, even unloaded (its target expired), stands for nothing.
  InverseCase expired = rest;
  expired.states[a].indentation_m = 1e-3;
  ASSERT_EQ(inv.solve(expired.targets, expired.states, 1.0), Status::ok);
  EXPECT_EQ(inv.cells()[a].role, CellRole::expired);
  EXPECT_FALSE(inv.renew_at_rest(0.7, 1.001));
  ASSERT_EQ(inv.solve(rest.targets, rest.states, 1.002), Status::ok);
  ASSERT_TRUE(inv.renew_at_rest(0.7, 1.003));
  // A refused solve, or a forgotten cache, leaves nothing to stand on.
  InverseCase bad = rest;
  bad.states[a].indentation_m = std::numeric_limits<double>::quiet_NaN();
  ASSERT_NE(inv.solve(bad.targets, bad.states, 7e-3), Status::ok);
  EXPECT_FALSE(inv.renew_at_rest(0.7, 8e-3));
  ASSERT_EQ(inv.solve(rest.targets, rest.states, 9e-3), Status::ok);
  inv.invalidate();
  EXPECT_FALSE(inv.renew_at_rest(0.7, 1e-2));
  ASSERT_EQ(inv.solve(rest.targets, rest.states, 1.1e-2), Status::ok);
  EXPECT_FALSE(inv.report().from_cache);        // every cell recomputed after invalidate()...
  EXPECT_TRUE(inv.renew_at_rest(0.7, 1.1e-2));  // ...and left at rest
  ASSERT_EQ(inv.solve(rest.targets, rest.states, 1.1e-2), Status::ok);
  EXPECT_TRUE(inv.renew_at_rest(0.7, 1.2e-2));
}

// The equivalence itself: two inverses fed the same ticks, one always solving and one renewing
// wherever it may, leave the same report, currents and cells on every tick (a press and a
// release between stretches at rest, the validity moving every tick).
TEST_F(InverseIncremental, RenewAtRestLeavesWhatSolveLeaves) {
  CellInverse renewing{m};
  const std::size_t a = m.fluid_cell_index(1, 2).value;
  InverseCase rest = blank();
  for (CellImpedanceTarget& t : rest.targets) {
    t = law_for_force(0.8, 3e-3);
  }
  InverseCase pressed = rest;
  within_envelope(pressed, a, 3e-3, 1e-3, 0.5);
  std::size_t renewed = 0;
  for (int tick = 0; tick < 60; ++tick) {
    const double now_s = 1e-3 * tick;
    InverseCase c = (tick >= 20 && tick < 30) ? pressed : rest;
    for (CellImpedanceTarget& t : c.targets) {
      t.valid_until_s = now_s + 0.05;
    }
    ASSERT_EQ(inv.solve(c.targets, c.states, now_s), Status::ok) << tick;
    // The caller's promise: every cell at rest on this tick and the last.
    const bool at_rest_twice = tick > 0 && !(tick >= 20 && tick <= 30);
    if (at_rest_twice && renewing.renew_at_rest(now_s + 0.05, now_s)) {
      ++renewed;
    } else {
      ASSERT_EQ(renewing.solve(c.targets, c.states, now_s), Status::ok) << tick;
    }
    const InverseReport& x = inv.report();
    const InverseReport& y = renewing.report();
    EXPECT_EQ(x.status, y.status) << tick;
    EXPECT_EQ(x.error_cell, y.error_cell) << tick;
    EXPECT_EQ(x.from_cache, y.from_cache) << tick;
    EXPECT_EQ(x.converged, y.converged) << tick;
    EXPECT_EQ(x.residual_predicted, y.residual_predicted) << tick;
    EXPECT_EQ(x.loaded_cells, y.loaded_cells) << tick;
    EXPECT_EQ(x.clamped_cells, y.clamped_cells) << tick;
    EXPECT_EQ(x.dirty_cells, y.dirty_cells) << tick;
    EXPECT_EQ(x.cell_updates, y.cell_updates) << tick;
    EXPECT_EQ(x.valve_updates, y.valve_updates) << tick;
    EXPECT_EQ(x.components_solved, y.components_solved) << tick;
    EXPECT_EQ(x.iterations, y.iterations) << tick;
    EXPECT_EQ(x.residual_norm_N, y.residual_norm_N) << tick;
    EXPECT_EQ(x.max_residual_N, y.max_residual_N) << tick;
    EXPECT_TRUE(std::ranges::equal(inv.currents_A(), renewing.currents_A())) << tick;
    EXPECT_TRUE(std::ranges::equal(inv.loaded_cells(), renewing.loaded_cells())) << tick;
    for (std::size_t i = 0; i < n; ++i) {
      EXPECT_EQ(inv.cells()[i].role, renewing.cells()[i].role) << tick << " cell " << i;
      EXPECT_EQ(inv.cells()[i].target_force_N, renewing.cells()[i].target_force_N) << tick << " cell " << i;
    }
  }
  // Renewed on every tick the caller vouches for (the first solve and the release's solve
  // leave every cell at rest): ticks 1-19 and 31-59.
  EXPECT_EQ(renewed, 48U);
}

TEST_F(InverseIncremental, UnchangedCellsCostNothing) {
  const std::size_t a = m.fluid_cell_index(1, 1).value;
  const std::size_t b = m.fluid_cell_index(2, 2).value;
  const std::size_t far = m.fluid_cell_index(4, 4).value;
  InverseCase c{std::vector<CellImpedanceTarget>(n, law_for_force(1.0, 4e-3)), std::vector<CellState>(n),
                0.0};
  c.states[a] = {4e-3, 2e-3};
  c.states[b] = {3e-3, 2e-3};
  c.states[far] = {3.5e-3, 1e-3};
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
  EXPECT_EQ(inv.report().dirty_cells, n);

  // Nothing changed: the cached currents, no work at all.
  const std::vector<double> before = copy(inv.currents_A());
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s + 1e-3), Status::ok);
  EXPECT_TRUE(inv.report().from_cache);
  EXPECT_EQ(inv.report().cell_updates, 0u);
  EXPECT_EQ(inv.report().valve_updates, 0u);
  EXPECT_EQ(copy(inv.currents_A()), before);

  // State moves within the tolerances and a refreshed validity are not changes either.
  c.states[a].indentation_m += 0.5e-7;
  c.states[b].rate_m_per_s += 0.5e-6;
  c.targets[far].valid_until_s += 1.0;
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
  EXPECT_TRUE(inv.report().from_cache);

  // The far cell moves: only its component (its own valves) is re-solved.
  c.states[far].indentation_m += 1e-4;
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
  EXPECT_FALSE(inv.report().from_cache);
  EXPECT_EQ(inv.report().dirty_cells, 1u);
  EXPECT_EQ(inv.report().components_solved, 1u);
  EXPECT_EQ(inv.report().valve_updates, m.layout().valves_of_cell(far).size());
  const std::vector<double> after = copy(inv.currents_A());
  for (std::size_t v = 0; v < after.size(); ++v) {
    const auto& fv = m.layout().valves_of_cell(far);
    if (std::find(fv.begin(), fv.end(), v) == fv.end()) {
      EXPECT_EQ(after[v], before[v]) << v;
    }
  }

  // One cell of the pair changes its law: the pair's component (6 valves), not the far cell.
  c.targets[a].stiffness_N_per_m *= 1.1;
  ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
  EXPECT_EQ(inv.report().dirty_cells, 1u);
  EXPECT_EQ(inv.report().components_solved, 1u);
  EXPECT_EQ(inv.report().valve_updates, 6u);
}

// ---- tracking -----------------------------------------------------------------------------------

// A finger between two cells presses in and holds, every target changing every tick (1 kHz):
// the allocation tracks with one step a tick; its rendered force stays on target.
TEST_F(InverseTracking, PressAndHoldStaysOnTarget) {
  const std::size_t a = m.fluid_cell_index(1, 1).value;
  const std::size_t b = m.fluid_cell_index(2, 2).value;
  InverseCase c = blank();
  for (const std::size_t cell : {a, b}) {
    c.targets[cell] = {900.0, 1.2, 5.0, 0.0, 0.0, 2.5, 1e9};
  }
  double worst = 0.0;
  int predicted = 0;
  for (int k = 0; k < 1500; ++k) {
    const double time = 1e-3 * k;
    const double d = time < 1.0 ? 0.5e-3 + 4.5e-3 * time : 5e-3;
    const double v = time < 1.0 ? 4.5e-3 : 0.0;
    c.states[a] = {d, v};
    c.states[b] = {0.7 * d, 0.7 * v};
    c.now_s = time;
    ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok);
    predicted += inv.report().residual_predicted ? 1 : 0;
    if (k % 10 == 0) {
      const std::vector<double> f = exact_forces(m, c, inv.currents_A());
      for (const std::size_t cell : {a, b}) {
        worst = std::max(worst, std::fabs(f[cell] - inv.cells()[cell].target_force_N));
      }
    }
  }
  std::printf("tracking a two-cell press: max |exact force - target| %.3g N (%d of 1500 ticks one step)\n",
              worst, predicted);
  EXPECT_LT(worst, 2e-3);
  EXPECT_GT(predicted, 0);
}

// ---- other grids and topologies -------------------------------------------------------------

TEST(InverseProfiles, OtherGridsAndTopologiesSolve) {
  for (const char* name : {"fingertip-16x16", "palm-64x64", "paper-table4"}) {
    const DeviceModel m(load_profile(std::string(MRSKIN_TEST_PROFILE_DIR) + "/" + name + ".toml"));
    CellInverse inv(m);
    const double depth = m.profile().design.indentation_m;
    // Full contact (a palm: the large-component path), each cell at its own target.
    const std::size_t n = m.layout().fluid_cell_count();
    CaseGenerator g(n, 6);
    InverseCase c{std::vector<CellImpedanceTarget>(n), std::vector<CellState>(n), 0.0};
    for (std::size_t i = 0; i < n; ++i) {
      c.states[i] = {g.u(0.3, 1.0) * depth, g.u(0.0, 1.0) < 0.3 ? 0.0 : g.u(0.0, 0.01)};
      c.targets[i] =
          law_for_force(g.u(0.0, 1.0) * m.profile().design.force_range_N, c.states[i].indentation_m);
    }
    ASSERT_EQ(inv.solve(c.targets, c.states, c.now_s), Status::ok) << name;
    EXPECT_EQ(inv.report().loaded_cells, n) << name;
    for (const double i : inv.currents_A()) {
      ASSERT_TRUE(i >= 0.0 && i <= m.profile().coil.max_current_A) << name;
    }
    std::printf("%s, full contact: %zu components, residual norm %.3g N over %zu cells\n", name,
                inv.report().components_solved, inv.report().residual_norm_N, n);
  }
  // The "direct" topology: single passages between cells (branch shape m = 0).
  std::string t = read_profile("mr-skin-5x5");
  t = std::regex_replace(t, std::regex("topology = \"chamber\""), "topology = \"direct\"");
  const DeviceModel m(parse_profile(t, "direct.toml"));
  CellInverse inv(m);
  CaseGenerator g(m.layout().fluid_cell_count(), 7);
  double worst = 0.0;
  for (int k = 0; k < 100; ++k) {
    std::vector<double> tau(m.layout().valve_count());
    for (double& x : tau) {
      x = g.u(0.0, 60.0);
    }
    const std::size_t cell = g.rng()() % m.layout().fluid_cell_count();
    const double q = std::pow(10.0, g.u(-9.0, -5.0));
    const double exact = m.valve_network_pressure_Pa(cell, q, tau).value;
    worst = std::max(worst, std::fabs(inv.valve_pressure_Pa(cell, q, tau).value - exact) / exact);
  }
  EXPECT_LT(worst, 1e-7);
}

// Every fluid cell pressed at once, each to its own law, so that no levels meet every aim: per
// cell a start depth, a rate (a share of the cells still) and a force at the start depth, drawn
// with a fixed seed.
struct EveryCellPressed {
  EveryCellPressed(const DeviceModel& m, unsigned seed, double still_share, double min_rate_m_per_s,
                   double min_force_share)
      : n(m.layout().fluid_cell_count()), base_m(n), rate_m_per_s(n), force_N(n), targets(n), states(n) {
    const double depth = m.profile().design.indentation_m;
    CaseGenerator g(n, seed);
    for (std::size_t i = 0; i < n; ++i) {
      base_m[i] = g.u(0.3, 0.6) * depth;
      rate_m_per_s[i] = still_share > 0.0 && g.u(0.0, 1.0) < still_share ? 0.0 : g.u(min_rate_m_per_s, 0.01);
      force_N[i] = g.u(min_force_share, 1.0) * m.profile().design.force_range_N;
    }
  }
  // The cells t_s after the start, moving on at their rates or held there.
  void at(double t_s, bool moving) {
    for (std::size_t i = 0; i < n; ++i) {
      const double d = base_m[i] + rate_m_per_s[i] * t_s;
      states[i] = {d, moving ? rate_m_per_s[i] : 0.0};
      targets[i] = law_for_force(force_N[i] * d / base_m[i], d);
    }
  }
  std::size_t n;
  std::vector<double> base_m;
  std::vector<double> rate_m_per_s;
  std::vector<double> force_N;
  std::vector<CellImpedanceTarget> targets;
  std::vector<CellState> states;
};

// A solve whole (max_iterations a solve) beside one in steps, on the same ticks.
struct WholeAndStepped {
  CellInverse& whole;
  CellInverse& stepped;
  int most_steps = 0;        // the stepped solve's, in one solve
  int most_whole_steps = 0;  // the whole solve's
  void solve(const EveryCellPressed& p, double now_s) {
    ASSERT_EQ(whole.solve(p.targets, p.states, now_s), Status::ok);
    ASSERT_EQ(stepped.solve(p.targets, p.states, now_s), Status::ok);
    most_steps = std::max(most_steps, stepped.report().iterations);
    most_whole_steps = std::max(most_whole_steps, whole.report().iterations);
  }
  [[nodiscard]] double whole_N() const { return whole.report().residual_norm_N; }
  [[nodiscard]] double stepped_N() const { return stepped.report().residual_norm_N; }
  void print(int tick) const {
    std::printf("tick %3d  residual whole %.5f N (%2d steps)  stepped %.5f N (%d steps)\n", tick, whole_N(),
                whole.report().iterations, stepped_N(), stepped.report().iterations);
  }
};

// A hand on the palm: one component of every fluid cell (the sparse path). By default it takes
// one Gauss-Newton step a solve and goes on from its levels on the next (large_component_steps);
// 0 lets it run max_iterations a solve, as before. Over a held press and a slow press, the
// stepped solve's residual follows the whole solve's within a few ticks, at a bounded cost.
TEST(InverseLargeComponents, StepsOverTheTicksFollowTheWholeSolve) {
  const DeviceModel m(load_profile(std::string(MRSKIN_TEST_PROFILE_DIR) + "/palm-64x64.toml"));
  InverseOptions whole_options;
  whole_options.large_component_steps = 0;
  CellInverse whole(m, whole_options);
  CellInverse stepped(m);
  EveryCellPressed press(m, 6, 0.3, 0.0, 0.0);
  WholeAndStepped both{whole, stepped};
  const double tick_s = 1e-3;
  double sum_whole = 0.0;
  double sum_stepped = 0.0;
  double first_stepped = 0.0;
  double held_whole = 0.0;
  double held_stepped = 0.0;
  for (int k = 0; k < 200; ++k) {
    // 100 ticks held, then 100 ticks pressing on at the rates (each cell its own law).
    press.at(k < 100 ? 0.0 : (k - 100) * tick_s, k >= 100);
    ASSERT_NO_FATAL_FAILURE(both.solve(press, k * tick_s));
    if (k == 0) {
      first_stepped = both.stepped_N();
    }
    if (k == 99) {
      held_whole = both.whole_N();
      held_stepped = both.stepped_N();
    }
    if (k % 10 == 0 || k < 10) {
      both.print(k);
    }
    if (k >= 100) {
      sum_whole += both.whole_N();
      sum_stepped += both.stepped_N();
    }
  }
  std::printf("pressing: mean residual whole %.5f N, stepped %.5f N; most steps a stepped solve %d\n",
              sum_whole / 100, sum_stepped / 100, both.most_steps);
  // Measured (20 sweeps a step): one step a solve, two on a tick whose step stalled (the
  // search's restart); held, 0.451 N after the first tick, 0.3934 against 0.3895 N after 100 (the
  // stepped solve stops where a step gains < 0.1 %); pressing, 0.571 against 0.555 N on average,
  // the first ticks of the press behind.
  EXPECT_LE(both.most_steps, 2);
  EXPECT_LT(held_stepped, 0.9 * first_stepped);  // it went on over the held ticks
  EXPECT_LE(held_stepped, 1.02 * held_whole);
  EXPECT_LE(sum_stepped, 1.05 * sum_whole);
}

// The 5x5 with every fluid cell pressed at once, each to its own law: one component of 13 cells
// on 12 valves, whose aims no levels meet while they press. The bridge's small_component_steps =
// 1 takes one Gauss-Newton step a solve (a search's trial two) and goes on next tick; the
// library's default solves it whole. Over a press and the hold after it, the stepped residual
// follows the whole solve's, at a bounded number of steps a tick.
TEST(InverseSmallComponents, StepsOverTheTicksFollowTheWholeSolve) {
  const DeviceModel m(load_profile(std::string(MRSKIN_TEST_PROFILE_DIR) + "/mr-skin-5x5.toml"));
  CellInverse whole(m);
  InverseOptions stepped_options;
  stepped_options.small_component_steps = 1;
  CellInverse stepped(m, stepped_options);
  EveryCellPressed press(m, 11, 0.0, 0.002, 0.2);
  WholeAndStepped both{whole, stepped};
  const double tick_s = 1e-3;
  double sum_whole = 0.0;
  double sum_stepped = 0.0;
  for (int k = 0; k < 400; ++k) {
    // 200 ticks pressing at the rates, then 200 ticks held.
    press.at(std::min(k, 200) * tick_s, k < 200);
    ASSERT_NO_FATAL_FAILURE(both.solve(press, k * tick_s));
    ASSERT_EQ(stepped.report().loaded_cells, press.n);
    for (const double i : stepped.currents_A()) {
      ASSERT_TRUE(i >= 0.0 && i <= m.profile().coil.max_current_A);
    }
    if (k < 200) {
      sum_whole += both.whole_N();
      sum_stepped += both.stepped_N();
    }
    if (k % 50 == 0 || k < 5) {
      both.print(k);
    }
  }
  std::printf(
      "held %.5f / %.5f N; pressing: mean residual whole %.5f N, stepped %.5f N; most steps a solve "
      "whole %d, stepped %d\n",
      both.whole_N(), both.stepped_N(), sum_whole / 200, sum_stepped / 200, both.most_whole_steps,
      both.most_steps);
  // Measured: pressing 0.1990 against 0.1968 N on average (+1.1 %), held 0.989 against 1.117 N
  // (the two stop at different compromises); at most 3 steps a solve (a solve's own step, or a
  // search tick's tracking step and its trial's two) against 12.
  EXPECT_LE(both.most_steps, 3);
  EXPECT_GT(both.most_whole_steps, both.most_steps);
  EXPECT_LE(both.stepped_N(), 1.02 * both.whole_N());
  EXPECT_LE(sum_stepped, 1.05 * sum_whole);
}

}  // namespace
