// Soaks (label `soak`, outside the default and CI runs: `ctest --preset soak`), issue 25:
//   BridgeTicksAgainstACheapPlant  10^8 bridge ticks (MRSKIN_SOAK_BRIDGE_TICKS) on the simulated
//     clock: the mock device's firmware and wire bytes, DeviceSession and Bridge as in
//     scene_rig.hpp, but above a first-order plant defined here (mock:// offers no cheaper plant
//     than its hydraulic network), the finger and the slave stream from the sweep scene looping.
//   ClosedLoopOnTheMock  10^7 closed-loop ticks (MRSKIN_SOAK_CLOSED_LOOP_TICKS) on the perturbed
//     mock (mock://?seed=1&perturbation=0.15, the default unit), every built-in scene in turn,
//     each for one of its cycles (the finger is out of contact at each switch).
// Both check, every tick: no NaN/Inf in the currents, targets and true forces, every step ok,
// the device enabled; and per window (MRSKIN_SOAK_WINDOW_TICKS, default 10^6, rounded to whole
// scene cycles / rotations): no NaN/Inf in the statistics, the window's counters (from the
// difference of BridgeStats) add up to the ticks run, no link error or fault, and the window's
// rendered-force RMS error of the last windows within kDriftFactor of the first's. One line per
// window. Fixed seeds; nothing is timed (the wall time is printed, never checked).
#include <fmt/core.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/bridge/scene.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/driver/session.hpp"
#include "mrskin/eval/truth_scorer.hpp"
#include "mrskin/sim/mock_device.hpp"
#include "mrskin/sim/open_mock.hpp"
#include "mrskin/sim/plant.hpp"

namespace {

using namespace mrskin;
using namespace mrskin::bridge;

// The last windows' rendered-force RMS error stays within this factor of the first window's
// (both ways: a collapse would mean the finger is no longer scored).
constexpr double kDriftFactor = 1.25;
constexpr std::size_t kLastWindowsCompared = 3;

std::uint64_t count_from_env(const char* name, std::uint64_t fallback) {
  const char* text = std::getenv(name);  // NOLINT(concurrency-mt-unsafe): read once, single thread
  if (text == nullptr || *text == '\0') {
    return fallback;
  }
  char* end = nullptr;
  const double value = std::strtod(text, &end);  // "1e8" as well as "100000000"
  if (end == text || *end != '\0' || !(value >= 1.0) || value > 1e12 || value != std::floor(value)) {
    ADD_FAILURE() << name << "='" << text << "' is not a whole count in [1, 1e12]";
    return fallback;
  }
  return static_cast<std::uint64_t>(value);
}

// A first-order plant, cheap enough for 10^8 ticks: each fluid cell's pad follows the finger
// (its sensors read the pad's depth: a fluid-cell sensor its cell, a valve sensor the mean of the
// cells the valve joins, as the network plant's), and its contact force relaxes with kTau_s
// towards k_open d + min(k_locked d, F_full * mean valve current / full current): soft with the
// valves open, up to F_full with them locked. No hydraulics, no fluid history.
class FirstOrderPlant final : public sim::Plant {
 public:
  explicit FirstOrderPlant(const model::DeviceProfile& profile)
      : profile_(profile),
        layout_(profile.rows, profile.cols),
        max_current_A_(profile.coil.max_current_A > 0.0 ? profile.coil.max_current_A : 1.0),
        depth_m_(layout_.fluid_cell_count(), 0.0),
        force_N_(layout_.fluid_cell_count(), 0.0),
        current_A_(layout_.valve_count(), 0.0) {}

