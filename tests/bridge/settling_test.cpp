// Settling of the closed force loop after a force step (docs/requirements.md; docs/bridge.md,
// Settling). Two scenes:
// - "force_step" (the figure): steps of about 1 N up and down on an elastic tissue. The rendered
//   force must be within 2 % of its final value (or of the observer's force error, where larger)
//   no later than 3 coil time constants + 5 ms after the ideal-actuation bound for the same step on
//   the same unit, on every built-in profile whose envelope holds the step.
// - "step" (regression bounds, the first statement of the figure): the brief's first statement
//   (within 2 % of the step in 3 coil time constants + 5 ms) measured on it. Scene "step"
// (scene.hpp): the finger holds at 1.5 mm, then moves on at a constant 5 mm/s, and the tissue's
// damping steps the target force up by 0.3 N at t = 1.0 s of every cycle; at t = 1.6 s the finger
// stops at 4.5 mm and the damping's 0.9 N leaves it (a step down). Measured on the mock's
// perturbed plant (seed 7) against the target the bridge renders (the tissue estimate clamped into
// the envelope), which keeps moving after the step (the elastic part): the band follows it.
//
// Each step is also run with ideal actuation: the same unit with the same history up to the step,
// then every valve of the pressed cell driven straight to the bound (max current up: sealed; zero
// down: open). No controller can move the force faster than that, so the ideal run's arrival in
// the band is the plant's own limit, and the loop is measured against it as well as against the
// brief's figure.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <limits>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/driver/model/coil.hpp"
#include "mrskin/eval/truth_scorer.hpp"
#include "mrskin/sim/open_mock.hpp"

