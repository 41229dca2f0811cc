// The cell observer against the network plant: exact recovery without noise or perturbation,
// and its measured error on the perturbed, noisy plant (printed; docs/model.md quotes it).
#include "mrskin/driver/model/observer.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <random>
#include <span>
#include <utility>
#include <vector>

#include "counting_new.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/model/device_model.hpp"
#include "mrskin/driver/model/magnetic.hpp"
#include "mrskin/driver/model/profile.hpp"
#include "mrskin/sim/network_plant.hpp"

namespace {

using mrskin::model::CellObserver;
using mrskin::model::DeviceModel;
using mrskin::model::ObserverOptions;
using mrskin::model::Status;
using mrskin::sim::NetworkPlant;
using mrskin::sim::NetworkPlantOptions;

constexpr double kTick_s = 1e-3;
constexpr int kSubsteps = 10;

// Press-hold-release of a set of cells (depth profile per cell), valves at one current.
struct Press {
  std::vector<std::size_t> cells;
  std::vector<double> peak_m;
};

struct Errors {
  double depth_rms_m = 0.0;
  double depth_max_m = 0.0;
  double rate_rms_m_per_s = 0.0;
  double force_rms_N = 0.0;
  double force_max_N = 0.0;
  std::size_t samples = 0;
};

double envelope(double t_s) {  // 0 -> 1 over 1 s, hold 0.5 s, back to 0 over 1 s
  if (t_s < 1.0) {
    return t_s;
  }
  if (t_s < 1.5) {
    return 1.0;
  }
  return std::max(0.0, 1.0 - (t_s - 1.5));
}

Errors run(const Press& press, const NetworkPlantOptions& plant_options, double current_A,
           const ObserverOptions& observer_options = {}) {
  const DeviceModel nominal(mrskin::model::default_profile());
  NetworkPlant plant(nominal.profile(), plant_options);
  CellObserver observer(nominal, observer_options);
  const std::size_t cells = nominal.layout().fluid_cell_count();
  std::vector<double> depth(cells, 0.0);
  std::vector<double> previous(cells, 0.0);
  std::vector<double> current(nominal.layout().valve_count(), current_A);
  std::vector<double> sensors(plant.sensor_count());
  std::vector<double> truth_N(cells);
  Errors e;
  double d2 = 0.0;
  double v2 = 0.0;
  double f2 = 0.0;
  plant.set_valve_currents(current);
  for (int tick = 0; tick < 2600; ++tick) {
    const double t = (tick + 1) * kTick_s;
    std::fill(depth.begin(), depth.end(), 0.0);
    for (std::size_t k = 0; k < press.cells.size(); ++k) {
      depth[press.cells[k]] = press.peak_m[k] * envelope(t);
    }
    plant.set_finger_indentation(depth);
    for (int s = 0; s < kSubsteps; ++s) {
      plant.step(kTick_s / kSubsteps);
    }
    plant.read_sensors(sensors);
    plant.contact_forces(truth_N);
    // Truth is the pad's depth, which leaves the finger when the membrane is sucked in.
    const std::span<const double> pad_m = plant.network().cell_indentation_m();
    EXPECT_EQ(observer.update(sensors, current, kTick_s), Status::ok);
    if (tick < 50) {  // the rate filter's start-up
      previous.assign(pad_m.begin(), pad_m.end());
      continue;
    }
    for (std::size_t c = 0; c < cells; ++c) {
      const double dd = observer.indentation_m()[c] - pad_m[c];
      const double dv = observer.velocity_m_per_s()[c] - (pad_m[c] - previous[c]) / kTick_s;
      const double df = observer.force_N()[c] - truth_N[c];
      d2 += dd * dd;
      v2 += dv * dv;
      f2 += df * df;
      e.depth_max_m = std::max(e.depth_max_m, std::abs(dd));
      e.force_max_N = std::max(e.force_max_N, std::abs(df));
      ++e.samples;
    }
    previous.assign(pad_m.begin(), pad_m.end());
  }
  const auto n = static_cast<double>(e.samples);
  e.depth_rms_m = std::sqrt(d2 / n);
  e.rate_rms_m_per_s = std::sqrt(v2 / n);
  e.force_rms_N = std::sqrt(f2 / n);
  return e;
}

void print(const char* name, const Errors& e) {
  std::printf(
      "observer %-28s depth rms %6.1f um max %6.1f um | rate rms %5.2f mm/s | force rms %.4f N max %.4f N\n",
      name, e.depth_rms_m * 1e6, e.depth_max_m * 1e6, e.rate_rms_m_per_s * 1e3, e.force_rms_N, e.force_max_N);
}

NetworkPlantOptions ideal() {
  NetworkPlantOptions o;
  o.perturbation = 0.0;
  o.command_delay_s = 0.0;
  o.hysteresis_scale = 0.0;
  o.sensor_noise_scale = 0.0;
  o.quantise_sensors = false;
  return o;
}

// Fluid-cell indices of the default 5 x 5: 0..2 row 0, 3..4 row 1, 5..7 row 2 (6: centre).
const Press kCentre{{6}, {4e-3}};
const Press kCorner{{0}, {4e-3}};
const Press kEdge{{5}, {3e-3}};
const Press kTwoCells{{6, 3}, {3e-3, 2e-3}};

TEST(ObserverIdeal, RecoversPressedCellsWithoutNoiseOrPerturbation) {
  for (const Press* p : {&kCentre, &kCorner, &kEdge, &kTwoCells}) {
    ObserverOptions matched;
    matched.steel_hysteresis = false;  // the ideal plant has none either
    const Errors e = run(*p, ideal(), 0.03, matched);
    print("ideal", e);
    EXPECT_LT(e.depth_max_m, 1e-6);  // non-negativity identifies the pressed cells exactly
    EXPECT_LT(e.force_max_N, 0.1);   // the observer's fast stepper against the plant's exact one
  }
}

TEST(ObserverPerturbed, ErrorOnThePerturbedNoisyPlant) {
  struct Case {
    const char* name;
    const Press* press;
    double current_A;
  };
  const Case cases[] = {{"centre 4 mm, 0.03 A", &kCentre, 0.03},
                        {"centre 4 mm, 0.08 A", &kCentre, 0.08},
                        {"corner 4 mm, 0.05 A", &kCorner, 0.05},
                        {"edge 3 mm, 0.05 A", &kEdge, 0.05},
                        {"two cells, 0.05 A", &kTwoCells, 0.05}};
  for (const Case& c : cases) {
    NetworkPlantOptions o;
    o.seed = 3;
    const Errors e = run(*c.press, o, c.current_A);
    print(c.name, e);
    // Bounds well above what is measured: they catch a broken observer, not a tuning change.
    EXPECT_LT(e.depth_rms_m, 10e-6) << c.name;
    EXPECT_LT(e.force_rms_N, 0.1) << c.name;
  }
}

// The local force model (the quasi-static cell law of the contacted cells, what large grids use
// by default) on the same presses: cheaper, no fluid history, so a larger force error.
TEST(ObserverPerturbed, LocalForceModelOnThePerturbedNoisyPlant) {
  struct Case {
    const char* name;
    const Press* press;
    double current_A;
  };
  const Case cases[] = {{"local: centre 4 mm, 0.03 A", &kCentre, 0.03},
                        {"local: centre 4 mm, 0.08 A", &kCentre, 0.08},
                        {"local: corner 4 mm, 0.05 A", &kCorner, 0.05},
                        {"local: edge 3 mm, 0.05 A", &kEdge, 0.05},
                        {"local: two cells, 0.05 A", &kTwoCells, 0.05}};
  ObserverOptions local;
  local.force_model = mrskin::model::ObserverForceModel::local;
  for (const Case& c : cases) {
    NetworkPlantOptions o;
    o.seed = 3;
    const Errors e = run(*c.press, o, c.current_A, local);
    print(c.name, e);
    EXPECT_LT(e.depth_rms_m, 10e-6) << c.name;
    EXPECT_LT(e.force_rms_N, 0.2) << c.name;
  }
}

// The default 5 x 5 on the perturbed noisy plant (seed 3) with its valves at one current, and an
// observer with the given options: a tick presses the finger, steps the plant and updates.
struct SeededRig {
  SeededRig(const ObserverOptions& options, double current_A)
      : plant(nominal.profile(), seeded()),
        observer(nominal, options),
        depth(nominal.layout().fluid_cell_count(), 0.0),
        current(nominal.layout().valve_count(), current_A),
        sensors(plant.sensor_count()) {
    plant.set_valve_currents(current);
  }
  static NetworkPlantOptions seeded() {
    NetworkPlantOptions o;
    o.seed = 3;
    return o;
  }
  void tick() {
    plant.set_finger_indentation(depth);
    for (int s = 0; s < kSubsteps; ++s) {
      plant.step(kTick_s / kSubsteps);
    }
    plant.read_sensors(sensors);
    EXPECT_EQ(observer.update(sensors, current, kTick_s), Status::ok);
  }
  const DeviceModel nominal{mrskin::model::default_profile()};
  NetworkPlant plant;
  CellObserver observer;
  std::vector<double> depth;
  std::vector<double> current;
  std::vector<double> sensors;
};

// A press of the centre cell at a steady 5 mm/s for 0.6 s that stops and holds for 0.4 s, on the
// perturbed noisy plant (seed 3): the observer's rate error while pressing (from 0.1 s) and
// holding (from 10 ticks after the stop), RMS and worst.
struct RateErrors {
  double pressing_rms_m_per_s = 0.0;
  double pressing_max_m_per_s = 0.0;
  double holding_rms_m_per_s = 0.0;
  double holding_max_m_per_s = 0.0;
};

RateErrors press_and_stop(const ObserverOptions& options) {
  SeededRig rig(options, 0.05);
  constexpr double kRate_m_per_s = 5e-3;
  constexpr int kStopTick = 600;
  RateErrors r;
  double pressing2 = 0.0;
  double holding2 = 0.0;
  int pressing = 0;
  int holding = 0;
  for (int tick = 0; tick < kStopTick + 400; ++tick) {
    const double t = (tick + 1) * kTick_s;
    rig.depth[6] = kRate_m_per_s * std::min(t, kStopTick * kTick_s);
    rig.tick();
    const double rate = rig.observer.velocity_m_per_s()[6];
    if (tick >= 100 && tick < kStopTick) {
      const double e = rate - kRate_m_per_s;
      pressing2 += e * e;
      ++pressing;
      r.pressing_max_m_per_s = std::max(r.pressing_max_m_per_s, std::abs(e));
    } else if (tick >= kStopTick + 10) {
      holding2 += rate * rate;
      ++holding;
      r.holding_max_m_per_s = std::max(r.holding_max_m_per_s, std::abs(rate));
    }
  }
  r.pressing_rms_m_per_s = std::sqrt(pressing2 / pressing);
  r.holding_rms_m_per_s = std::sqrt(holding2 / holding);
  return r;
}

void print(const char* name, const RateErrors& r) {
  std::printf("%-26s rate error pressing rms %.2f max %.2f mm/s | holding rms %.2f max %.2f mm/s\n", name,
              r.pressing_rms_m_per_s * 1e3, r.pressing_max_m_per_s * 1e3, r.holding_rms_m_per_s * 1e3,
              r.holding_max_m_per_s * 1e3);
}

// The segmented-line rate (RateEstimator::segmented_line) against the filtered difference: on a
// steady press and a hold a line through the depths since the last change has far less noise,
// and it follows the stop within a few ticks (the change is found on its prediction error),
// not after its 20 ms memory.
TEST(ObserverRate, SegmentedLineHasLessRateNoiseOnAPressAndAHold) {
  ObserverOptions line;
  line.rate_estimator = mrskin::model::RateEstimator::segmented_line;
  const RateErrors filtered = press_and_stop(ObserverOptions{});
  const RateErrors segmented = press_and_stop(line);
  print("rate: filtered difference", filtered);
  print("rate: segmented line", segmented);
  EXPECT_LT(segmented.pressing_rms_m_per_s, 0.5 * filtered.pressing_rms_m_per_s);
  EXPECT_LT(segmented.holding_rms_m_per_s, 0.5 * filtered.holding_rms_m_per_s);
  EXPECT_LT(segmented.holding_max_m_per_s, filtered.holding_max_m_per_s);
}

TEST(ObserverRate, BadRateOptionsAreRefused) {
  const DeviceModel nominal(mrskin::model::default_profile());
  for (const double bad :
       {0.0, -1.0, std::numeric_limits<double>::quiet_NaN(), std::numeric_limits<double>::infinity()}) {
    ObserverOptions memory;
    memory.rate_memory_s = bad;
    EXPECT_THROW(CellObserver(nominal, memory), mrskin::InvalidArgument);
    ObserverOptions threshold;
    threshold.rate_change_threshold_sigma = bad;
    EXPECT_THROW(CellObserver(nominal, threshold), mrskin::InvalidArgument);
  }
}

// The 5 x 5 at rest on the noisy plant (seed 3, nothing touching): with the rest gate the
// depths are exactly zero on every tick whose readings are all within 3 sigma (the fit is
// skipped); without it noise spreads micrometres of depth over a few cells. A press is found
// as before once a reading leaves the gate.
struct RestCount {
  int zero_ticks = 0;
  double largest_idle_depth_m = 0.0;
  double pressed_depth_m = 0.0;
};

RestCount rest_then_press(const ObserverOptions& options) {
  SeededRig rig(options, 0.0);
  RestCount r;
  for (int tick = 0; tick < 400; ++tick) {
    rig.depth[6] = tick < 300 ? 0.0 : 1e-3;  // the centre pressed 1 mm for the last 100 ticks
    rig.tick();
    const std::span<const double> d = rig.observer.indentation_m();
    if (tick < 300) {
      const double largest = *std::max_element(d.begin(), d.end());
      r.zero_ticks += largest == 0.0 ? 1 : 0;
      r.largest_idle_depth_m = std::max(r.largest_idle_depth_m, largest);
    } else {
      r.pressed_depth_m = d[6];
    }
  }
  return r;
}

TEST(ObserverRest, NoiseAloneLeavesTheDepthsAtZeroAndAPressIsFound) {
  const RestCount gated = rest_then_press(ObserverOptions{});
  ObserverOptions off;
  off.rest_gate_sigma = 0.0;
  const RestCount ungated = rest_then_press(off);
  std::printf(
      "rest gate: %d of 300 idle ticks at zero depth (largest %.1f um), pressed %.3f mm; without: %d "
      "(largest %.1f um), pressed %.3f mm\n",
      gated.zero_ticks, gated.largest_idle_depth_m * 1e6, gated.pressed_depth_m * 1e3, ungated.zero_ticks,
      ungated.largest_idle_depth_m * 1e6, ungated.pressed_depth_m * 1e3);
  EXPECT_GE(gated.zero_ticks, 270);
  EXPECT_LT(ungated.zero_ticks, gated.zero_ticks);
  EXPECT_NEAR(gated.pressed_depth_m, ungated.pressed_depth_m, 1e-9);
  EXPECT_NEAR(gated.pressed_depth_m, 1e-3, 50e-6);
}

// From rest a reading past the gate gets rest_sweeps sweeps, not `sweeps`: the press is found
// as with twelve, and noise leaves no depth near the contact threshold either way.
TEST(ObserverRest, AFewSweepsFromRestFindThePressAsTwelveDo) {
  ObserverOptions twelve;
  twelve.rest_sweeps = twelve.sweeps;
  twelve.small_grid_sweeps = twelve.sweeps;
  const RestCount full = rest_then_press(twelve);
  const RestCount capped = rest_then_press(ObserverOptions{});
  std::printf("from rest, %d sweeps: pressed %.4f mm, largest idle %.2f um; %d: %.4f mm, %.2f um\n",
              ObserverOptions{}.rest_sweeps, capped.pressed_depth_m * 1e3, capped.largest_idle_depth_m * 1e6,
              twelve.sweeps, full.pressed_depth_m * 1e3, full.largest_idle_depth_m * 1e6);
  EXPECT_NEAR(capped.pressed_depth_m, full.pressed_depth_m, 1e-6);
  EXPECT_LT(capped.largest_idle_depth_m, ObserverOptions{}.contact_threshold_m);
  EXPECT_EQ(capped.zero_ticks, full.zero_ticks);  // the gate's ticks are the same ones
  ObserverOptions bad;
  bad.rest_sweeps = 0;
  EXPECT_THROW(CellObserver(DeviceModel(mrskin::model::default_profile()), bad), mrskin::InvalidArgument);
}

// A small grid's fit sweeps at most small_grid_sweeps times a tick and takes up what a capped
// tick left on the next (it starts from the last depths): a press, a hold and a release on the
// noisy plant (seed 3) read as with twelve sweeps, within a fraction of the sensors' noise.
TEST(ObserverSweeps, ASmallGridsCappedFitFollowsAPressAsTwelveSweepsDo) {
  ObserverOptions twelve;
  twelve.small_grid_sweeps = twelve.sweeps;
  SeededRig capped_rig(ObserverOptions{}, 0.0);
  SeededRig full_rig(twelve, 0.0);
  double worst_m = 0.0;
  double held_capped_m = 0.0;
  double held_full_m = 0.0;
  double capped_sq = 0.0;
  double full_sq = 0.0;
  int samples = 0;
  for (int tick = 0; tick < 900; ++tick) {
    // The centre and the cell at the right edge: 0 -> 2 and 1 mm in 300 ms, held, released.
    const double ramp = tick < 300 ? tick / 300.0 : (tick < 600 ? 1.0 : (900 - tick) / 300.0);
    capped_rig.depth[6] = full_rig.depth[6] = 2e-3 * ramp;
    capped_rig.depth[7] = full_rig.depth[7] = 1e-3 * ramp;
    capped_rig.tick();
    full_rig.tick();
    const std::span<const double> a = capped_rig.observer.indentation_m();
    const std::span<const double> b = full_rig.observer.indentation_m();
    for (std::size_t c = 0; c < a.size(); ++c) {
      worst_m = std::max(worst_m, std::abs(a[c] - b[c]));
      capped_sq += (a[c] - capped_rig.depth[c]) * (a[c] - capped_rig.depth[c]);
      full_sq += (b[c] - full_rig.depth[c]) * (b[c] - full_rig.depth[c]);
      ++samples;
    }
    if (tick == 599) {
      held_capped_m = a[6];
      held_full_m = b[6];
    }
  }
  const double capped_rms_m = std::sqrt(capped_sq / samples);
  const double full_rms_m = std::sqrt(full_sq / samples);
  std::printf(
      "fit at %d sweeps against %d: depth error %.3f against %.3f um RMS, largest difference %.2f um, "
      "held %.4f against %.4f mm\n",
      ObserverOptions{}.small_grid_sweeps, twelve.sweeps, capped_rms_m * 1e6, full_rms_m * 1e6, worst_m * 1e6,
      held_capped_m * 1e3, held_full_m * 1e3);
  EXPECT_LT(capped_rms_m, 1.05 * full_rms_m);
  EXPECT_LT(worst_m, 5 * 2e-6);  // the 5 x 5's sensors: 2 um of noise
  EXPECT_NEAR(held_capped_m, held_full_m, 1e-6);
  ObserverOptions bad;
  bad.small_grid_sweeps = 0;
  EXPECT_THROW(CellObserver(DeviceModel(mrskin::model::default_profile()), bad), mrskin::InvalidArgument);
}

// The network's step spread over the ticks of 4 ms (the default) against a whole step every tick,
// on the perturbed noisy plant at fixed currents: the same force error within a tenth (it
// tracks a finger that moves between its steps by the touched cells' undrained law). A bad step
// length is refused.
TEST(ObserverNetworkPhases, AStepSpreadOverTicksFollowsAPressAsWholeStepsDo) {
  ObserverOptions whole;
  whole.network_step_s = 0.0;
  for (const double current_A : {0.0, 0.05}) {
    for (const Press* press : {&kCentre, &kTwoCells}) {
      NetworkPlantOptions o;
      o.seed = 3;
      const Errors spread = run(*press, o, current_A);
      const Errors every_tick = run(*press, o, current_A, whole);
      print("network in phases", spread);
      print("network every tick", every_tick);
      EXPECT_LT(spread.force_rms_N, 1.1 * every_tick.force_rms_N + 1e-3) << current_A;
      EXPECT_LT(spread.force_max_N, 1.5 * every_tick.force_max_N + 5e-3) << current_A;
    }
  }
  const DeviceModel nominal(mrskin::model::default_profile());
  for (const double bad_s : {-1e-3, 2.0, std::numeric_limits<double>::quiet_NaN()}) {
    ObserverOptions bad;
    bad.network_step_s = bad_s;
    EXPECT_THROW(CellObserver(nominal, bad), mrskin::InvalidArgument) << bad_s;
  }
}

// The network refuses a step whose linear solve is off the laws (a jump in the inputs, stiff
// cells); the step spread over ticks is checked on its last tick, and the ticks before that one
// are then taken again as one shorter step (this tick's time lost, as a whole step's refused
// tick loses its own). The default tolerance (0.25) refuses nothing on this press; at 5e-4 some
// 4-tick steps are refused and the 3-tick steps before them pass (4 refusals here; from 4e-4
// down the shorter steps are refused too, and their ticks report the error). Every tick is ok
// and the force follows the default observer's (measured: 0.067 N of 2.5 N at most).
TEST(ObserverNetworkPhases, ARefusedStepIsTakenAgainAsTheShorterStepBeforeIt) {
  ObserverOptions strict;
  strict.network_linearisation_tolerance = 5e-4;
  SeededRig rig(ObserverOptions{}, 0.05);
  CellObserver strict_observer(rig.nominal, strict);
  int errors = 0;
  double worst_N = 0.0;
  double peak_N = 0.0;
  for (int tick = 0; tick < 600; ++tick) {
    // The centre and its right neighbour: 0 -> 3 and 1.5 mm in 100 ms, held, out in 100 ms.
    const double ramp = tick < 100 ? tick / 100.0 : (tick < 400 ? 1.0 : std::max(0.0, (500 - tick) / 100.0));
    rig.depth[6] = 3e-3 * ramp;
    rig.depth[7] = 1.5e-3 * ramp;
    rig.tick();
    if (strict_observer.update(rig.sensors, rig.current, kTick_s) != Status::ok) {
      ++errors;
      continue;
    }
    const std::span<const double> a = rig.observer.force_N();
    const std::span<const double> b = strict_observer.force_N();
    for (std::size_t c = 0; c < a.size(); ++c) {
      worst_N = std::max(worst_N, std::abs(a[c] - b[c]));
      peak_N = std::max(peak_N, std::abs(a[c]));
    }
  }
  std::printf(
      "tolerance %.3g: %zu steps refused (default %zu), %d errors, largest force difference %.4f N of %.3f "
      "N\n",
      strict.network_linearisation_tolerance, strict_observer.network_steps_refused(),
      rig.observer.network_steps_refused(), errors, worst_N, peak_N);
  EXPECT_EQ(rig.observer.network_steps_refused(), 0U);
  EXPECT_GT(strict_observer.network_steps_refused(), 0U);
  EXPECT_EQ(errors, 0);
  EXPECT_LT(worst_N, 0.05 * peak_N);
  for (const double bad : {0.0, -0.1, std::numeric_limits<double>::infinity()}) {
    ObserverOptions wrong;
    wrong.network_linearisation_tolerance = bad;
    EXPECT_THROW(CellObserver(rig.nominal, wrong), mrskin::InvalidArgument) << bad;
  }
}

// The fit's misfit is computed when asked: the last update's, whatever exclusion follows it, and
// 0 after a reset.
TEST(ObserverInputs, TheMisfitIsTheLastUpdatesUntilTheNext) {
  SeededRig rig(ObserverOptions{}, 0.05);
  rig.depth[6] = 1e-3;
  for (int tick = 0; tick < 20; ++tick) {
    rig.tick();
  }
  const double misfit_m = rig.observer.sensor_misfit_m();
  EXPECT_GT(misfit_m, 0.0);
  EXPECT_LT(misfit_m, 1e-5);  // within a few of the sensors' 2 um of noise
  EXPECT_EQ(rig.observer.sensor_misfit_m(), misfit_m);
  ASSERT_EQ(rig.observer.set_sensor_excluded(3, true), Status::ok);
  EXPECT_EQ(rig.observer.sensor_misfit_m(), misfit_m);
  rig.tick();
  EXPECT_NE(rig.observer.sensor_misfit_m(), misfit_m);
  rig.observer.reset();
  EXPECT_EQ(rig.observer.sensor_misfit_m(), 0.0);
}

TEST(ObserverRest, ANegativeGateIsRefused) {
  const DeviceModel nominal(mrskin::model::default_profile());
  ObserverOptions bad;
  bad.rest_gate_sigma = -1.0;
  EXPECT_THROW(CellObserver(nominal, bad), mrskin::InvalidArgument);
  bad.rest_gate_sigma = std::numeric_limits<double>::quiet_NaN();
  EXPECT_THROW(CellObserver(nominal, bad), mrskin::InvalidArgument);
}

TEST(ObserverInputs, BadInputsAreRefusedAndStateKept) {
  const DeviceModel nominal(mrskin::model::default_profile());
  CellObserver observer(nominal, ObserverOptions{});
  std::vector<double> sensors(nominal.profile().sensors.size(), 1e-3);
  std::vector<double> current(nominal.layout().valve_count(), 0.0);
  ASSERT_EQ(observer.update(sensors, current, 1e-3), Status::ok);
  const std::vector<double> before(observer.indentation_m().begin(), observer.indentation_m().end());
  std::vector<double> bad = sensors;
  bad[3] = std::numeric_limits<double>::quiet_NaN();
  EXPECT_EQ(observer.update(bad, current, 1e-3), Status::not_finite);
  EXPECT_EQ(observer.update(std::span<const double>(sensors.data(), 5), current, 1e-3), Status::out_of_range);
  EXPECT_EQ(observer.update(sensors, current, 0.0), Status::out_of_range);
  EXPECT_EQ(observer.update(sensors, current, std::nan("")), Status::out_of_range);
  const std::vector<double> after(observer.indentation_m().begin(), observer.indentation_m().end());
  EXPECT_EQ(before, after);
  ObserverOptions wrong;
  wrong.sweeps = 0;
  EXPECT_THROW(CellObserver(nominal, wrong), mrskin::InvalidArgument);
}

// Large grids' noise floor (ObserverOptions::noise_floor_sigma) on the 16x16 (128 fluid cells):
// readings made from a depth map as the profile's sensors read it (the mean depth of the cells
// a valve joins), plus Gaussian noise of the sensors' sigma (seeded).
class NoiseFloor : public ::testing::Test {
 protected:
  NoiseFloor() : model_(mrskin::model::load_profile("fingertip-16x16")) {}

