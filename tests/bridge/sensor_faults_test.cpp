// Sensor faults (issue 25): stuck, noisy and offset sensors found from the readings and the
// observer's residuals, within 200 ms, reported with the sensor and its cells; no false alarm on
// the built-in scenes over seeds 1-8; the faulty sensor leaves the fit, and a cell left with no
// sensor releases the valves. Closed loop on the simulated clock against the perturbed mock.
#include "mrskin/bridge/sensor_faults.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/driver/layout.hpp"
#include "mrskin/driver/model/profile.hpp"
#include "mrskin/eval/truth_scorer.hpp"
#include "mrskin/sim/open_mock.hpp"

namespace mrskin::bridge {
namespace {

struct FaultRun {
  BridgeStats stats;
  std::vector<SensorFaultEvent> events;
  double max_noise_ratio = 0.0;    // over healthy sensors and readings
  double max_mean_residual = 0.0;  // |mean residual|, sigmas, healthy sensors
  bool halted = false;
  DeviceState state = DeviceState::disabled;
  std::vector<double> currents_A;
};

// late_fraction > 0: the host misses periods as a starved daemon does (the unit runs on each
// millisecond; the loop wakes late on about that fraction of them, in runs of 1-12 periods).
FaultRun run(const std::string& scene_name, double seconds, const std::string& uri,
             const BridgeOptions& options = {}, double late_fraction = 0.0) {
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  OpenedDevice dev = open_device(uri, clock, open);
  auto scene = make_scene(scene_name);
  Bridge loop(*dev.session, *scene, options);
  sim::MockDeviceTruth truth(*sim::mock_of(dev));
  eval::TruthScorer scorer(truth, sim::mock_of(dev)->layout().fluid_cell_count(), loop.options());
  loop.set_tick_watcher(&scorer);
  loop.set_perf_clock(&clock);
  scene->set_start(clock.now());
  EXPECT_EQ(loop.enable(), ResultCode::ok);
  std::vector<double> finger(sim::mock_of(dev)->layout().fluid_cell_count());
  FaultRun r;
  const SensorFaultMonitor& monitor = loop.sensor_fault_monitor();
  const auto ticks = static_cast<int>(seconds * 1000.0);
  std::mt19937_64 late_rng(11);
  std::uniform_int_distribution<int> late_run(1, 12);
  // A run of r late periods starts with probability q: late runs cover f = q r / (1 + q r).
  const double late_start = late_fraction / (6.5 * (1.0 - late_fraction));
  int late_left = 0;
  for (int k = 0; k < ticks; ++k) {
    mrskin::eval::press_scene_finger(*scene, to_seconds(clock.now() - scene->start()),
                                     sim::mock_of(dev)->layout(), finger, loop.scale().length);
    sim::mock_of(dev)->set_finger_indentation(finger);
    sim::mock_of(dev)->step(clock.now());
    if (late_left == 0 && late_fraction > 0.0 && std::generate_canonical<double, 53>(late_rng) < late_start) {
      late_left = late_run(late_rng);
    }
    if (late_left > 0) {
      --late_left;
    } else {
      (void)loop.step(clock.now());
    }
    clock.advance(std::chrono::milliseconds(1));
    for (std::size_t s = 0; s < dev.session->sensors().size(); ++s) {
      if (monitor.fault(s) == SensorFault::none) {
        r.max_noise_ratio = std::max(r.max_noise_ratio, monitor.noise_ratio(s));
        r.max_mean_residual = std::max(r.max_mean_residual, std::abs(monitor.mean_residual_sigma(s)));
      }
    }
    SensorFaultEvent e;
    while (loop.take_sensor_fault(e)) {
      r.events.push_back(e);
    }
  }
  r.stats = loop.stats();
  r.halted = loop.halted();
  r.state = dev.session->state();
  r.currents_A.resize(sim::mock_of(dev)->layout().valve_count());
  sim::mock_of(dev)->applied_currents(r.currents_A);
  return r;
}

// ---- the monitor alone, on synthetic readings --------------------------------------------------

class Monitor : public ::testing::Test {
 protected:
  model::DeviceProfile profile = model::load_profile("mr-skin-5x5");
  GridLayout layout{profile.rows, profile.cols};
  std::mt19937_64 rng{7};
  std::normal_distribution<double> normal{0.0, 1.0};

