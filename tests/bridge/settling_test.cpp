// Settling of the closed force loop after a force step (docs/requirements.md: within 2 % of the step
// in at most 3 coil time constants of the profile plus 5 ms, in simulated time). Scene "step"
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
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/driver/model/coil.hpp"
#include "mrskin/eval/truth_scorer.hpp"
#include "mrskin/sim/open_mock.hpp"

namespace mrskin::bridge {
namespace {

enum class Actuation { loop, ideal };

constexpr double kStepAt_s = 1.0;       // in each cycle of scene "step": the finger moves on
constexpr double kStepDownAt_s = 1.6;   // ...and stops at 4.5 mm: the damping's force goes
constexpr double kWindowUp_s = 0.4;     // scored after each step (the load lasts 0.6 s)
constexpr double kWindowDown_s = 0.35;  // (the hold lasts 0.4 s)
constexpr double kBandFraction = 0.02;

// One step's window, tick by tick (1 ms), on the pressed (centre) fluid cell.
struct StepWindow {
  double before_N = 0.0;  // the loop's target on the last tick before the step
  std::vector<double> target_N;
  std::vector<double> true_N;
};

// Scene "step" on mock://?seed=7, synchronous, simulated clock: windows of `window_s` from
// step_at_s in cycles first_cycle..last_cycle. Actuation::ideal runs the loop up to the step of
// first_cycle, then drives the centre cell's valves to the bound for the window and stops there.
std::vector<StepWindow> run_steps(int first_cycle, int last_cycle, double step_at_s, double window_s,
                                  Actuation actuation, double& coil_tau_s) {
  const bool up = step_at_s == kStepAt_s;
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  OpenedDevice dev = open_device("mock://?seed=7", clock, open);
  coil_tau_s = model::coil_time_constant_s(dev.session->profile()->coil);
  auto scene = make_scene("step");
  Bridge bridge(*dev.session, *scene);
  sim::MockDeviceTruth truth(*sim::mock_of(dev));
  eval::TruthScorer scorer(truth, sim::mock_of(dev)->layout().fluid_cell_count(), BridgeOptions{});
  bridge.set_tick_watcher(&scorer);
  bridge.set_perf_clock(&clock);
  scene->set_start(clock.now());
  EXPECT_EQ(bridge.enable(), ResultCode::ok);
  const GridLayout& layout = sim::mock_of(dev)->layout();
  std::vector<double> finger(layout.fluid_cell_count());
  std::vector<double> true_N(layout.fluid_cell_count());
  // The finger presses the centre fluid cell alone (scene.hpp).
  mrskin::eval::press_scene_finger(*scene, step_at_s, layout, finger);
  const auto centre =
      static_cast<std::size_t>(std::max_element(finger.begin(), finger.end()) - finger.begin());
  std::vector<double> ideal_A(layout.valve_count(), 0.0);

  std::vector<StepWindow> out;
  const double cycle_s = scene->cycle_s();
  const int window_ticks = static_cast<int>(std::lround(window_s * 1e3));
  const int ticks = static_cast<int>(std::lround((last_cycle + 1) * cycle_s * 1e3));
  const bool trace = std::getenv("SETTLING_TRACE") != nullptr && actuation == Actuation::loop;
  double before_N = 0.0;
  int in_window = -1;  // ticks into the current window, -1 outside one
  for (int k = 0; k < ticks; ++k) {
    const double t_s = k * 1e-3;
    const int cycle = static_cast<int>(t_s / cycle_s);
    const double in_cycle_s = t_s - cycle * cycle_s;
    const bool scored = cycle >= first_cycle;
    if (scored && std::fabs(in_cycle_s - step_at_s) < 0.5e-3) {
      in_window = 0;
      out.push_back(StepWindow{.before_N = before_N, .target_N = {}, .true_N = {}});
      if (actuation == Actuation::ideal) {
        std::fill(ideal_A.begin(), ideal_A.end(), 0.0);
        for (std::size_t v : layout.valves_of_cell(centre)) {
          ideal_A[v] = up ? dev.session->info().max_current_A : 0.0;
        }
      }
    }
    mrskin::eval::press_scene_finger(*scene, t_s, layout, finger);
    sim::mock_of(dev)->set_finger_indentation(finger);
    sim::mock_of(dev)->step(clock.now());
    if (actuation == Actuation::ideal && in_window >= 0) {
      (void)dev.session->poll(clock.now());
      EXPECT_EQ(dev.session->send_valve_currents(ideal_A), ResultCode::ok);
    } else {
      (void)bridge.step(clock.now());
    }
    truth.true_forces(true_N);
    const double target = bridge.targets_N()[centre];
    if (std::fabs(in_cycle_s - (step_at_s - 1e-3)) < 0.5e-3) {
      before_N = target;  // the last tick before the step
    }
    // SETTLING_TRACE=1: the third cycle's step, every 3 ms (finger, target, true force, currents).
    if (trace && cycle == 2 && in_cycle_s > step_at_s - 0.1 && in_cycle_s < step_at_s + 0.45 && k % 3 == 0) {
      std::printf("t %.3f finger %.3f mm rate %.2f mm/s role %d target %.3f true %.3f currents", t_s,
                  finger[centre] * 1e3, bridge.observer().velocity_m_per_s()[centre] * 1e3,
                  static_cast<int>(bridge.inverse().cells()[centre].role), target, true_N[centre]);
      for (std::size_t v : layout.valves_of_cell(centre)) {
        std::printf(" %.4f", bridge.currents_A()[v]);
      }
      std::printf("\n");
    }
    if (in_window >= 0) {
      out.back().target_N.push_back(target);
      out.back().true_N.push_back(true_N[centre]);
      if (++in_window == window_ticks) {
        in_window = -1;
        if (actuation == Actuation::ideal) {
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
Measured measure(const char* name, double step_at_s, double window_s) {
  const bool up = step_at_s == kStepAt_s;
  double coil_tau_s = 0.0;
  const std::vector<StepWindow> loop =
      run_steps(0, kCycles - 1, step_at_s, window_s, Actuation::loop, coil_tau_s);
  EXPECT_EQ(loop.size(), static_cast<std::size_t>(kCycles));
  Measured m;
  m.limit_s = 3.0 * coil_tau_s + 5e-3;
  std::printf("%s: coil tau %.2f ms, limit %.1f ms (3 tau + 5 ms), band %.0f %% of the step\n", name,
              coil_tau_s * 1e3, m.limit_s * 1e3, kBandFraction * 100.0);
  for (std::size_t i = 0; i < loop.size(); ++i) {
    const std::vector<StepWindow> ideal = run_steps(static_cast<int>(i), static_cast<int>(i), step_at_s,
                                                    window_s, Actuation::ideal, coil_tau_s);
    EXPECT_EQ(ideal.size(), 1U);
    if (ideal.size() != 1U) {
      continue;
    }
    const StepResponse r = analyse(loop[i], ideal[0], up);
    std::printf(
        "  step %zu: %+.3f N, loop settled after %5.1f ms, ideal actuation in the band after %5.1f ms "
        "(window %.0f ms), peak |error| %.3f N, mean |error| in the second half %.4f N\n",
        i + 1, r.step_N, r.settling_s * 1e3, r.ideal_s * 1e3, window_s * 1e3, r.peak_error_N,
        r.error_after_N);
    m.steps.push_back(r);
  }
  return m;
}

TEST(Settling, ForceStepOnThePerturbedPlant) {
  const Measured m = measure("settling", kStepAt_s, kWindowUp_s);
  for (std::size_t i = 0; i < m.steps.size(); ++i) {
    const StepResponse& r = m.steps[i];
    EXPECT_GT(r.step_N, 0.05);
    // The plant's own limit: sealed at once, the force still needs longer than the brief's
    // figure to rise by the step (it builds only as fast as the finger fills the cell's
    // compliance). Fails, and says so, if a plant or a profile ever makes the figure reachable.
    EXPECT_GT(r.ideal_s, m.limit_s) << "the figure is reachable on this plant: assert it";
    // Regression bound (docs/bridge.md).
    EXPECT_LT(r.error_after_N, 0.12);  // measured 0.089-0.101 N: the target chatters (docs/bridge.md)
  }
}

TEST(Settling, ForceStepDownOnThePerturbedPlant) {
  const Measured m = measure("settling down", kStepDownAt_s, kWindowDown_s);
  for (const StepResponse& r : m.steps) {
    EXPECT_LT(r.step_N, -0.3);
    EXPECT_GT(r.ideal_s, m.limit_s) << "the figure is reachable on this plant: assert it";
    EXPECT_LT(r.error_after_N, 0.03);  // regression bound (docs/bridge.md)
  }
}

}  // namespace
}  // namespace mrskin::bridge