  // Fraction of cell-ticks with depth, the largest depth off `pressed`, and the last depth there.
  struct Seen {
    double with_depth = 0.0;
    double largest_elsewhere_m = 0.0;
    double pressed_m = 0.0;
  };
  Seen run(const ObserverOptions& options, std::size_t pressed, double depth_m, int ticks) {
    CellObserver observer(model_, options);
    const mrskin::model::DeviceProfile& p = model_.profile();
    std::vector<double> depth(model_.layout().fluid_cell_count(), 0.0);
    depth[pressed] = depth_m;
    std::vector<double> readings(p.sensors.size(), 0.0);
    std::vector<double> current(model_.layout().valve_count(), 0.0);
    std::mt19937 random(11);
    Seen seen;
    std::size_t touched = 0;
    for (int tick = 0; tick < ticks; ++tick) {
      for (std::size_t k = 0; k < p.sensors.size(); ++k) {
        const mrskin::model::SensorSpec& s = p.sensors[k];
        std::normal_distribution<double> noise(0.0, s.noise_std);
        double mean_m = depth[s.index];
        if (s.place == mrskin::model::PlaceKind::valve) {
          const std::vector<std::size_t>& joined = model_.layout().cells_of_valve(s.index);
          mean_m = 0.0;
          for (const std::size_t c : joined) {
            mean_m += depth[c] / static_cast<double>(joined.size());
          }
        }
        readings[k] = mean_m + noise(random);
      }
      EXPECT_EQ(observer.update(readings, current, 1e-3), Status::ok);
      const std::span<const double> d = observer.indentation_m();
      for (std::size_t c = 0; c < d.size(); ++c) {
        touched += d[c] > 0.0 ? 1 : 0;
        if (c != pressed) {
          seen.largest_elsewhere_m = std::max(seen.largest_elsewhere_m, d[c]);
        }
      }
      seen.pressed_m = d[pressed];
    }
    seen.with_depth = static_cast<double>(touched) / static_cast<double>(ticks * depth.size());
    return seen;
  }