  [[nodiscard]] std::size_t sensor_count() const noexcept override { return profile_.sensors.size(); }
  void set_valve_currents(std::span<const double> current_A) noexcept override {
    const std::size_t n = std::min(current_A.size(), current_A_.size());
    std::copy_n(current_A.begin(), n, current_A_.begin());
  }
  void set_finger_indentation(std::span<const double> indentation_m) noexcept override {
    for (std::size_t i = 0; i < depth_m_.size() && i < indentation_m.size(); ++i) {
      depth_m_[i] = std::max(0.0, indentation_m[i]);
    }
  }
  void step(double dt_s) noexcept override {
    if (dt_s != last_dt_s_) {
      last_dt_s_ = dt_s;
      alpha_ = 1.0 - std::exp(-dt_s / kTau_s);
    }
    for (std::size_t c = 0; c < depth_m_.size(); ++c) {
      const std::vector<std::size_t>& valves = layout_.valves_of_cell(c);
      double sum_A = 0.0;
      for (const std::size_t v : valves) {
        sum_A += std::max(0.0, current_A_[v]);
      }
      const double mean_A = valves.empty() ? 0.0 : sum_A / static_cast<double>(valves.size());
      const double d = depth_m_[c];
      const double held_N = std::min(kLocked_N_per_m * d, kFull_N * std::min(1.0, mean_A / max_current_A_));
      const double steady_N = d > 0.0 ? kOpen_N_per_m * d + held_N : 0.0;
      force_N_[c] += alpha_ * (steady_N - force_N_[c]);
    }
  }
  void read_sensors(std::span<double> out) const noexcept override {
    for (std::size_t k = 0; k < out.size() && k < profile_.sensors.size(); ++k) {
      const model::SensorSpec& s = profile_.sensors[k];
      double value = 0.0;
      if (s.quantity == model::SensorQuantity::displacement && s.place == model::PlaceKind::fluid_cell) {
        value = depth_m_[s.index];
      } else if (s.quantity == model::SensorQuantity::displacement && s.place == model::PlaceKind::valve) {
        const std::vector<std::size_t>& joined = layout_.cells_of_valve(s.index);
        for (const std::size_t c : joined) {
          value += depth_m_[c];
        }
        value /= static_cast<double>(std::max<std::size_t>(joined.size(), 1));
      }
      out[k] = value;
    }
  }
  void contact_forces(std::span<double> out_N) const noexcept override {
    const std::size_t n = std::min(out_N.size(), force_N_.size());
    std::copy_n(force_N_.begin(), n, out_N.begin());
  }

 private:
  static constexpr double kTau_s = 5e-3;
  static constexpr double kOpen_N_per_m = 50.0;
  static constexpr double kLocked_N_per_m = 600.0;
  static constexpr double kFull_N = 2.0;
  model::DeviceProfile profile_;
  GridLayout layout_;
  double max_current_A_;
  std::vector<double> depth_m_;
  std::vector<double> force_N_;
  std::vector<double> current_A_;
  double last_dt_s_ = -1.0;
  double alpha_ = 0.0;
};

// The slave stream and the finger from built-in scenes: one scene looping on its own (its
// script repeats every cycle_s()), or several in turn, each for one cycle, restarted at its
// turn (every cycle starts and ends out of contact, so the finger is lifted at each switch).
class SceneSchedule final : public SlaveSource {
 public:
  explicit SceneSchedule(const std::vector<std::string_view>& names) {
    for (const std::string_view name : names) {
      scenes_.push_back(make_scene(name));
      const auto cycle = static_cast<std::uint64_t>(std::llround(scenes_.back()->cycle_s() * 1000.0));
      cycle_ticks_.push_back(cycle);
      period_ticks_ += cycle;
    }
  }
  void begin(TimePoint now) noexcept {
    current_ = 0;
    left_ = cycle_ticks_[0];
    scenes_[0]->set_start(now);
  }
  // Before each tick: the next scene's turn when this one's cycle is over.
  void advance(TimePoint now) noexcept {
    if (scenes_.size() > 1 && left_ == 0) {
      current_ = (current_ + 1) % scenes_.size();
      left_ = cycle_ticks_[current_];
      scenes_[current_]->set_start(now);
    }
    if (left_ > 0) {
      --left_;
    }
  }
  void finger(TimePoint now, const GridLayout& layout, std::span<double> indentation_m) const noexcept {
    const Scene& s = *scenes_[current_];
    mrskin::eval::press_scene_finger(s, to_seconds(now - s.start()), layout, indentation_m);
  }
  bool latest(TimePoint now, SlaveSample& out) noexcept override {
    return scenes_[current_]->latest(now, out);
  }
  // Ticks after which the schedule repeats: one cycle of each scene.
  [[nodiscard]] std::uint64_t period_ticks() const noexcept { return period_ticks_; }

