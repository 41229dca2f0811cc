// Bumpless reload (issue 25): a rate change (1000 <-> 200 Hz) or a gain change in the middle of a
// press keeps the rendered force within 0.05 N of a run without the reload, for the 200 ms after
// it, on the simulated clock (Bridge::retune keeps every state), and never leaves the band between
// the run without the reload and the run at the new settings throughout by more than 0.05 N (a
// bump leaves both). A bridge built anew at that moment, as reloads did before, is shown beside it.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <tuple>
#include <utility>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/eval/truth_scorer.hpp"
#include "mrskin/sim/open_mock.hpp"

namespace mrskin::bridge {
namespace {

enum class Change { none, retune, rebuild };

struct Trace {
  std::vector<std::vector<double>> true_N;    // per millisecond, per fluid cell
  std::vector<std::vector<double>> target_N;  // the bridge's target at that millisecond
  double reload_s = 0.0;
  // Rendered-force error against the tissue law over the 200 ms after the reload (the bridge's
  // own score, true state: BridgeStats), N RMS.
  double window_rms_N = 0.0;
};

// The demo on the perturbed mock (seed 7): the mock steps every millisecond, the bridge at its
// rate. At reload_s the bridge is retuned to `after` (or built anew with it).
Trace run(double seconds, const BridgeTuning& before, const BridgeTuning& after, double reload_s,
          Change change) {
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  OpenedDevice dev = open_device("mock://?seed=7", clock, open);
  auto scene = make_scene("demo");
  auto options_for = [](const BridgeTuning& t) {
    BridgeOptions o;
    apply_tuning(t, o);
    return o;
  };
  auto bridge = std::make_unique<Bridge>(*dev.session, *scene, options_for(before));
  bridge->set_perf_clock(&clock);
  sim::MockDeviceTruth truth(*sim::mock_of(dev));
  // A rebuilt bridge is scored afresh, by a scorer of its own.
  std::optional<eval::TruthScorer> scorer;
  scorer.emplace(truth, sim::mock_of(dev)->layout().fluid_cell_count(), options_for(before));
  bridge->set_tick_watcher(&*scorer);
  scene->set_start(clock.now());
  EXPECT_EQ(bridge->enable(), ResultCode::ok);
  const GridLayout& layout = sim::mock_of(dev)->layout();
  std::vector<double> finger(layout.fluid_cell_count());
  Trace trace;
  trace.reload_s = reload_s;
  double rate_hz = before.rate_hz;
  TimePoint next_tick = clock.now();
  const auto ms = static_cast<int>(seconds * 1000.0);
  const int reload_ms = static_cast<int>(reload_s * 1000.0);
  double sq0 = 0.0;
  double n0 = 0.0;
  const auto score_window = [&] {
    const BridgeStats& s = bridge->stats();
    return std::pair<double, double>{s.true_state_sq_error_sum_N2, static_cast<double>(s.force_samples)};
  };
  for (int k = 0; k < ms; ++k) {
    if (k == reload_ms) {
      std::tie(sq0, n0) = score_window();
    }
    if (k == reload_ms + 200) {
      const auto [sq1, n1] = score_window();
      // A new bridge scores from zero.
      const double sq = change == Change::rebuild ? sq1 : sq1 - sq0;
      const double n = change == Change::rebuild ? n1 : n1 - n0;
      trace.window_rms_N = n > 0.0 ? std::sqrt(sq / n) : 0.0;
    }
    if (k == reload_ms && change != Change::none) {
      if (change == Change::retune) {
        bridge->retune(after);
      } else {
        bridge = std::make_unique<Bridge>(*dev.session, *scene, options_for(after));
        bridge->set_perf_clock(&clock);
        scorer.emplace(truth, sim::mock_of(dev)->layout().fluid_cell_count(), options_for(after));
        bridge->set_tick_watcher(&*scorer);
        EXPECT_EQ(bridge->enable(), ResultCode::ok);
      }
      rate_hz = after.rate_hz;
      next_tick = clock.now();
    }
    mrskin::eval::press_scene_finger(*scene, to_seconds(clock.now() - scene->start()), layout, finger);
    sim::mock_of(dev)->set_finger_indentation(finger);
    sim::mock_of(dev)->step(clock.now());
    if (clock.now() >= next_tick) {
      (void)bridge->step(clock.now());
      next_tick += from_seconds(1.0 / rate_hz);
    }
    std::vector<double> f(layout.fluid_cell_count());
    sim::mock_of(dev)->true_contact_forces(f);
    trace.true_N.push_back(std::move(f));
    const auto t = bridge->targets_N();
    trace.target_N.emplace_back(t.begin(), t.end());
    clock.advance(std::chrono::milliseconds(1));
  }
  return trace;
}

// Largest per-cell difference of the true force over [from_s, from_s + span_s).
double max_difference_N(const Trace& a, const Trace& b, double from_s, double span_s) {
  double worst = 0.0;
  const auto first = static_cast<std::size_t>(from_s * 1000.0);
  const auto last =
      std::min({a.true_N.size(), b.true_N.size(), static_cast<std::size_t>((from_s + span_s) * 1000.0)});
  for (std::size_t k = first; k < last; ++k) {
    for (std::size_t c = 0; c < a.true_N[k].size(); ++c) {
      worst = std::max(worst, std::abs(a.true_N[k][c] - b.true_N[k][c]));
    }
  }
  return worst;
}

// How far the reloaded run's force strays outside the band between the run without the reload
// and the run at the new settings throughout, at each millisecond and cell: a bump leaves both,
// a settings change that renders better moves from one towards the other.
double max_outside_band_N(const Trace& reloaded, const Trace& before, const Trace& after, double from_s,
                          double span_s) {
  double worst = 0.0;
  const auto first = static_cast<std::size_t>(from_s * 1000.0);
  const auto last = std::min({reloaded.true_N.size(), before.true_N.size(), after.true_N.size(),
                              static_cast<std::size_t>((from_s + span_s) * 1000.0)});
  for (std::size_t k = first; k < last; ++k) {
    for (std::size_t c = 0; c < reloaded.true_N[k].size(); ++c) {
      const double lo = std::min(before.true_N[k][c], after.true_N[k][c]);
      const double hi = std::max(before.true_N[k][c], after.true_N[k][c]);
      const double r = reloaded.true_N[k][c];
      worst = std::max(worst, r < lo ? lo - r : (r > hi ? r - hi : 0.0));
    }
  }
  return worst;
}

// The middle of the demo's first press: 0.1 s after a cell first carries 0.5 N.
double mid_press_s(const Trace& t) {
  for (std::size_t k = 0; k < t.true_N.size(); ++k) {
    if (*std::max_element(t.true_N[k].begin(), t.true_N[k].end()) > 0.5) {
      return static_cast<double>(k) * 1e-3 + 0.1;
    }
  }
  return -1.0;
}

BridgeTuning at_rate(double rate_hz) {
  BridgeTuning t;
  t.rate_hz = rate_hz;
  return t;
}

struct ReloadCase {
  const char* name;
  BridgeTuning before;
  BridgeTuning after;
  double bound_N;  // the 200 ms after the reload against the run without it
};

BridgeTuning with_gain(double gain_per_s) {
  BridgeTuning t;
  t.feedback_gain_per_s = gain_per_s;
  return t;
}

class Reload : public ::testing::TestWithParam<ReloadCase> {};

TEST_P(Reload, InTheMiddleOfAPressIsBumpless) {
  const ReloadCase c = GetParam();
  constexpr double kSeconds = 2.5;
  const double reload_s = mid_press_s(run(kSeconds, c.before, c.before, 0.0, Change::none));
  const Trace baseline = run(kSeconds, c.before, c.before, reload_s, Change::none);  // scored from reload_s
  ASSERT_GT(reload_s, 0.0);
  ASSERT_LT(reload_s + 0.2, kSeconds);
  // Still pressing over the window: the comparison is made under load.
  const auto at = static_cast<std::size_t>(reload_s * 1000.0);
  EXPECT_GT(*std::max_element(baseline.true_N[at].begin(), baseline.true_N[at].end()), 0.3);
  const Trace retuned = run(kSeconds, c.before, c.after, reload_s, Change::retune);
  const Trace rebuilt = run(kSeconds, c.before, c.after, reload_s, Change::rebuild);
  const double retune_N = max_difference_N(baseline, retuned, reload_s, 0.2);
  const double rebuild_N = max_difference_N(baseline, rebuilt, reload_s, 0.2);
  const Trace after_only = run(kSeconds, c.after, c.after, reload_s, Change::none);
  const double first_150ms_N = max_difference_N(baseline, retuned, reload_s, 0.15);
  const double outside_N = max_outside_band_N(retuned, baseline, after_only, reload_s, 0.2);
  std::printf(
      "%-15s reload at %.3f s: the true force within %.4f N of the run without it over 200 ms (%.4f N "
      "over 150 ms; a new bridge instead: %.3f N; the run at the new settings throughout differs from the "
      "one without by %.4f N)\n",
      c.name, reload_s, retune_N, first_150ms_N, rebuild_N,
      max_difference_N(after_only, baseline, reload_s, 0.2));
  std::printf(
      "%-15s error against the tissue law (true state) over those 200 ms: %.4f N RMS reloaded, %.4f N "
      "without, %.4f N at the new settings throughout\n",
      c.name, retuned.window_rms_N, baseline.window_rms_N, after_only.window_rms_N);
  std::printf(
      "%-15s outside the band between the run without the reload and the run at the new settings "
      "throughout: %.4f N at most over 200 ms (a new bridge instead: %.4f N)\n",
      c.name, outside_N, max_outside_band_N(rebuilt, baseline, after_only, reload_s, 0.2));
  // Where the runs differ most: the force each renders and the target each renders it to. A bump
  // would show as a rendering error; a different target means the master's state has moved on.
  std::size_t worst_k = at;
  std::size_t worst_cell = 0;
  for (std::size_t k = at; k < at + 200; ++k) {
    for (std::size_t i = 0; i < baseline.true_N[k].size(); ++i) {
      if (std::abs(baseline.true_N[k][i] - retuned.true_N[k][i]) >
          std::abs(baseline.true_N[worst_k][worst_cell] - retuned.true_N[worst_k][worst_cell])) {
        worst_k = k;
        worst_cell = i;
      }
    }
  }
  std::printf(
      "%-15s largest difference %zu ms after, cell %zu: without the reload %.4f N (target %.4f N), "
      "reloaded %.4f N (target %.4f N)\n",
      c.name, worst_k - at, worst_cell, baseline.true_N[worst_k][worst_cell],
      baseline.target_N[worst_k][worst_cell], retuned.true_N[worst_k][worst_cell],
      retuned.target_N[worst_k][worst_cell]);
  EXPECT_LE(retune_N, c.bound_N);
  EXPECT_LE(first_150ms_N, 0.05);
  // No bump: within 0.05 N of the band the two settings span, every millisecond and cell.
  EXPECT_LE(outside_N, 0.05);
  // No worse than either setting on its own, give or take 2 mN: no bump.
  EXPECT_LE(retuned.window_rms_N, std::max(baseline.window_rms_N, after_only.window_rms_N) + 0.002);
  // Before the reload the runs are the same run.
  EXPECT_EQ(max_difference_N(baseline, retuned, 0.0, reload_s), 0.0);
}

INSTANTIATE_TEST_SUITE_P(
    RateAndGain, Reload,
    // Every reload within the 0.05 N. 200 -> 1000 Hz missed it (0.068 N) while the tissue
    // fit forgot per sample: at 200 Hz its memory was 1 s, so the law lagged the press by 0.3 N
    // behind the 1 kHz bridge's; its memory is now a time (TissueEstimatorOptions::memory_s).
    ::testing::Values(ReloadCase{"1000_to_200_Hz", at_rate(1000.0), at_rate(200.0), 0.05},
                      ReloadCase{"200_to_1000_Hz", at_rate(200.0), at_rate(1000.0), 0.05},
                      ReloadCase{"gain_30_to_60", with_gain(30.0), with_gain(60.0), 0.05},
                      ReloadCase{"gain_30_to_10", with_gain(30.0), with_gain(10.0), 0.05}),
    [](const ::testing::TestParamInfo<ReloadCase>& p) { return std::string(p.param.name); });

TEST(Retune, RefusesBadValuesAndChangesNothing) {
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  OpenedDevice dev = open_device("mock://", clock, open);
  auto scene = make_scene("demo");
  Bridge bridge(*dev.session, *scene);
  BridgeTuning t = bridge.tuning();
  EXPECT_EQ(t.rate_hz, 1000.0);
  for (const std::function<void(BridgeTuning&)>& spoil : std::vector<std::function<void(BridgeTuning&)>>{
           [](BridgeTuning& x) { x.rate_hz = 0.5; }, [](BridgeTuning& x) { x.rate_hz = std::nan(""); },
           [](BridgeTuning& x) { x.feedback_gain_per_s = -1.0; },
           [](BridgeTuning& x) { x.stale_fade_s = 0.0; },
           [](BridgeTuning& x) { x.mapping.cells_per_m = 0.0; },
           [](BridgeTuning& x) { x.resend_period_s = 0.0; }}) {
    BridgeTuning bad = bridge.tuning();
    bad.rate_hz = 200.0;
    spoil(bad);
    EXPECT_THROW(bridge.retune(bad), InvalidArgument);
    EXPECT_EQ(bridge.tuning().rate_hz, 1000.0);
    EXPECT_EQ(bridge.tuning().stale_fade_s, t.stale_fade_s);
  }
  t.rate_hz = 200.0;
  t.stale_hold_s = 0.3;
  bridge.retune(t);
  EXPECT_EQ(bridge.tuning().rate_hz, 200.0);
  EXPECT_EQ(bridge.tuning().stale_hold_s, 0.3);
  EXPECT_DOUBLE_EQ(bridge.tick_period_s(), 0.005);
}

}  // namespace
}  // namespace mrskin::bridge