  DeviceModel model_;
};

TEST_F(NoiseFloor, IdleNoiseLeavesTheCellsAtZero) {
  ObserverOptions without;
  without.noise_floor_sigma = 0.0;
  const Seen spread = run(without, 40, 0.0, 300);
  const Seen floor = run(ObserverOptions{}, 40, 0.0, 300);
  std::printf(
      "idle 16x16: cell-ticks with depth %.1f %% without the floor, %.2f %% with it; largest %.2f / %.2f "
      "um\n",
      100.0 * spread.with_depth, 100.0 * floor.with_depth, 1e6 * spread.largest_elsewhere_m,
      1e6 * floor.largest_elsewhere_m);
  EXPECT_GT(spread.with_depth, 0.2) << "without the floor noise spreads depth (the test would show nothing)";
  EXPECT_LT(floor.with_depth, 0.01);
  EXPECT_LT(floor.largest_elsewhere_m, 5e-6);
}

TEST_F(NoiseFloor, APressIsRecoveredWithinTheFloorsBias) {
  // An interior cell under four valve sensors that each average four cells: the floor costs
  // about 4 x 2 sigmas (4 um at 0.5 um) of its depth.
  const double sigma_m = model_.profile().sensors.front().noise_std;
  const std::size_t pressed = 60;
  const Seen seen = run(ObserverOptions{}, pressed, 100e-6, 400);
  std::printf("press 100 um on cell %zu: %.1f um estimated, at most %.2f um elsewhere\n", pressed,
              1e6 * seen.pressed_m, 1e6 * seen.largest_elsewhere_m);
  EXPECT_NEAR(seen.pressed_m, 100e-6 - 8.0 * sigma_m, 4.0 * sigma_m);
  EXPECT_LT(seen.largest_elsewhere_m, 10.0 * sigma_m);
}

TEST_F(NoiseFloor, ABadFloorIsRefused) {
  ObserverOptions bad;
  bad.noise_floor_sigma = -1.0;
  EXPECT_THROW(CellObserver(model_, bad), mrskin::InvalidArgument);
  bad.noise_floor_sigma = std::numeric_limits<double>::quiet_NaN();
  EXPECT_THROW(CellObserver(model_, bad), mrskin::InvalidArgument);
  bad.noise_floor_sigma = std::numeric_limits<double>::infinity();
  EXPECT_THROW(CellObserver(model_, bad), mrskin::InvalidArgument);
}

// Large grids carry the fit's residual from tick to tick (ObserverOptions::residual_refresh_ticks):
// the same depths and sensor residuals as computing it afresh every tick, through a press, its
// release, a sensor excluded and put back, and a reset.
TEST_F(NoiseFloor, TheCarriedResidualMatchesOneComputedEveryTick) {
  ObserverOptions afresh;
  afresh.residual_refresh_ticks = 1;
  ObserverOptions carried;  // the default: afresh every 1024 ticks
  CellObserver a(model_, afresh);
  CellObserver b(model_, carried);
  const mrskin::model::DeviceProfile& p = model_.profile();
  const std::size_t cells = model_.layout().fluid_cell_count();
  std::vector<double> depth(cells, 0.0);
  std::vector<double> readings(p.sensors.size(), 0.0);
  std::vector<double> current(model_.layout().valve_count(), 0.0);
  std::mt19937 random(5);
  double worst_depth_m = 0.0;
  double worst_residual_sigma = 0.0;
  std::size_t moved_ticks = 0;
  for (int tick = 0; tick < 2500; ++tick) {
    // A press on cells 60 and 61 from tick 200 to 1400 (up to 150 um), noise throughout.
    const double press_m =
        tick < 200 || tick > 1400 ? 0.0 : 150e-6 * std::sin(3.14159 * (tick - 200) / 1200.0);
    depth[60] = press_m;
    depth[61] = 0.5 * press_m;
    for (std::size_t k = 0; k < p.sensors.size(); ++k) {
      const mrskin::model::SensorSpec& s = p.sensors[k];
      std::normal_distribution<double> noise(0.0, s.noise_std);
      double mean_m = s.place == mrskin::model::PlaceKind::fluid_cell ? depth[s.index] : 0.0;
      if (s.place == mrskin::model::PlaceKind::valve) {
        const std::vector<std::size_t>& joined = model_.layout().cells_of_valve(s.index);
        for (const std::size_t c : joined) {
          mean_m += depth[c] / static_cast<double>(joined.size());
        }
      }
      readings[k] = mean_m + noise(random);
    }
    if (tick == 700 || tick == 900) {  // a sensor out, then back
      ASSERT_EQ(a.set_sensor_excluded(5, tick == 700), Status::ok);
      ASSERT_EQ(b.set_sensor_excluded(5, tick == 700), Status::ok);
    }
    if (tick == 2000) {
      a.reset();
      b.reset();
    }
    ASSERT_EQ(a.update(readings, current, 1e-3), Status::ok);
    ASSERT_EQ(b.update(readings, current, 1e-3), Status::ok);
    const std::span<const double> da = a.indentation_m();
    const std::span<const double> db = b.indentation_m();
    for (std::size_t c = 0; c < cells; ++c) {
      worst_depth_m = std::max(worst_depth_m, std::abs(da[c] - db[c]));
    }
    moved_ticks += da[60] > 0.0 ? 1 : 0;
    const std::span<const double> ra = a.sensor_residual_sigma();
    const std::span<const double> rb = b.sensor_residual_sigma();
    for (std::size_t k = 0; k < ra.size(); ++k) {
      worst_residual_sigma = std::max(worst_residual_sigma, std::abs(ra[k] - rb[k]));
    }
  }
  std::printf(
      "carried against afresh: depths within %.3g m, residuals within %.3g sigma; %zu ticks pressed\n",
      worst_depth_m, worst_residual_sigma, moved_ticks);
  EXPECT_GT(moved_ticks, 800U) << "the press must show (or the comparison proves little)";
  EXPECT_LT(worst_depth_m, 1e-12);  // round-off: a thousandth of a nanometre
  EXPECT_LT(worst_residual_sigma, 1e-6);
  ObserverOptions bad;
  bad.residual_refresh_ticks = 0;
  EXPECT_THROW(CellObserver(model_, bad), mrskin::InvalidArgument);
}

// Net outflow per fluid cell from the network model's passages: a press through open valves
// sends fluid out; the same press (1 mm, below the full-current threshold) held behind valves at
// full current seals the cell. The local
// force model tracks no flows.
TEST(ObserverFlows, OpenValvesFlowAndFullCurrentSeals) {
  const DeviceModel nominal(mrskin::model::default_profile());
  const std::size_t centre = 6;  // the default 5 x 5's centre fluid cell
  auto outflow_while_pressing = [&](double current_A, double hold_s) {
    NetworkPlant plant(nominal.profile(), ideal());
    CellObserver observer(nominal, ObserverOptions{});
    std::vector<double> depth(nominal.layout().fluid_cell_count(), 0.0);
    std::vector<double> sensors(plant.sensor_count());
    std::vector<double> current(nominal.layout().valve_count(), current_A);
    plant.set_valve_currents(current);
    const int ramp = 500;  // 0 -> 1 mm in 0.5 s (2 mm/s), then held
    const int total = ramp + static_cast<int>(hold_s * 1000.0);
    for (int tick = 1; tick <= total; ++tick) {
      depth[centre] = 1e-3 * std::min(1.0, static_cast<double>(tick) / ramp);
      plant.set_finger_indentation(depth);
      for (int s = 0; s < kSubsteps; ++s) {
        plant.step(kTick_s / kSubsteps);
      }
      plant.read_sensors(sensors);
      EXPECT_EQ(observer.update(sensors, current, kTick_s), Status::ok);
    }
    EXPECT_EQ(observer.outflow_m3_per_s().size(), nominal.layout().fluid_cell_count());
    return observer.outflow_m3_per_s()[centre];
  };
  EXPECT_GT(outflow_while_pressing(0.0, 0.0), 1e-7);  // loading at 2 mm/s through open valves
  EXPECT_LT(outflow_while_pressing(0.1, 0.2), 1e-9);  // held at full current: sealed (creep 3e-10)
  ObserverOptions local;
  local.force_model = mrskin::model::ObserverForceModel::local;
  EXPECT_TRUE(CellObserver(nominal, local).outflow_m3_per_s().empty());
}

// The coil pass is skipped while the currents are bit for bit those on which no coil moved the tick
// before (ObserverCoils: 2,048 valves on the palm). A current that changes after the coils settled
// must still reach the yields: two rigs held on the same currents until every coil settled read
// the same force, and after one valve changed in one of them, different forces.
TEST(ObserverCoils, ACurrentChangedAfterTheCoilsSettledReachesTheForces) {
  SeededRig held(ObserverOptions{}, 0.03);
  SeededRig changed(ObserverOptions{}, 0.03);
  constexpr std::size_t kCell = 6;            // the centre
  for (int tick = 1; tick <= 1500; ++tick) {  // a 2 mm press, held: the coils settle (tau ~5 ms)
    const double depth_m = 2e-3 * std::min(1.0, tick / 500.0);
    held.depth[kCell] = depth_m;
    changed.depth[kCell] = depth_m;
    held.tick();
    changed.tick();
  }
  ASSERT_EQ(held.observer.force_N()[kCell], changed.observer.force_N()[kCell]);
  const std::size_t valve = changed.nominal.layout().valves_of_cell(kCell).front();
  changed.current[valve] = 0.06;
  for (int tick = 0; tick < 50; ++tick) {
    held.tick();
    changed.tick();
  }
  EXPECT_NE(held.observer.force_N()[kCell], changed.observer.force_N()[kCell]);
}

// After a release the network relaxes through valves at their yield (the observer's steel keeps a
// remanent yield at 0 A): its flow decays about as 1/t^2 and never counts as settled in seconds. Untouched,
// the observer then steps it several ticks at once while the largest link moves at most 1 nL in the ticks a
// step runs ahead. The next press must see the same forces as an observer that steps every tick.
TEST(ObserverFlows, AReleasedSkinsSlowTailIsSteppedSeveralTicksAtOnce) {
  const DeviceModel nominal(mrskin::model::default_profile());
  const std::size_t centre = 6;  // the default 5 x 5's centre fluid cell
  NetworkPlant plant(nominal.profile(), ideal());
  ObserverOptions every_tick_options;
  every_tick_options.skip_settled_network = false;
  CellObserver lazy(nominal, ObserverOptions{});
  CellObserver every_tick(nominal, every_tick_options);
  std::vector<double> depth(nominal.layout().fluid_cell_count(), 0.0);
  std::vector<double> sensors(plant.sensor_count());
  std::vector<double> current(nominal.layout().valve_count(), 0.05);  // released at 0 A
  std::vector<double> last_outflow(depth.size(), 0.0);
  int tail_ticks = 0;
  int tail_steps = 0;
  double worst_force_N = 0.0;
  double peak_force_N = 0.0;
  constexpr int kRelease = 800;     // pressed 0 -> 3 mm over 0.5 s, held to 0.8 s, released
  constexpr int kNextPress = 6800;  // 6 s untouched, then pressed again for 0.3 s
  for (int tick = 1; tick <= kNextPress + 300; ++tick) {
    double d = 0.0;
    if (tick < kRelease) {
      d = 3e-3 * std::min(1.0, tick / 500.0);
    } else if (tick >= kNextPress) {
      d = 3e-3 * std::min(1.0, (tick - kNextPress) / 300.0);
    }
    depth[centre] = d;
    std::fill(current.begin(), current.end(), tick < kRelease ? 0.05 : 0.0);
    plant.set_valve_currents(current);
    plant.set_finger_indentation(depth);
    for (int s = 0; s < kSubsteps; ++s) {
      plant.step(kTick_s / kSubsteps);
    }
    plant.read_sensors(sensors);
    ASSERT_EQ(lazy.update(sensors, current, kTick_s), Status::ok);
    ASSERT_EQ(every_tick.update(sensors, current, kTick_s), Status::ok);
    const std::span<const double> q = lazy.outflow_m3_per_s();
    if (tick > kNextPress - 2000 && tick < kNextPress) {  // the last 2 s untouched
      ++tail_ticks;
      tail_steps += std::equal(q.begin(), q.end(), last_outflow.begin()) ? 0 : 1;
    }
    std::copy(q.begin(), q.end(), last_outflow.begin());
    if (tick >= kNextPress) {
      worst_force_N =
          std::max(worst_force_N, std::abs(lazy.force_N()[centre] - every_tick.force_N()[centre]));
      peak_force_N = std::max(peak_force_N, every_tick.force_N()[centre]);
    }
  }
  std::printf(
      "released skin's tail: %d network steps in the last %d untouched ticks; next press %.3f N, "
      "forces apart by %.2e N at most\n",
      tail_steps, tail_ticks, peak_force_N, worst_force_N);
  EXPECT_GT(peak_force_N, 0.1);  // the press is a press
  EXPECT_LT(tail_steps, tail_ticks / 4);
  EXPECT_LT(worst_force_N, 1e-3);
}

// The compensated current lands the plant's hysteretic valve (magnetic.hpp's play operator, run
// exactly) on the yield the anhysteretic curve gives at the requested current, coming down from
// a high current and going up from a low one.
TEST(ObserverHysteresis, CompensatedCurrentReachesTheAnhystereticYield) {
  const DeviceModel nominal(mrskin::model::default_profile());
  const auto& profile = nominal.profile();
  ASSERT_GT(profile.magnetic.steel.coercivity_A_per_m, 0.0);
  for (const auto& [from_A, wanted_A] :
       {std::pair{0.08, 0.02}, std::pair{0.01, 0.05}, std::pair{0.06, 0.03}}) {
    SCOPED_TRACE(testing::Message() << from_A << " A -> " << wanted_A << " A");
    CellObserver observer(nominal, ObserverOptions{});
    std::vector<double> sensors(profile.sensors.size(), 0.0);
    std::vector<double> current(nominal.layout().valve_count(), from_A);
    for (int i = 0; i < 200; ++i) {  // 40 coil time constants: settled
      ASSERT_EQ(observer.update(sensors, current, 1e-3), Status::ok);
    }
    const double command_A = observer.hysteresis_compensated_current_A(0, wanted_A);
    EXPECT_EQ(from_A > wanted_A, command_A < wanted_A);
    mrskin::model::HysteresisState plant{};
    ASSERT_TRUE(mrskin::model::gap_field_hysteretic(profile.magnetic, profile.fluid, from_A, plant).ok());
    const auto reached =
        mrskin::model::gap_field_hysteretic(profile.magnetic, profile.fluid, command_A, plant);
    const auto anhysteretic = mrskin::model::gap_field(profile.magnetic, profile.fluid, wanted_A);
    ASSERT_TRUE(reached.ok() && anhysteretic.ok());
    EXPECT_NEAR(reached.value.yield_stress_Pa, anhysteretic.value.yield_stress_Pa,
                0.01 * anhysteretic.value.yield_stress_Pa);
  }
  EXPECT_EQ(CellObserver(nominal, ObserverOptions{}).hysteresis_compensated_current_A(0, 0.0), 0.0);
}

TEST(ObserverHotPath, UpdateDoesNotAllocate) {
  const DeviceModel nominal(mrskin::model::default_profile());
  ObserverOptions line;
  line.rate_estimator = mrskin::model::RateEstimator::segmented_line;
  for (const ObserverOptions& options : {ObserverOptions{}, line}) {
    CellObserver observer(nominal, options);
    std::vector<double> sensors(nominal.profile().sensors.size(), 0.0);
    std::vector<double> current(nominal.layout().valve_count(), 0.04);
    ASSERT_EQ(observer.update(sensors, current, 1e-3), Status::ok);
    const auto before = mrskin::test::allocation_count();
    for (int i = 0; i < 300; ++i) {
      sensors[4] = 1e-3 * std::sin(i * 0.02);
      (void)observer.update(sensors, current, 1e-3);
    }
    EXPECT_EQ(mrskin::test::allocation_count(), before);
  }
}

}  // namespace