 private:
  std::vector<std::unique_ptr<Scene>> scenes_;
  std::vector<std::uint64_t> cycle_ticks_;
  std::uint64_t period_ticks_ = 0;
  std::size_t current_ = 0;
  std::uint64_t left_ = 0;
};

bool finite(std::span<const double> values) noexcept {
  return std::all_of(values.begin(), values.end(), [](double v) { return std::isfinite(v); });
}

bool stats_finite(const BridgeStats& s) noexcept {
  const double values[] = {s.force_sq_error_sum_N2,    s.force_max_abs_error_N,  s.true_state_sq_error_sum_N2,
                           s.release_sq_error_sum_N2,  s.max_current_A,          s.inverse_residual_sum_N,
                           s.passivity_energy_J,       s.passivity_min_energy_J, s.force_rms_error_N(),
                           s.true_state_rms_error_N(), s.release_rms_error_N(),  s.clamped_fraction(),
                           s.slave_force.max_N()};
  return finite(values);
}

struct Window {
  std::uint64_t end_tick = 0;
  std::uint64_t ticks = 0;
  bool whole = true;  // a whole window (the remainder of a run is not compared for drift)
  double rms_N = 0.0;
  double true_state_rms_N = 0.0;
  double max_so_far_N = 0.0;  // BridgeStats keeps the maximum since the start only
  double clamp_fraction = 0.0;
  double max_force_N = 0.0;    // largest true contact force in the window
  double max_current_A = 0.0;  // largest valve current the bridge asked for in the window
  std::uint64_t scored = 0;
};

struct SoakOutcome {
  std::vector<Window> windows;
  std::uint64_t ticks_run = 0;
  std::uint64_t failed_steps = 0;
  std::uint64_t nonfinite_ticks = 0;
  std::uint64_t not_enabled_ticks = 0;  // after the device's first ENABLED tick
  std::uint64_t ticks_to_enable = 0;    // enable() is a request: the ticks before its answer
  std::uint64_t first_bad_tick = 0;     // first tick with any of the three above (0: none)
  double wall_s = 0.0;
};

// Runs `ticks` ticks of the rig's closed loop (finger -> mock step -> bridge step -> 1 ms) and
// checks as it goes. window_ticks: a whole number of the schedule's periods.
SoakOutcome soak(const char* label, sim::MockDevice& mock, DeviceSession& session, Bridge& loop,
                 SceneSchedule& schedule, SimulatedClock& clock, std::uint64_t ticks,
                 std::uint64_t window_ticks) {
  SoakOutcome out;
  const GridLayout& layout = mock.layout();
  std::vector<double> finger(layout.fluid_cell_count(), 0.0);
  std::vector<double> truth_N(layout.fluid_cell_count(), 0.0);
  BridgeStats prev = loop.stats();
  SessionCounters prev_counters = session.counters();
  std::uint64_t prev_failed = 0;
  Window w;
  const auto wall0 = std::chrono::steady_clock::now();  // printed only, never checked
  fmt::print("[{}] {} ticks, windows of {} ticks ({}-tick schedule period)\n", label, ticks, window_ticks,
             schedule.period_ticks());
  fmt::print("[{}] {:>12} {:>10} {:>10} {:>10} {:>8} {:>8} {:>9} {:>10}\n", label, "ticks", "rms_N",
             "true_rms_N", "max_err_N", "clamp%", "max_F_N", "max_I_mA", "wall_s");
  std::fflush(stdout);
  schedule.begin(clock.now());
  for (std::uint64_t k = 1; k <= ticks; ++k) {
    const TimePoint now = clock.now();
    schedule.advance(now);
    schedule.finger(now, layout, finger);
    mock.set_finger_indentation(finger);
    mock.step(now);
    const ResultCode rc = loop.step(now);
    clock.advance(std::chrono::milliseconds(1));
    mock.true_contact_forces(truth_N);
    const bool ok_step = rc == ResultCode::ok;
    const bool ok_values = finite(loop.currents_A()) && finite(loop.targets_N()) && finite(truth_N);
    const bool enabled = session.state() == DeviceState::enabled;
    if (!enabled && out.ticks_to_enable == k - 1) {
      ++out.ticks_to_enable;  // still waiting for the unit to answer the enable request
    }
    const bool ok_state = (enabled || out.ticks_to_enable == k) && !loop.halted();
    out.failed_steps += ok_step ? 0 : 1;
    out.nonfinite_ticks += ok_values ? 0 : 1;
    out.not_enabled_ticks += ok_state ? 0 : 1;
    if (out.first_bad_tick == 0 && !(ok_step && ok_values && ok_state)) {
      out.first_bad_tick = k;
      fmt::print("[{}] first bad tick {}: step {}, values {}, state {} (mock state {} fault {})\n", label, k,
                 ok_step ? "ok" : "FAILED", ok_values ? "finite" : "NOT FINITE", to_string(session.state()),
                 static_cast<unsigned>(mock.state()), static_cast<unsigned>(mock.fault()));
      std::fflush(stdout);
    }
    for (const double f : truth_N) {
      w.max_force_N = std::max(w.max_force_N, std::abs(f));
    }
    for (const double i : loop.currents_A()) {
      w.max_current_A = std::max(w.max_current_A, std::abs(i));
    }
    ++w.ticks;
    if (w.ticks == window_ticks || k == ticks) {
      const BridgeStats& s = loop.stats();
      const SessionCounters& c = session.counters();
      w.end_tick = k;
      w.whole = w.ticks == window_ticks;
      w.scored = s.force_samples - prev.force_samples;
      const double sq = s.force_sq_error_sum_N2 - prev.force_sq_error_sum_N2;
      const double true_sq = s.true_state_sq_error_sum_N2 - prev.true_state_sq_error_sum_N2;
      w.rms_N = w.scored > 0 ? std::sqrt(sq / static_cast<double>(w.scored)) : 0.0;
      w.true_state_rms_N = w.scored > 0 ? std::sqrt(true_sq / static_cast<double>(w.scored)) : 0.0;
      w.max_so_far_N = s.force_max_abs_error_N;
      const std::uint64_t loaded = s.target_cell_ticks - prev.target_cell_ticks;
      const std::uint64_t clamped = s.clamped_cell_ticks - prev.clamped_cell_ticks;
      w.clamp_fraction = loaded > 0 ? static_cast<double>(clamped) / static_cast<double>(loaded) : 0.0;
      const double wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - wall0).count();
      fmt::print("[{}] {:>12} {:>10.5f} {:>10.5f} {:>10.4f} {:>8.2f} {:>8.4f} {:>9.3f} {:>10.1f}\n", label, k,
                 w.rms_N, w.true_state_rms_N, w.max_so_far_N, 100.0 * w.clamp_fraction, w.max_force_N,
                 1e3 * w.max_current_A, wall_s);
      std::fflush(stdout);

      // Counters: every tick counted once; the window's scored and loaded cell-ticks within
      // what its ticks allow; no link error, fault or catch-up in the window.
      const std::uint64_t cells = layout.fluid_cell_count();
      EXPECT_EQ(s.ticks - prev.ticks, w.ticks) << "window ending at " << k;
      EXPECT_EQ(s.ticks, k);
      EXPECT_EQ(loop.live_ticks(), k);
      EXPECT_GT(w.scored, 0U) << "window ending at " << k << ": nothing scored";
      EXPECT_LE(w.scored, w.ticks * cells);
      EXPECT_LE(loaded, w.ticks * cells);
      EXPECT_LE(clamped, loaded);
      EXPECT_LE(s.slave_samples - prev.slave_samples, w.ticks);
      EXPECT_EQ(s.observer_errors - prev.observer_errors, 0U) << "window ending at " << k;
      EXPECT_EQ(s.inverse_errors - prev.inverse_errors, 0U) << "window ending at " << k;
      EXPECT_EQ(s.send_failures - prev.send_failures, 0U) << "window ending at " << k;
      EXPECT_EQ(s.sensor_faults, 0U);
      EXPECT_EQ(s.sensor_fault_halts, 0U);
      EXPECT_EQ(c.faults, 0U);
      EXPECT_EQ(c.crc_errors - prev_counters.crc_errors, 0U);
      EXPECT_EQ(c.decode_errors - prev_counters.decode_errors, 0U);
      EXPECT_EQ(c.sequence_gaps - prev_counters.sequence_gaps, 0U);
      EXPECT_EQ(c.telemetry_timeouts - prev_counters.telemetry_timeouts, 0U);
      EXPECT_EQ(c.disconnects - prev_counters.disconnects, 0U);
      EXPECT_GE(c.telemetry - prev_counters.telemetry, w.ticks - 1) << "one telemetry packet per tick";
      EXPECT_LE(c.telemetry - prev_counters.telemetry, w.ticks + 1);
      EXPECT_EQ(mock.skipped_time_s(), 0.0);
      // State and values.
      EXPECT_EQ(session.state(), DeviceState::enabled) << "window ending at " << k;
      EXPECT_EQ(mock.fault(), 0U) << "window ending at " << k;
      EXPECT_EQ(out.failed_steps - prev_failed, 0U) << "window ending at " << k;
      EXPECT_TRUE(stats_finite(s)) << "window ending at " << k;
      EXPECT_TRUE(std::isfinite(loop.live_rms_error_N()) && std::isfinite(loop.live_stiffness_N_per_m()));
      EXPECT_TRUE(std::isfinite(w.rms_N) && std::isfinite(w.true_state_rms_N));

      out.windows.push_back(w);
      prev = s;
      prev_counters = c;
      prev_failed = out.failed_steps;
      w = Window{};
    }
  }
  const SessionCounters& c = session.counters();
  fmt::print(
      "[{}] session: sent {}, received {}, telemetry {}, heartbeats {}, faults {}, state {}; mock fault {}\n",
      label, c.sent, c.received, c.telemetry, c.heartbeats, c.faults, to_string(session.state()),
      static_cast<unsigned>(mock.fault()));
  out.ticks_run = ticks;
  out.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - wall0).count();
  return out;
}