namespace mrskin::bridge {
namespace {

enum class Actuation { loop, seal, open };  // seal, open: every valve of the pressed cells at its bound

constexpr double kStepAt_s = 1.0;       // in each cycle of scene "step": the finger moves on
constexpr double kStepDownAt_s = 1.6;   // ...and stops at 4.5 mm: the damping's force goes
constexpr double kWindowUp_s = 0.4;     // scored after each step (the load lasts 0.6 s)
constexpr double kWindowDown_s = 0.35;  // (the hold lasts 0.4 s)
constexpr double kBandFraction = 0.02;

// One step to measure: a scene on a unit, the step's time in each cycle and the window after it.
struct StepCase {
  std::string_view scene;
  std::string uri;
  double step_at_s = 0.0;
  double window_s = 0.0;
  bool up = true;
  double lead_in_s = 0.0;  // the finger's move before step_at_s (the level before it is the step's start)
  int cycles = 0;          // 0: kCycles
  BridgeOptions options{};
};

// One step's window, tick by tick (1 ms), summed over the cells the finger presses in it.
struct StepWindow {
  double before_N = 0.0;       // the loop's target on the last tick before the step...
  double before_true_N = 0.0;  // ...and the rendered force, both before the lead-in
  bool contained = true;       // the window's last target lies inside the envelope (not clamped)
  double law_step_N = 0.0;     // the scene's tissue law at the slave's true state: end less start
  std::vector<double> target_N;
  std::vector<double> true_N;
  std::vector<double> estimate_N;  // the observer's force
  std::vector<double> law_N;       // the scene's tissue law at the slave's true state
};

// The fluid cells the scene's finger presses at either end of a step.
std::vector<std::size_t> pressed_cells(const Scene& scene, const GridLayout& layout, double from_s,
                                       double to_s) {
  std::vector<double> a(layout.fluid_cell_count());
  std::vector<double> b(layout.fluid_cell_count());
  mrskin::eval::press_scene_finger(scene, from_s, layout, a);
  mrskin::eval::press_scene_finger(scene, to_s, layout, b);
  std::vector<std::size_t> cells;
  for (std::size_t i = 0; i < a.size(); ++i) {
    if (a[i] > 0.0 || b[i] > 0.0) {
      cells.push_back(i);
    }
  }
  return cells;
}

// The case's scene on its unit, synchronous, simulated clock: windows from the step in cycles
// first_cycle..last_cycle. Actuation::seal and ::open run the loop up to the step of first_cycle,
// then drive the pressed cells' valves to that bound for the window and stop there.
std::vector<StepWindow> run_steps(const StepCase& c, int first_cycle, int last_cycle, Actuation actuation,
                                  double& coil_tau_s) {
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  OpenedDevice dev = open_device(c.uri, clock, open);
  coil_tau_s = model::coil_time_constant_s(dev.session->profile()->coil);
  auto scene = make_scene(c.scene);
  Bridge bridge(*dev.session, *scene, c.options);
  sim::MockDeviceTruth truth(*sim::mock_of(dev));
  eval::TruthScorer scorer(truth, sim::mock_of(dev)->layout().fluid_cell_count(), bridge.options());
  bridge.set_tick_watcher(&scorer);
  bridge.set_perf_clock(&clock);
  scene->set_start(clock.now());
  EXPECT_EQ(bridge.enable(), ResultCode::ok);
  const GridLayout& layout = sim::mock_of(dev)->layout();
  std::vector<double> finger(layout.fluid_cell_count());
  std::vector<double> true_N(layout.fluid_cell_count());
  const std::vector<std::size_t> cells = pressed_cells(*scene, layout, c.step_at_s, c.step_at_s + 0.15);
  EXPECT_FALSE(cells.empty());
  std::vector<double> ideal_A(layout.valve_count(), 0.0);
  const auto sum_of = [&cells](std::span<const double> per_cell) {
    double sum = 0.0;
    for (std::size_t i : cells) {
      sum += per_cell[i];
    }
    return sum;
  };

  std::vector<StepWindow> out;
  const double cycle_s = scene->cycle_s();
  const int window_ticks = static_cast<int>(std::lround(c.window_s * 1e3));
  const int ticks = static_cast<int>(std::lround((last_cycle + 1) * cycle_s * 1e3));
  const bool trace = std::getenv("SETTLING_TRACE") != nullptr && actuation == Actuation::loop;
  double before_N = 0.0;
  double before_true_N = 0.0;
  double law_before_N = 0.0;
  int in_window = -1;  // ticks into the current window, -1 outside one
  for (int k = 0; k < ticks; ++k) {
    const double t_s = k * 1e-3;
    const int cycle = static_cast<int>(t_s / cycle_s);
    const double in_cycle_s = t_s - cycle * cycle_s;
    const bool scored = cycle >= first_cycle;
    if (scored && std::fabs(in_cycle_s - c.step_at_s) < 0.5e-3) {
      in_window = 0;
      out.push_back(StepWindow{.before_N = before_N,
                               .before_true_N = before_true_N,
                               .contained = true,
                               .target_N = {},
                               .true_N = {},
                               .estimate_N = {},
                               .law_N = {}});
      if (actuation != Actuation::loop) {
        std::fill(ideal_A.begin(), ideal_A.end(), 0.0);
        for (std::size_t cell : cells) {
          for (std::size_t v : layout.valves_of_cell(cell)) {
            ideal_A[v] = actuation == Actuation::seal ? dev.session->info().max_current_A : 0.0;
          }
        }
      }
    }
    mrskin::eval::press_scene_finger(*scene, t_s, layout, finger, bridge.scale().length);
    sim::mock_of(dev)->set_finger_indentation(finger);
    sim::mock_of(dev)->step(clock.now());
    if (actuation != Actuation::loop && in_window >= 0) {
      (void)dev.session->poll(clock.now());
      EXPECT_EQ(dev.session->send_valve_currents(ideal_A), ResultCode::ok);
    } else {
      (void)bridge.step(clock.now());
    }
    truth.true_forces(true_N);
    const double target = sum_of(bridge.targets_N());
    if (std::fabs(in_cycle_s - (c.step_at_s - c.lead_in_s - 1e-3)) < 0.5e-3) {
      before_N = target;  // the last tick before the step (and its lead-in)
      before_true_N = sum_of(true_N);
      law_before_N = scene->slave_truth(t_s).force_N;
    }
    // SETTLING_TRACE=1: the third cycle's step, every 3 ms (finger, target, true force, estimate).
    if (trace && cycle == 2 && in_cycle_s > c.step_at_s - c.lead_in_s - 0.05 &&
        in_cycle_s < c.step_at_s + c.window_s && k % 3 == 0) {
      const model::CellSolution& solution = bridge.inverse().cells()[cells.front()];
      std::printf("t %.3f finger %.3f mm target %.3f true %.3f estimate %.3f role %s currents", t_s,
                  finger[cells.front()] * 1e3, target, sum_of(true_N), sum_of(bridge.observer().force_N()),
                  model::to_string(solution.role));
      for (std::size_t v : layout.valves_of_cell(cells.front())) {
        std::printf(" %.4f", bridge.currents_A()[v]);
      }
      std::printf("\n");
    }
    if (in_window >= 0) {
      out.back().target_N.push_back(target);
      out.back().true_N.push_back(sum_of(true_N));
      out.back().estimate_N.push_back(sum_of(bridge.observer().force_N()));
      out.back().law_N.push_back(scene->slave_truth(t_s).force_N);
      if (++in_window == window_ticks) {
        in_window = -1;
        out.back().law_step_N = scene->slave_truth(t_s).force_N - law_before_N;
        for (std::size_t i : cells) {  // the envelope of the window's last tick
          const double floor_N = bridge.envelope_floor_N()[i];
          const double ceiling_N = bridge.envelope_ceiling_N()[i];
          const double target_N = bridge.targets_N()[i];
          out.back().contained =
              out.back().contained &&
              !(std::isnan(floor_N) || target_N <= floor_N + 1e-9 || target_N >= ceiling_N - 1e-9);
        }
        if (actuation != Actuation::loop) {
          break;
        }
      }
    }
    clock.advance(std::chrono::milliseconds(1));
  }
  return out;
}

struct StepResponse {
  double step_N = 0.0;         // the step the band is a fraction of
  double settling_s = 0.0;     // loop: last tick outside the band, from the step (window if never in)
  double ideal_s = 0.0;        // ideal actuation: first tick at the step's level (window if never)
  double error_after_N = 0.0;  // loop: mean |error| over the window's second half
  double peak_error_N = 0.0;   // loop: largest |error| in the window
  int ideal_short_ticks = 0;   // ideal actuation: ticks more than 7 % below the law (law >= 0.3 N)
};

// Up: the step is the highest target in the first 20 ms less the last one before it, and the
// loop's band follows its target. Down: the target falls with the drain (its floor is the
// observer's force once the valves are open), so the step is the target at the window's end less
// the last one before it. The ideal run is measured against a fixed level, whatever the target's
// noise does: up, the level the step reaches (before + step); down, its own final force (the
// plant's floor: the tissue's target lies below it).
StepResponse analyse(const StepWindow& loop, const StepWindow& ideal, bool up) {
  StepResponse r;
  const std::size_t n = loop.target_N.size();
  const std::size_t first_20ms = std::min<std::size_t>(21, n);
  r.step_N =
      (up ? *std::max_element(loop.target_N.begin(), loop.target_N.begin() + static_cast<long>(first_20ms))
          : loop.target_N.back()) -
      loop.before_N;
  const double band_N = kBandFraction * std::fabs(r.step_N);
  int last_out = -1;
  double tail_sum = 0.0;
  for (std::size_t j = 0; j < n; ++j) {
    const double error = loop.true_N[j] - loop.target_N[j];
    if (std::fabs(error) > band_N) {
      last_out = static_cast<int>(j);
    }
    r.peak_error_N = std::max(r.peak_error_N, std::fabs(error));
    if (j >= n / 2) {
      tail_sum += std::fabs(error);
    }
  }
  r.settling_s = (last_out + 1) * 1e-3;
  r.error_after_N = tail_sum / static_cast<double>(n - n / 2);
  r.ideal_s = static_cast<double>(n) * 1e-3;
  for (std::size_t j = 0; j < ideal.true_N.size() && j < ideal.law_N.size(); ++j) {
    r.ideal_short_ticks += ideal.law_N[j] >= 0.3 && ideal.true_N[j] < 0.93 * ideal.law_N[j] ? 1 : 0;
  }
  if (!ideal.true_N.empty()) {
    const double level_N = up ? loop.before_N + r.step_N - band_N : ideal.true_N.back() + band_N;
    for (std::size_t j = 0; j < ideal.true_N.size(); ++j) {
      if (up ? ideal.true_N[j] >= level_N : ideal.true_N[j] <= level_N) {
        r.ideal_s = static_cast<double>(j + 1) * 1e-3;
        break;
      }
    }
  }
  return r;
}

// Sanitizer builds run one cycle: they look for memory and threading errors, and the figures are
// the release build's (as closed_loop_test).
#ifdef MRSKIN_SANITIZED
constexpr int kCycles = 1;
#else
constexpr int kCycles = 4;
#endif

struct Measured {
  double limit_s = 0.0;  // 3 coil time constants + 5 ms
  std::vector<StepResponse> steps;
};

// kCycles steps, the loop and the ideal bound, printed one line each.
Measured measure(const char* name, const StepCase& c) {
  double coil_tau_s = 0.0;
  const std::vector<StepWindow> loop = run_steps(c, 0, kCycles - 1, Actuation::loop, coil_tau_s);
  EXPECT_EQ(loop.size(), static_cast<std::size_t>(kCycles));
  Measured m;
  m.limit_s = 3.0 * coil_tau_s + 5e-3;
  std::printf("%s: coil tau %.2f ms, limit %.1f ms (3 tau + 5 ms), band %.0f %% of the step\n", name,
              coil_tau_s * 1e3, m.limit_s * 1e3, kBandFraction * 100.0);
  for (std::size_t i = 0; i < loop.size(); ++i) {
    const std::vector<StepWindow> ideal = run_steps(c, static_cast<int>(i), static_cast<int>(i),
                                                    c.up ? Actuation::seal : Actuation::open, coil_tau_s);
    EXPECT_EQ(ideal.size(), 1U);
    if (ideal.size() != 1U) {
      continue;
    }
    const StepResponse r = analyse(loop[i], ideal[0], c.up);
    std::printf(
        "  step %zu: %+.3f N, loop settled after %5.1f ms, ideal actuation in the band after %5.1f ms "
        "(window %.0f ms), peak |error| %.3f N, mean |error| in the second half %.4f N; ideal actuation "
        "more than 7 %% below the law for %d ms\n",
        i + 1, r.step_N, r.settling_s * 1e3, r.ideal_s * 1e3, c.window_s * 1e3, r.peak_error_N,
        r.error_after_N, r.ideal_short_ticks);
    m.steps.push_back(r);
  }
  return m;
}

// ---- the figure: force steps of about 1 N ----------------------------------------------------

// Scene "force_step" (scene.hpp): the finger stops at 4.8 mm at t = 1.35 s of each cycle after a
// 0.35 s press from a hold at 1.5 mm (up), and at 2.9 mm at t = 3.826 s after 76 ms at 25 mm/s
// (down).
// The target is final from the stop on; each window is the hold that follows.
constexpr double kForceStepUpAt_s = 1.35;
constexpr double kForceStepUpLeadIn_s = 0.35;
constexpr double kForceStepDownAt_s = 3.826;
constexpr double kForceStepWindow_s = 0.6;
constexpr double kFinal_s = 0.05;  // the final value: the last 50 ms of the window

// The brief's settling (docs/requirements.md): the band is 2 % of the rendered force's final
// value, or the observer's force error there where larger; the loop settles at its last tick
// outside the band. The ideal-actuation bound branches from the loop's own state at the stop
// (the same unit, the same history): every valve of the pressed cells sealed, or all open, from
// then on; the first tick either run spends inside the band is the bound, as no actuation that
// switches later gets there sooner.
struct FinalSettling {
  double step_N = 0.0;            // final value less the rendered force before the lead-in
  double law_step_N = 0.0;        // the scene's force step (its tissue law at the slave's true state)
  double final_N = 0.0;           // rendered (true) force, mean over the window's last 50 ms
  double observer_error_N = 0.0;  // mean |estimate - true| over the window's last 50 ms
  double band_N = 0.0;
  double settling_s = 0.0;      // the loop's last tick outside the band, from the stop
  double ideal_s = 0.0;         // the bound (the window if neither run gets there)
  bool ideal_sealed = false;    // the bound is the sealed run's
  double target_error_N = 0.0;  // final value less the target's mean over the last 50 ms
};

// The first tick at which the run is inside [final - band, final + band].
double first_inside_s(const StepWindow& run, double final_N, double band_N) {
  for (std::size_t j = 0; j < run.true_N.size(); ++j) {
    if (std::fabs(run.true_N[j] - final_N) <= band_N) {
      return static_cast<double>(j + 1) * 1e-3;
    }
  }
  return std::numeric_limits<double>::infinity();
}

FinalSettling analyse_final(const StepWindow& loop, const StepWindow& sealed, const StepWindow& open) {
  FinalSettling r;
  const std::size_t n = loop.true_N.size();
  const std::size_t tail = std::min<std::size_t>(n, static_cast<std::size_t>(std::lround(kFinal_s * 1e3)));
  double target_N = 0.0;
  for (std::size_t j = n - tail; j < n; ++j) {
    r.final_N += loop.true_N[j] / static_cast<double>(tail);
    target_N += loop.target_N[j] / static_cast<double>(tail);
    r.observer_error_N += std::fabs(loop.estimate_N[j] - loop.true_N[j]) / static_cast<double>(tail);
  }
  r.target_error_N = r.final_N - target_N;
  r.step_N = r.final_N - loop.before_true_N;
  r.law_step_N = loop.law_step_N;
  r.band_N = std::max(kBandFraction * std::fabs(r.final_N), r.observer_error_N);
  int last_out = -1;
  for (std::size_t j = 0; j < n; ++j) {
    if (std::fabs(loop.true_N[j] - r.final_N) > r.band_N) {
      last_out = static_cast<int>(j);
    }
  }
  r.settling_s = (last_out + 1) * 1e-3;
  const double sealed_s = first_inside_s(sealed, r.final_N, r.band_N);
  const double open_s = first_inside_s(open, r.final_N, r.band_N);
  r.ideal_sealed = sealed_s < open_s;
  r.ideal_s = std::min({sealed_s, open_s, static_cast<double>(n) * 1e-3});
  return r;
}

// Every step of the case's cycles on its unit, printed one line each. Returns the steps whose
// final target lay inside the envelope (the others are printed, not held to the figure).
struct Settled {
  std::size_t held = 0;            // steps whose final target lay inside the envelope
  double worst_after_bound_s = 0;  // their largest settling time less the ideal bound
};

Settled settle_steps(const char* name, const StepCase& c, bool expect_figure) {
  const int cycles = c.cycles > 0 ? c.cycles : kCycles;
  double coil_tau_s = 0.0;
  const std::vector<StepWindow> loop = run_steps(c, 0, cycles - 1, Actuation::loop, coil_tau_s);
  EXPECT_EQ(loop.size(), static_cast<std::size_t>(cycles));
  const double allowance_s = 3.0 * coil_tau_s + 5e-3;
  std::printf("%s on %s: coil tau %.2f ms, allowance %.1f ms (3 tau + 5 ms) after the ideal bound\n", name,
              c.uri.c_str(), coil_tau_s * 1e3, allowance_s * 1e3);
  Settled out;
  for (std::size_t i = 0; i < loop.size(); ++i) {
    const auto cycle = static_cast<int>(i);
    const std::vector<StepWindow> sealed = run_steps(c, cycle, cycle, Actuation::seal, coil_tau_s);
    const std::vector<StepWindow> open = run_steps(c, cycle, cycle, Actuation::open, coil_tau_s);
    if (sealed.size() != 1U || open.size() != 1U) {
      ADD_FAILURE() << "step " << i + 1 << ": no ideal run";
      continue;
    }
    const FinalSettling r = analyse_final(loop[i], sealed[0], open[0]);
    std::printf(
        "  step %zu: law %+.3f N, rendered %+.3f N to %.3f N (target %+.4f N from it%s), band %.4f N "
        "(observer %.4f N): ideal bound %5.1f ms (%s), loop settled %5.1f ms (%+5.1f ms)\n",
        i + 1, r.law_step_N, r.step_N, r.final_N, -r.target_error_N, loop[i].contained ? "" : ", clamped",
        r.band_N, r.observer_error_N, r.ideal_s * 1e3, r.ideal_sealed ? "sealed" : "open", r.settling_s * 1e3,
        (r.settling_s - r.ideal_s) * 1e3);
    if (!loop[i].contained) {
      continue;  // the unit cannot render this step's final force: no figure to hold
    }
    ++out.held;
    out.worst_after_bound_s = std::max(out.worst_after_bound_s, r.settling_s - r.ideal_s);
    if (!expect_figure) {
      continue;
    }
    EXPECT_GT(std::fabs(r.law_step_N), 0.9) << "step " << i + 1 << ": not the figure's step of about 1 N";
    EXPECT_EQ(r.law_step_N > 0.0, c.up) << "step " << i + 1;
    EXPECT_LT(r.ideal_s, c.window_s) << "step " << i + 1 << ": no ideal run reaches the band";
    EXPECT_LE(r.settling_s, r.ideal_s + allowance_s + 1e-9) << "step " << i + 1;
  }
  return out;
}

std::size_t expect_settles(const char* name, const StepCase& c) { return settle_steps(name, c, true).held; }

// Scene force_step's up or down step on a unit (cycles 0: kCycles).
StepCase force_step_case(const std::string& uri, bool up, int cycles) {
  return {.scene = "force_step",
          .uri = uri,
          .step_at_s = up ? kForceStepUpAt_s : kForceStepDownAt_s,
          .window_s = kForceStepWindow_s,
          .up = up,
          .lead_in_s = up ? kForceStepUpLeadIn_s : 0.0,
          .cycles = cycles};
}

TEST(Settling, ForceStepsOfOneNewtonOnTheDefaultUnit) {
  for (const bool up : {true, false}) {
    EXPECT_EQ(expect_settles(up ? "up" : "down", force_step_case("mock://?seed=7", up, 0)),
              static_cast<std::size_t>(kCycles))
        << "the default unit renders every step";
  }
}

// The drain-then-seal (BridgeOptions::drain_then_seal) is what meets the figure after the up step:
// without it the threshold currents approach the target slowly from above and the feedback winds
// the request down meanwhile (docs/bridge.md, Settling).
TEST(Settling, WithoutTheDrainThenSealTheUpStepMissesTheFigure) {
  StepCase c = force_step_case("mock://?seed=7", true, 1);
  c.options.drain_then_seal = false;
  const Settled s = settle_steps("up, drain-then-seal off", c, false);
  EXPECT_EQ(s.held, 1U);
  EXPECT_GT(s.worst_after_bound_s, 0.04);  // measured 0.067 s, and the final force 0.12 N short
}

// Every other built-in profile, measured, not run by default (one cycle of the 16x16 takes about
// 70 s here; issue 21): each step is held to the figure where its unit's envelope holds it, and
// printed with "clamped" where it does not (docs/bridge.md, Settling). MRSKIN_SETTLING_PROFILES
// names them (comma-separated; default fingertip-16x16).
TEST(Settling, DISABLED_MeasureForceStepsOnTheOtherBuiltInProfiles) {
  const char* env = std::getenv("MRSKIN_SETTLING_PROFILES");
  const std::string list = env != nullptr ? env : "fingertip-16x16";
  std::size_t from = 0;
  while (from < list.size()) {
    const std::size_t comma = std::min(list.find(',', from), list.size());
    const std::string uri = "mock://" + list.substr(from, comma - from) + "?seed=7";
    from = comma + 1;
    for (const bool up : {true, false}) {
      (void)expect_settles(up ? "up" : "down", force_step_case(uri, up, 1));
    }
  }
}

// ---- the first statement, on the damped tissue (scene "step") --------------------------------

TEST(Settling, ForceStepOnThePerturbedPlant) {
  const Measured m =
      measure("settling",
              {.scene = "step", .uri = "mock://?seed=7", .step_at_s = kStepAt_s, .window_s = kWindowUp_s});
  for (std::size_t i = 0; i < m.steps.size(); ++i) {
    const StepResponse& r = m.steps[i];
    EXPECT_GT(r.step_N, 0.05);
    // The plant's own limit: sealed at once, the force still needs longer than the brief's
    // figure to rise by the step (it builds only as fast as the finger fills the cell's
    // compliance). Fails, and says so, if a plant or a profile ever makes the figure reachable.
    EXPECT_GT(r.ideal_s, m.limit_s) << "the figure is reachable on this plant: assert it";
    // Even sealed from the step, the force stays more than 7 % below the law at the finger's true
    // state for longer than 5 % of a cycle's scored ticks (1826 with the law at 0.3 N or more:
    // tests/bridge/golden/scene_stats_seed7.txt, 4175 over 8 s): no actuation after the step
    // brings step's p95 within 7 % (docs/bridge.md, "The damped step"). Measured 119-125 ms.
    EXPECT_GT(r.ideal_short_ticks, 92) << "ideal actuation meets step's p95: hold the loop to it";
    // Regression bound (docs/bridge.md).
    EXPECT_LT(r.error_after_N, 0.12);  // measured 0.089-0.101 N: the target chatters (docs/bridge.md)
  }
}

TEST(Settling, ForceStepDownOnThePerturbedPlant) {
  const Measured m = measure("settling down", {.scene = "step",
                                               .uri = "mock://?seed=7",
                                               .step_at_s = kStepDownAt_s,
                                               .window_s = kWindowDown_s,
                                               .up = false});
  for (const StepResponse& r : m.steps) {
    EXPECT_LT(r.step_N, -0.3);
    EXPECT_GT(r.ideal_s, m.limit_s) << "the figure is reachable on this plant: assert it";
    EXPECT_LT(r.error_after_N, 0.03);  // regression bound (docs/bridge.md)
  }
}

}  // namespace
}  // namespace mrskin::bridge