  // Healthy readings at depth_m for every sensor: the profile's noise, quantised.
  std::vector<double> readings(double depth_m) {
    std::vector<double> y(profile.sensors.size());
    for (std::size_t k = 0; k < y.size(); ++k) {
      const model::SensorSpec& s = profile.sensors[k];
      y[k] = std::nearbyint((depth_m + s.noise_std * normal(rng)) / s.resolution) * s.resolution;
    }
    return y;
  }
};

TEST_F(Monitor, HealthySensorsRaiseNothingInAMillionReadings) {
  SensorFaultMonitor m(profile, layout, {});
  const std::vector<double> residual(profile.sensors.size(), 0.0);
  for (int k = 0; k < 1'000'000; ++k) {
    ASSERT_EQ(m.update(readings(0.0), residual), SensorFaultMonitor::npos) << "reading " << k;
  }
  EXPECT_EQ(m.faulty_count(), 0U);
}

TEST_F(Monitor, AStuckSensorIsFoundWithinItsRun) {
  SensorFaultMonitor m(profile, layout, {});
  // 2 um of noise on a 2.5 um step: a healthy reading repeats with p <= 0.47 each time.
  const std::size_t run = m.stuck_run_readings(3);
  EXPECT_GE(run, 30U);
  EXPECT_LE(run, 45U);
  const std::vector<double> residual(profile.sensors.size(), 0.0);
  std::size_t found = SensorFaultMonitor::npos;
  std::size_t at = 0;
  for (std::size_t k = 0; k < 200 && found == SensorFaultMonitor::npos; ++k) {
    std::vector<double> y = readings(0.0);
    y[3] = 5e-6;
    found = m.update(y, residual);
    at = k + 1;
  }
  EXPECT_EQ(found, 3U);
  EXPECT_EQ(m.fault(3), SensorFault::stuck);
  EXPECT_EQ(at, run);
  EXPECT_DOUBLE_EQ(m.evidence(3), 5e-6);
  // Sensor 3 sits under a valve and reads its cells: they keep other readers.
  EXPECT_FALSE(m.cells_of_sensor(3).empty());
  EXPECT_EQ(m.unobservable_cell(), SensorFaultMonitor::npos);
  EXPECT_EQ(m.healthy_count(), profile.sensors.size() - 1);
}

// A unit's declared deadband (protocol 1.2's SensorDeadband: 2 counts, 5 um here) holds a
// healthy reading for as long as its value stays within the band: no run of such repeats is a
// stuck sensor. A stuck one is found once the observer's residual for it leaves what the band
// explains, within its run.
// A reading that is not finite skips only its own sensor (the lean pass gives way to the full
// one while the sensors' histories differ): a stuck sensor 3 is found at its run whatever sensor
// 5 reads, and one reading later when its own reading was lost once, on the first reading (the
// histories then differ for two readings) or later.
TEST_F(Monitor, AReadingThatIsNotFiniteSkipsOnlyItsSensor) {
  const std::vector<double> residual(profile.sensors.size(), 0.0);
  for (const std::size_t lost : {std::size_t{5}, std::size_t{3}}) {
    for (const std::size_t lost_at : {std::size_t{0}, std::size_t{1}, std::size_t{10}}) {
      SensorFaultMonitor m(profile, layout, {});
      const std::size_t run = m.stuck_run_readings(3);
      std::size_t found = SensorFaultMonitor::npos;
      std::size_t at = 0;
      for (std::size_t k = 0; k < 200 && found == SensorFaultMonitor::npos; ++k) {
        std::vector<double> y = readings(0.0);
        y[3] = 5e-6;
        if (k == lost_at) {
          y[lost] = std::numeric_limits<double>::quiet_NaN();
        }
        found = m.update(y, residual);
        at = k + 1;
      }
      EXPECT_EQ(found, 3U) << lost << " at " << lost_at;
      EXPECT_EQ(at, lost == 3 ? run + 1 : run) << lost << " at " << lost_at;
      EXPECT_EQ(m.faulty_count(), 1U) << lost << " at " << lost_at;
      EXPECT_LT(m.noise_ratio(5), 25.0) << lost << " at " << lost_at;
    }
  }
}

TEST_F(Monitor, ARepeatWithinADeadbandIsNoEvidenceOfAStuckSensor) {
  const double band_m = 2 * profile.sensors[3].resolution;
  SensorFaultMonitor m(profile, layout, {}, band_m);
  const std::size_t run = m.stuck_run_readings(3);
  const double sigma = std::sqrt(std::pow(profile.sensors[3].noise_std, 2) +
                                 std::pow(profile.sensors[3].resolution, 2) / 12.0);
  const double band_sigma = band_m / sigma;
  std::vector<double> residual(profile.sensors.size(), 0.0);
  // Every reading held (the band at rest), with residuals up to what the band explains.
  const std::vector<double> held = readings(0.0);
  for (std::size_t k = 0; k < 100 * run; ++k) {
    residual[3] = (k % 2 == 0 ? 1.0 : -1.0) * (band_sigma + SensorFaultMonitor::kDeadbandMarginSigma);
    ASSERT_EQ(m.update(held, residual), SensorFaultMonitor::npos) << "reading " << k;
  }
  // The finger moves; sensor 3 stays where it was, and its residual grows past the band.
  residual[3] = band_sigma + SensorFaultMonitor::kDeadbandMarginSigma + 1.0;
  std::size_t found = SensorFaultMonitor::npos;
  std::size_t at = 0;
  for (std::size_t k = 0; k < 2 * run && found == SensorFaultMonitor::npos; ++k) {
    std::vector<double> y = readings(50e-6);
    y[3] = held[3];
    found = m.update(y, residual);
    at = k + 1;
  }
  EXPECT_EQ(found, 3U);
  EXPECT_EQ(m.fault(3), SensorFault::stuck);
  EXPECT_LE(at, run);  // the held readings before counted for nothing, and reset nothing either
  EXPECT_THROW(SensorFaultMonitor(profile, layout, {}, -1e-6), InvalidArgument);
  EXPECT_THROW(SensorFaultMonitor(profile, layout, {}, std::nan("")), InvalidArgument);
}

TEST_F(Monitor, ANoisySensorIsFound) {
  SensorFaultMonitor m(profile, layout, {});
  const std::vector<double> residual(profile.sensors.size(), 0.0);
  std::size_t found = SensorFaultMonitor::npos;
  int at = 0;
  for (int k = 0; k < 200 && found == SensorFaultMonitor::npos; ++k) {
    std::vector<double> y = readings(0.0);
    y[4] += 50e-6 * normal(rng);  // the mock's noisy fault: 20 steps of 2.5 um
    found = m.update(y, residual);
    at = k + 1;
  }
  EXPECT_EQ(found, 4U);
  EXPECT_EQ(m.fault(4), SensorFault::noisy);
  EXPECT_LE(at, 20);
}

// Readings of a finger pressing at 10 mm/s, read 1-12 ms apart: taken as evenly spaced, the
// second difference reads the press as noise; spaced by the unit's clock (wrapping past 2^32 us
// on the way), it is the sensors' own noise. A noisy sensor read so is still found.
TEST_F(Monitor, UnevenlySpacedReadingsOfAMovingFingerAreNoNoise) {
  const std::vector<double> residual(profile.sensors.size(), 0.0);
  constexpr double kRate_m_per_s = 0.01;
  for (const bool timed : {false, true}) {
    SensorFaultMonitor m(profile, layout, {});
    std::mt19937_64 gaps(3);
    std::uniform_int_distribution<std::uint32_t> gap_ms(1, 12);
    std::uint32_t t_us = 0xFFFFFFFFU - 50'000U;
    double t_s = 0.0;
    std::size_t found = SensorFaultMonitor::npos;
    for (int k = 0; k < 2000 && found == SensorFaultMonitor::npos; ++k) {
      const std::uint32_t gap_us = 1000U * gap_ms(gaps);
      t_us += gap_us;
      t_s += 1e-6 * gap_us;
      const std::vector<double> y = readings(kRate_m_per_s * std::fmod(t_s, 0.2));  // 2 mm presses
      found = timed ? m.update(y, residual, t_us) : m.update(y, residual);
    }
    if (timed) {
      EXPECT_EQ(found, SensorFaultMonitor::npos) << "sensor " << found << " " << to_string(m.fault(found));
    } else {
      EXPECT_NE(found, SensorFaultMonitor::npos);  // the even spacing's false alarm, shown
    }
  }
  SensorFaultMonitor m(profile, layout, {});
  std::uint32_t t_us = 0;
  std::size_t found = SensorFaultMonitor::npos;
  int at = 0;
  for (int k = 0; k < 200 && found == SensorFaultMonitor::npos; ++k) {
    t_us += 1000U * static_cast<std::uint32_t>(1 + k % 7);
    std::vector<double> y = readings(kRate_m_per_s * 1e-6 * t_us);
    y[4] += 50e-6 * normal(rng);
    found = m.update(y, residual, t_us);
    at = k + 1;
  }
  EXPECT_EQ(found, 4U);
  EXPECT_EQ(m.fault(4), SensorFault::noisy);
  EXPECT_LE(at, 20);
}

// The spacing across what else reaches the monitor: a restart after a gap (the finger far on),
// readings without a time (taken as even), a reading twice at the same time, a gap of 2^31 us, and
// a lost reading on one sensor while the finger moves (the full pass weighs as the lean one: the
// other sensors' figures are those of a monitor that lost nothing).
TEST_F(Monitor, TheSpacingHoldsAcrossRestartsUntimedAndLostReadings) {
  const std::vector<double> residual(profile.sensors.size(), 0.0);
  SensorFaultMonitor lost(profile, layout, {});
  SensorFaultMonitor whole(profile, layout, {});
  std::mt19937_64 gaps(5);
  std::uniform_int_distribution<std::uint32_t> gap_ms(1, 9);
  std::uint32_t t_us = 0xFFFFFFFFU - 20'000U;  // wraps within the first readings
  double t_s = 0.0;
  double worst = 0.0;
  // A finger pressing 1 mm deep and back once a second (up to 6.3 mm/s).
  const auto depth_at = [](double s) { return 1e-3 * (1.0 - std::cos(2.0 * 3.14159265358979 * s)); };
  std::vector<double> y = readings(0.0);
  for (int k = 0; k < 3000; ++k) {
    std::uint32_t gap_us = 1000U * gap_ms(gaps);
    double gap_s = 1e-6 * gap_us;
    if (k == 800) {  // the host away 0.5 s: the history starts again
      lost.restart_history();
      whole.restart_history();
      gap_us = 500'000U;
      gap_s = 0.5;
    }
    const bool untimed = k >= 1000 && k < 1100;  // readings 1 ms apart that came without a time
    if (untimed) {
      gap_s = 1e-3;
    }
    if (k == 1500) {
      gap_us = 0x80000000U;  // the unit's clock jumped 2^31 us between readings 1 ms apart
    }
    t_us += gap_us;
    t_s += gap_s;
    if (k != 1700) {  // reading 1700 is reading 1699's sample again, at its time
      y = readings(depth_at(t_s));
    } else {
      t_us -= gap_us;
    }
    std::vector<double> y_lost = y;
    if (k == 2000 || k == 2001 || k == 2500) {
      y_lost[5] = std::numeric_limits<double>::quiet_NaN();
    }
    const std::size_t a = untimed ? lost.update(y_lost, residual) : lost.update(y_lost, residual, t_us);
    const std::size_t b = untimed ? whole.update(y, residual) : whole.update(y, residual, t_us);
    ASSERT_EQ(a, SensorFaultMonitor::npos) << "reading " << k << ": sensor " << a;
    ASSERT_EQ(b, SensorFaultMonitor::npos) << "reading " << k << ": sensor " << b;
    for (std::size_t s = 0; s < y.size(); ++s) {
      if (k < 1500 || k > 1600) {  // the clock's jump passes for two readings' worth of motion
        worst = std::max(worst, whole.noise_ratio(s));
      }
      if (s != 5 && k >= 2000) {
        ASSERT_DOUBLE_EQ(lost.noise_ratio(s), whole.noise_ratio(s)) << "reading " << k << ", sensor " << s;
      }
    }
  }
  EXPECT_LT(worst, 8.0);
}

TEST_F(Monitor, AnOffsetResidualIsFoundAndTheLargestIsBlamed) {
  SensorFaultMonitor m(profile, layout, {});
  std::vector<double> residual(profile.sensors.size(), 0.0);
  residual[2] = -40.0;  // the fit spreads one shifted zero a little onto the neighbours
  residual[5] = 12.0;
  std::size_t found = SensorFaultMonitor::npos;
  for (int k = 0; k < 200 && found == SensorFaultMonitor::npos; ++k) {
    found = m.update(readings(0.0), residual);
  }
  EXPECT_EQ(found, 2U);
  EXPECT_EQ(m.fault(2), SensorFault::offset);
  EXPECT_LT(m.evidence(2), -15.0);
}

// The fit splits a shift on sensor 0 evenly between sensor 0 and sensor 2 (they read the same
// cells): +29 and -29 sigma, with sensors 1 and 3 also below zero (the pattern offset:0 leaves on
// the 5x5). Sensor 2 even a little ahead: the blame goes to the sensor its neighbours oppose.
TEST_F(Monitor, AnEvenlySplitShiftIsBlamedOnTheSensorItsNeighboursOppose) {
  SensorFaultMonitor m(profile, layout, {});
  std::vector<double> residual(profile.sensors.size(), 0.0);
  residual[0] = 29.0;
  residual[1] = -18.6;
  residual[2] = -29.5;
  residual[3] = -13.8;
  std::size_t found = SensorFaultMonitor::npos;
  for (int k = 0; k < 200 && found == SensorFaultMonitor::npos; ++k) {
    found = m.update(readings(0.0), residual);
  }
  EXPECT_EQ(found, 0U);
  EXPECT_EQ(m.fault(0), SensorFault::offset);
  EXPECT_EQ(m.fault(2), SensorFault::none);
  EXPECT_GT(m.evidence(0), 14.0);
}

TEST_F(Monitor, ACellWithNoHealthySensorLeftIsNamed) {
  SensorFaultMonitor m(profile, layout, {});
  // The corner cell is read by two valve sensors: stick both.
  const std::size_t corner = 0;
  const std::vector<std::size_t>& valves = layout.valves_of_cell(corner);
  ASSERT_EQ(valves.size(), 2U);
  const std::vector<double> residual(profile.sensors.size(), 0.0);
  std::vector<std::size_t> found;
  for (int k = 0; k < 300; ++k) {
    std::vector<double> y = readings(0.0);
    y[valves[0]] = 0.0;  // sensors are generated under the valves, in valve order
    y[valves[1]] = 0.0;
    if (const std::size_t s = m.update(y, residual); s != SensorFaultMonitor::npos) {
      found.push_back(s);
    }
  }
  ASSERT_EQ(found.size(), 2U);
  EXPECT_EQ(m.unobservable_cell(), corner);
  m.reset();
  EXPECT_EQ(m.faulty_count(), 0U);
  EXPECT_EQ(m.unobservable_cell(), SensorFaultMonitor::npos);
}

// Any one sensor may fail on a built-in unit: every fluid cell is read by at least two.
TEST(SensorCoverage, EveryCellOfTheBuiltInProfilesHasTwoSensors) {
  for (const char* name : {"mr-skin-5x5", "fingertip-16x16", "palm-64x64", "paper-table4"}) {
    const model::DeviceProfile profile = model::load_profile(name);
    const GridLayout layout(profile.rows, profile.cols);
    const SensorFaultMonitor m(profile, layout, {});
    std::vector<int> readers(layout.fluid_cell_count(), 0);
    for (std::size_t k = 0; k < profile.sensors.size(); ++k) {
      for (const std::size_t c : m.cells_of_sensor(k)) {
        ++readers.at(c);
      }
    }
    EXPECT_GE(*std::min_element(readers.begin(), readers.end()), 2) << name;
  }
}

TEST_F(Monitor, BadOptionsAreRefused) {
  SensorFaultOptions o;
  o.noise_ratio_limit = 0.5;
  EXPECT_THROW(SensorFaultMonitor(profile, layout, o), InvalidArgument);
  o = {};
  o.false_alarm_probability = 0.0;
  EXPECT_THROW(SensorFaultMonitor(profile, layout, o), InvalidArgument);
}

// ---- closed loop on the mock ----------------------------------------------------------------------

#ifdef MRSKIN_SANITIZED
constexpr bool kFull = false;  // sanitizer builds look for memory errors: one seed, 2 s
#else
constexpr bool kFull = true;
#endif

struct SensorCase {
  const char* fault;
  std::size_t sensor;
  SensorFault kind;
};

class OneFaultySensor : public ::testing::TestWithParam<SensorCase> {};

// Found within 200 ms of its start (t = 0), named, left out of the fit: the rendering holds the
// product's figure on the 11 sensors left (stuck:3 rendered 0.11 N RMS before it was detected).
TEST_P(OneFaultySensor, IsFoundNamedAndLeftOut) {
  const SensorCase c = GetParam();
  const FaultRun r = run("demo", kFull ? 4.0 : 1.0, std::string("mock://?seed=7&faults=") + c.fault);
  std::printf("%-9s", c.fault);
  for (const SensorFaultEvent& e : r.events) {
    std::printf("  sensor %zu %s at %.3f s (evidence %.3g, %zu sensors left)", e.sensor, to_string(e.fault),
                e.at_s, e.evidence, e.healthy_left);
  }
  std::printf("  rms %.4f N (true state %.4f N)", r.stats.force_rms_error_N(),
              r.stats.true_state_rms_error_N());
  if (kFull) {  // the same run with the sensor left in the fit
    BridgeOptions blind;
    blind.sensor_faults.enabled = false;
    const FaultRun b = run("demo", 4.0, std::string("mock://?seed=7&faults=") + c.fault, blind);
    std::printf("; undetected: rms %.4f N (true state %.4f N)", b.stats.force_rms_error_N(),
                b.stats.true_state_rms_error_N());
  }
  std::printf("\n");
  ASSERT_EQ(r.events.size(), 1U);
  EXPECT_EQ(r.events[0].sensor, c.sensor);
  EXPECT_EQ(r.events[0].fault, c.kind);
  EXPECT_LE(r.events[0].at_s, 0.2);
  EXPECT_EQ(r.events[0].healthy_left, 11U);
  EXPECT_EQ(r.events[0].unobservable_cell, SensorFaultMonitor::npos);
  EXPECT_EQ(r.stats.sensor_faults, 1U);
  EXPECT_EQ(r.stats.sensor_fault_halts, 0U);
  EXPECT_FALSE(r.halted);
  EXPECT_EQ(r.state, DeviceState::enabled);
  if (kFull) {
    EXPECT_LE(r.stats.force_rms_error_N(), 0.04);
    EXPECT_LE(r.stats.true_state_rms_error_N(), 0.04);
  }
}

INSTANTIATE_TEST_SUITE_P(MockFaults, OneFaultySensor,
                         ::testing::Values(SensorCase{"stuck:3", 3, SensorFault::stuck},
                                           SensorCase{"noisy:4", 4, SensorFault::noisy},
                                           SensorCase{"offset:3", 3, SensorFault::offset},
                                           SensorCase{"offset:0", 0, SensorFault::offset},
                                           SensorCase{"stuck:11", 11, SensorFault::stuck}),
                         [](const ::testing::TestParamInfo<SensorCase>& p) {
                           std::string name = p.param.fault;
                           std::replace(name.begin(), name.end(), ':', '_');
                           return name;
                         });

// A shifted zero on any one sensor is blamed on that sensor, whatever the fit's sweeps (the fit
// splits some shifts evenly between two sensors: offset:7 was blamed on sensor 10 before the
// neighbours' signs decided, and with 4 sweeps offset:0, :7 and :10 were).
TEST(SensorFaults, AShiftOnAnySensorIsBlamedOnIt) {
  const std::size_t sensors = model::load_profile("mr-skin-5x5").sensors.size();
  for (const int sweeps : {6, 4}) {
    BridgeOptions options;
    options.observer.small_grid_sweeps = sweeps;
    for (std::size_t k = 0; k < sensors; ++k) {
      const FaultRun r = run("demo", 0.1, "mock://?seed=7&faults=offset:" + std::to_string(k), options);
      ASSERT_EQ(r.events.size(), 1U) << "offset:" << k << ", " << sweeps << " sweeps";
      EXPECT_EQ(r.events[0].sensor, k) << sweeps << " sweeps";
      EXPECT_EQ(r.events[0].fault, SensorFault::offset) << "offset:" << k;
    }
  }
}

// Both sensors of the corner cell fail: that cell is read by none, so the bridge releases the
// valves, disables the device and refuses enable.
TEST(SensorFaults, ACellLeftUnreadReleasesTheValves) {
  const model::DeviceProfile profile = model::load_profile("mr-skin-5x5");
  const GridLayout layout(profile.rows, profile.cols);
  const std::vector<std::size_t>& valves = layout.valves_of_cell(0);
  ASSERT_EQ(valves.size(), 2U);
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  OpenedDevice dev = open_device(
      "mock://?seed=7&faults=stuck:" + std::to_string(valves[0]) + ",noisy:" + std::to_string(valves[1]),
      clock, open);
  auto scene = make_scene("demo");
  Bridge loop(*dev.session, *scene);
  scene->set_start(clock.now());
  ASSERT_EQ(loop.enable(), ResultCode::ok);
  std::vector<double> finger(layout.fluid_cell_count());
  std::vector<SensorFaultEvent> events;
  auto tick = [&] {
    mrskin::eval::press_scene_finger(*scene, to_seconds(clock.now() - scene->start()), layout, finger);
    sim::mock_of(dev)->set_finger_indentation(finger);
    sim::mock_of(dev)->step(clock.now());
    (void)loop.step(clock.now());
    clock.advance(std::chrono::milliseconds(1));
    SensorFaultEvent e;
    while (loop.take_sensor_fault(e)) {
      events.push_back(e);
    }
  };
  for (int k = 0; k < 300; ++k) {
    tick();
  }
  ASSERT_EQ(events.size(), 2U);
  EXPECT_EQ(events[0].unobservable_cell, SensorFaultMonitor::npos);
  EXPECT_EQ(events[1].unobservable_cell, 0U);
  EXPECT_LE(events[1].at_s, 0.2);
  EXPECT_TRUE(loop.halted());
  EXPECT_EQ(loop.stats().sensor_fault_halts, 1U);
  EXPECT_EQ(dev.session->state(), DeviceState::disabled);
  loop.request(Bridge::Request::enable);
  for (int k = 0; k < 100; ++k) {
    tick();
  }
  EXPECT_TRUE(loop.halted()) << "enable must not bring back a cell no sensor reads";
  std::vector<double> applied(layout.valve_count());
  sim::mock_of(dev)->applied_currents(applied);
  for (const double a : applied) {
    EXPECT_EQ(a, 0.0);
  }
}

// Readings from before a gap are no history: a halt of 2 s while the finger moves on, then
// enable, once raised four "noisy" sensors and released the valves (mrskinctl's e-stop test).
TEST(SensorFaults, AHaltOrALinkGapIsNoFault) {
  struct Gap {
    const char* uri;
    int halt_ms;  // -1: no halt
    int enable_ms;
  };
  // Halted in the middle of the first press, enabled in a later one or at rest; a link gap of
  // 0.3 s in the middle of a press.
  for (const Gap g :
       {Gap{"mock://?seed=7", 550, 1500}, Gap{"mock://?seed=7", 550, 2500}, Gap{"mock://?seed=7", 1200, 1900},
        Gap{"mock://?seed=7&faults=disconnect:0.55+0.3", -1, -1}}) {
    const char* uri = g.uri;
    SimulatedClock clock;
    OpenOptions open;
    open.synchronous_mock = true;
    OpenedDevice dev = open_device(uri, clock, open);
    auto scene = make_scene("demo");
    Bridge loop(*dev.session, *scene);
    scene->set_start(clock.now());
    ASSERT_EQ(loop.enable(), ResultCode::ok);
    std::vector<double> finger(sim::mock_of(dev)->layout().fluid_cell_count());
    for (int k = 0; k < 5000; ++k) {
      if (k == g.halt_ms) {
        loop.request(Bridge::Request::estop);
      } else if (k == g.enable_ms) {
        loop.request(Bridge::Request::enable);
      }
      mrskin::eval::press_scene_finger(*scene, to_seconds(clock.now() - scene->start()),
                                       sim::mock_of(dev)->layout(), finger);
      sim::mock_of(dev)->set_finger_indentation(finger);
      sim::mock_of(dev)->step(clock.now());
      (void)loop.step(clock.now());
      clock.advance(std::chrono::milliseconds(1));
    }
    EXPECT_EQ(loop.stats().sensor_faults, 0U)
        << uri << " halted " << g.halt_ms << "-" << g.enable_ms << " ms";
    EXPECT_FALSE(loop.halted()) << uri;
  }
}

// A host that wakes late reads the newest of several readings: the readings the monitor sees are
// unevenly spaced, and a second difference that takes them as even reads a moving finger as
// noise (two mrskin-bridged daemons and a DDS peer on 2 cores skipped 15-60 % of their periods
// and one flagged 4 sensors noisy and halted). Spaced by the unit's clock, no false alarm.
TEST(SensorFaults, AHostThatWakesLateRaisesNoFalseAlarm) {
  for (const std::string_view name : scene_names()) {
    const FaultRun r = run(std::string(name), kFull ? 6.0 : 2.0, "mock://?seed=7", {}, 0.5);
    EXPECT_EQ(r.stats.sensor_faults, 0U) << name;
    EXPECT_FALSE(r.halted) << name;
    // On time the largest is 4.7 (NoFalseAlarmOnTheScenes); spaced as even it was 9.5-27.4 here.
    EXPECT_LT(r.max_noise_ratio, 8.0) << name;
    for (const SensorFaultEvent& e : r.events) {
      ADD_FAILURE() << name << ": sensor " << e.sensor << " " << to_string(e.fault) << " at " << e.at_s
                    << " s";
    }
    std::printf("%-8s late on half the periods: %llu ticks, max noise ratio %.2f\n",
                std::string(name).c_str(), static_cast<unsigned long long>(r.stats.ticks), r.max_noise_ratio);
  }  // A noisy sensor is still found, within 200 ms of the unit's time.
  const FaultRun noisy = run("demo", 1.0, "mock://?seed=7&faults=noisy:4", {}, 0.5);
  ASSERT_EQ(noisy.events.size(), 1U);
  EXPECT_EQ(noisy.events[0].sensor, 4U);
  EXPECT_EQ(noisy.events[0].fault, SensorFault::noisy);
  EXPECT_LE(noisy.events[0].at_s, 0.2);
}

// No false alarm: every built-in scene over seeds 1-8 (sanitizer builds: seed 7, 2 s).
TEST(SensorFaults, NoFalseAlarmOnTheScenes) {
  for (const std::string_view name : scene_names()) {
    double noise = 0.0;
    double residual = 0.0;
    for (int seed = kFull ? 1 : 7; seed <= (kFull ? 8 : 7); ++seed) {
      const FaultRun r = run(std::string(name), kFull ? 6.0 : 2.0, "mock://?seed=" + std::to_string(seed));
      EXPECT_EQ(r.stats.sensor_faults, 0U) << name << " seed " << seed;
      for (const SensorFaultEvent& e : r.events) {
        ADD_FAILURE() << name << " seed " << seed << ": sensor " << e.sensor << " " << to_string(e.fault)
                      << " at " << e.at_s << " s";
      }
      noise = std::max(noise, r.max_noise_ratio);
      residual = std::max(residual, r.max_mean_residual);
    }
    // The margins: the noise ratio's limit is 25, the offset's 15 sigmas.
    std::printf("%-8s max noise ratio %.2f  max |mean residual| %.2f sigma\n", std::string(name).c_str(),
                noise, residual);
  }
}

// Classic CAN's unit declares a 2-count sensor deadband (protocol 1.2): its held readings raise no
// false alarm on the scenes. A stuck sensor is found once the finger moves its cells, within its
// run of the residual leaving the band: sensor 3 (under the demo's press) within 200 ms. At rest
// it cannot be told from a healthy one, and reads right within the band: sensor 11, whose cells
// only `tumour` presses, is found there, and on the demo is never found and does no harm.
TEST(SensorFaults, BehindAClassicCanDeadbandNoFalseAlarmAndAStuckSensorIsFoundOncePressed) {
  for (const std::string_view name : scene_names()) {
    const FaultRun r = run(std::string(name), kFull ? 6.0 : 2.0, "mock://?seed=7&bus=can");
    EXPECT_EQ(r.stats.sensor_faults, 0U) << name;
    for (const SensorFaultEvent& e : r.events) {
      ADD_FAILURE() << name << ": sensor " << e.sensor << " " << to_string(e.fault) << " at " << e.at_s
                    << " s";
    }
  }
  const FaultRun pressed = run("demo", 1.0, "mock://?seed=7&bus=can&faults=stuck:3");
  ASSERT_EQ(pressed.events.size(), 1U);
  EXPECT_EQ(pressed.events[0].sensor, 3U);
  EXPECT_EQ(pressed.events[0].fault, SensorFault::stuck);
  EXPECT_LE(pressed.events[0].at_s, 0.2);
  EXPECT_FALSE(pressed.halted);
  const FaultRun at_rest = run("demo", 4.0, "mock://?seed=7&bus=can&faults=stuck:11");
  EXPECT_TRUE(at_rest.events.empty());
  EXPECT_LE(at_rest.stats.force_rms_error_N(), 0.04);
  EXPECT_LE(at_rest.stats.true_state_rms_error_N(), 0.04);
  const FaultRun tumour = run("tumour", 3.5, "mock://?seed=7&bus=can&faults=stuck:11");
  ASSERT_EQ(tumour.events.size(), 1U);
  EXPECT_EQ(tumour.events[0].sensor, 11U);
  EXPECT_EQ(tumour.events[0].fault, SensorFault::stuck);
  std::printf(
      "stuck:3 on the demo found at %.3f s; stuck:11 on tumour at %.3f s; on the demo unfound, "
      "rms %.4f N (true state %.4f N)\n",
      pressed.events[0].at_s, tumour.events[0].at_s, at_rest.stats.force_rms_error_N(),
      at_rest.stats.true_state_rms_error_N());
}

// The leak is not seen (docs/reliability.md): the pads follow the finger whatever the valves
// hold, so the displacement readings do not change. Kept so that a detector that claims it
// (or a false alarm it causes) shows here.
TEST(SensorFaults, ALeakIsNotASensorFault) {
  const FaultRun r = run("demo", kFull ? 3.0 : 1.0, "mock://?seed=7&faults=leak:5");
  EXPECT_EQ(r.stats.sensor_faults, 0U);
  std::printf("leak:5  rms %.4f N, no sensor fault (the leak is not observable from displacement)\n",
              r.stats.force_rms_error_N());
}

// MRSKIN_SENSOR_FAULT_TICKS=1000000: that many fault-free closed-loop ticks, the scenes in turn
// (docs/reliability.md; not in CI: about two minutes).
TEST(SensorFaults, FaultFreeTicksRaiseNothing) {
  const char* env = std::getenv("MRSKIN_SENSOR_FAULT_TICKS");
  if (env == nullptr) {
    GTEST_SKIP() << "set MRSKIN_SENSOR_FAULT_TICKS";
  }
  const double ticks = std::strtod(env, nullptr);
  double done = 0.0;
  int seed = 1;
  while (done < ticks) {
    for (const std::string_view name : scene_names()) {
      const FaultRun r = run(std::string(name), 10.0, "mock://?seed=" + std::to_string(seed));
      EXPECT_EQ(r.stats.sensor_faults, 0U) << name << " seed " << seed;
      done += static_cast<double>(r.stats.ticks);
    }
    ++seed;
  }
  std::printf("%.0f fault-free closed-loop ticks (seeds 1-%d): no sensor fault\n", done, seed - 1);
}

}  // namespace
}  // namespace mrskin::bridge