// The verdict common to both soaks: nothing bad on any tick, and no drift.
void expect_steady(const char* label, const SoakOutcome& r, std::uint64_t ticks) {
  EXPECT_EQ(r.ticks_run, ticks);
  EXPECT_EQ(r.failed_steps, 0U);
  EXPECT_EQ(r.nonfinite_ticks, 0U);
  EXPECT_EQ(r.not_enabled_ticks, 0U);
  EXPECT_LE(r.ticks_to_enable, 10U) << "the unit answers the enable request within a few ticks";
  EXPECT_EQ(r.first_bad_tick, 0U);
  std::vector<const Window*> whole;
  for (const Window& w : r.windows) {
    if (w.whole) {
      whole.push_back(&w);
    }
  }
  fmt::print("[{}] {} ticks in {:.1f} s wall ({:.0f} ticks/s); {} whole windows\n", label, r.ticks_run,
             r.wall_s, r.wall_s > 0.0 ? static_cast<double>(r.ticks_run) / r.wall_s : 0.0, whole.size());
  if (whole.size() < 2) {
    fmt::print("[{}] fewer than two whole windows: drift not compared\n", label);
    return;
  }
  const double first = whole.front()->rms_N;
  const std::size_t from = whole.size() > kLastWindowsCompared ? whole.size() - kLastWindowsCompared : 1;
  for (std::size_t i = from; i < whole.size(); ++i) {
    const double rms = whole[i]->rms_N;
    fmt::print(
        "[{}] drift: window ending at {} {:.5f} N vs first {:.5f} N (ratio {:.3f}, allowed "
        "1/{:.2f}..{:.2f})\n",
        label, whole[i]->end_tick, rms, first, first > 0.0 ? rms / first : 0.0, kDriftFactor, kDriftFactor);
    EXPECT_LE(rms, kDriftFactor * first) << "window ending at " << whole[i]->end_tick;
    EXPECT_GE(rms, first / kDriftFactor) << "window ending at " << whole[i]->end_tick;
  }
  std::fflush(stdout);
}

// The requested window (default: a tenth of the run, at most 10^6 ticks) rounded to whole schedule
// periods (at least one), and not above the run.
std::uint64_t window_for(std::uint64_t ticks, std::uint64_t period) {
  const std::uint64_t requested =
      count_from_env("MRSKIN_SOAK_WINDOW_TICKS", std::clamp<std::uint64_t>(ticks / 10, 1, 1'000'000));
  const std::uint64_t periods = std::max<std::uint64_t>(1, (requested + period / 2) / period);
  return std::min(ticks, periods * period);
}

TEST(BridgeSoak, BridgeTicksAgainstACheapPlant) {
  const std::uint64_t ticks = count_from_env("MRSKIN_SOAK_BRIDGE_TICKS", 100'000'000);
  const model::LoadedProfile loaded = model::load_profile_with_text("mr-skin-5x5");
  sim::MockOptions options;
  options.seed = 1;
  options.calibration_error = -1.0;  // the nominal calibration: no network plant to measure
  auto mock = std::make_shared<sim::MockDevice>(loaded.profile, loaded.text, options,
                                                std::make_unique<FirstOrderPlant>(loaded.profile));
  SimulatedClock clock;
  DeviceSession session(mock->connect(true, &clock), clock, SessionOptions{});
  SceneSchedule schedule({"sweep"});
  Bridge loop(session, schedule);
  sim::MockDeviceTruth truth(*mock);
  eval::TruthScorer scorer(truth, mock->layout().fluid_cell_count(), BridgeOptions{});
  loop.set_tick_watcher(&scorer);
  loop.set_perf_clock(&clock);  // deterministic: no wall time in the loop
  ASSERT_EQ(loop.enable(), ResultCode::ok);
  const SoakOutcome r =
      soak("cheap", *mock, session, loop, schedule, clock, ticks, window_for(ticks, schedule.period_ticks()));
  expect_steady("cheap", r, ticks);
}

TEST(BridgeSoak, ClosedLoopOnTheMock) {
  const std::uint64_t ticks = count_from_env("MRSKIN_SOAK_CLOSED_LOOP_TICKS", 10'000'000);
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  OpenedDevice dev = open_device("mock://?seed=1&perturbation=0.15", clock, open);
  std::vector<std::string_view> names(scene_names().begin(), scene_names().end());
  SceneSchedule schedule(names);
  Bridge loop(*dev.session, schedule);
  sim::MockDeviceTruth truth(*sim::mock_of(dev));
  eval::TruthScorer scorer(truth, sim::mock_of(dev)->layout().fluid_cell_count(), BridgeOptions{});
  loop.set_tick_watcher(&scorer);
  loop.set_perf_clock(&clock);
  ASSERT_EQ(loop.enable(), ResultCode::ok);
  const SoakOutcome r = soak("mock", *sim::mock_of(dev), *dev.session, loop, schedule, clock, ticks,
                             window_for(ticks, schedule.period_ticks()));
  expect_steady("mock", r, ticks);
}

}  // namespace
