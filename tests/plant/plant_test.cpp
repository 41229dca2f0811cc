// The perturbed network plant under the mock device: spread, delay, sensors, allocation.
#include <gtest/gtest.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <limits>
#include <span>
#include <vector>

#include "counting_new.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/model/device_model.hpp"
#include "mrskin/driver/model/profile.hpp"
#include "mrskin/sim/network_plant.hpp"

namespace {

using mrskin::model::DeviceProfile;
using mrskin::sim::NetworkPlant;
using mrskin::sim::NetworkPlantOptions;

TEST(PlantPerturbation, WithinSpreadAndRepeatablePerSeed) {
  const DeviceProfile nominal = mrskin::model::default_profile();
  const DeviceProfile a = mrskin::sim::perturbed_profile(nominal, 0.15, 7);
  const DeviceProfile b = mrskin::sim::perturbed_profile(nominal, 0.15, 7);
  const DeviceProfile c = mrskin::sim::perturbed_profile(nominal, 0.15, 8);
  EXPECT_EQ(a.fluid.viscosity_Pa_s, b.fluid.viscosity_Pa_s);
  EXPECT_NE(a.fluid.viscosity_Pa_s, c.fluid.viscosity_Pa_s);
  const auto within = [](double x, double x0, double w) { return std::abs(x / x0 - 1.0) <= w + 1e-12; };
  for (const DeviceProfile* p : {&a, &c}) {
    EXPECT_TRUE(within(p->fluid.viscosity_Pa_s, nominal.fluid.viscosity_Pa_s, 0.15));
    EXPECT_TRUE(within(p->fluid.carrier_factor, nominal.fluid.carrier_factor, 0.15));
    EXPECT_TRUE(within(p->membrane.youngs_modulus_Pa, nominal.membrane.youngs_modulus_Pa, 0.15));
    EXPECT_TRUE(within(p->valve.gap_m, nominal.valve.gap_m, 0.03));
    EXPECT_EQ(p->magnetic.fluid_gap_m, p->valve.gap_m);
  }
  EXPECT_THROW((void)mrskin::sim::perturbed_profile(nominal, 0.7, 1), mrskin::InvalidArgument);
}

TEST(PlantSensors, TwelveDisplacementSensorsQuantisedToTheirResolution) {
  const DeviceProfile nominal = mrskin::model::default_profile();
  NetworkPlant plant(nominal, NetworkPlantOptions{});
  ASSERT_EQ(plant.sensor_count(), 12U);
  std::vector<double> depth(13, 0.0);
  depth[6] = 2e-3;  // centre cell
  plant.set_finger_indentation(depth);
  for (int i = 0; i < 20; ++i) {
    plant.step(1e-4);
  }
  std::vector<double> y(plant.sensor_count());
  plant.read_sensors(y);
  const double res = nominal.sensors[0].resolution;
  double sum = 0.0;
  for (const double v : y) {
    EXPECT_NEAR(v / res, std::round(v / res), 1e-6);
    sum += v;
  }
  // The four valves around the centre read a quarter of its depth each (plus noise).
  EXPECT_NEAR(sum, 4.0 * 2e-3 / 4.0, 8 * 4 * nominal.sensors[0].noise_std + 12 * res);
  EXPECT_EQ(plant.failed_steps(), 0U);
}

TEST(PlantCommands, CurrentsReachTheCoilsOnlyAfterTheBusDelay) {
  NetworkPlantOptions o;
  o.command_delay_s = 1.5e-3;
  NetworkPlant plant(mrskin::model::default_profile(), o);
  std::vector<double> current(12, 0.05);
  plant.set_valve_currents(current);
  for (int i = 0; i < 14; ++i) {  // 1.4 ms
    plant.step(1e-4);
  }
  for (const double i : plant.coil_current_A()) {
    EXPECT_EQ(i, 0.0);
  }
  for (int i = 0; i < 30; ++i) {
    plant.step(1e-4);
  }
  for (const double i : plant.coil_current_A()) {
    EXPECT_GT(i, 0.0);
  }
  for (const double tau : plant.valve_yield_stress_Pa()) {
    EXPECT_GT(tau, 0.0);
  }
}

TEST(PlantCommands, BadCommandsAreClampedOrIgnored) {
  NetworkPlantOptions o;
  o.command_delay_s = 0.0;
  NetworkPlant plant(mrskin::model::default_profile(), o);
  std::vector<double> current(12, 5.0);  // above the coil's limit
  current[0] = std::nan("");
  plant.set_valve_currents(current);
  std::vector<double> wrong(3, 0.01);
  plant.set_valve_currents(wrong);  // wrong size: ignored
  for (int i = 0; i < 200; ++i) {
    plant.step(1e-4);
  }
  const double max_A = mrskin::model::default_profile().coil.max_current_A;
  EXPECT_EQ(plant.coil_current_A()[0], 0.0);
  for (std::size_t v = 1; v < 12; ++v) {
    EXPECT_LE(plant.coil_current_A()[v], max_A * (1 + 1e-9));
    EXPECT_GT(plant.coil_current_A()[v], 0.5 * max_A);
  }
  EXPECT_EQ(plant.failed_steps(), 0U);
}

// The steel's play keeps a remanent yield at 0 A after the maximum current. On/off steps (a
// unipolar driver) cannot lower it; a decaying alternating current (a bipolar driver's degauss,
// MockDevice's StateRequest degauss) walks the play back towards zero.
TEST(PlantHysteresis, AnAlternatingDecayDegaussesTheCores) {
  NetworkPlantOptions o;
  o.command_delay_s = 0.0;
  const double max_A = mrskin::model::default_profile().coil.max_current_A;
  const auto remanent_Pa = [&](bool alternating) {
    NetworkPlant plant(mrskin::model::default_profile(), o);
    std::vector<double> current(12, max_A);
    const auto hold = [&](double a, int steps = 200) {  // 20 ms: about four coil time constants
      std::fill(current.begin(), current.end(), a);
      plant.set_valve_currents(current);
      for (int i = 0; i < steps; ++i) {
        plant.step(1e-4);
      }
    };
    hold(max_A);
    hold(0.0, 2000);  // settled: no current left in the coil
    const double after_max_Pa = plant.valve_yield_stress_Pa()[0];
    double sign = 1.0;
    for (double a = max_A; a > 1e-3 * max_A; a *= 0.85) {
      hold(sign * a);
      if (alternating) {
        sign = -sign;
      } else {
        hold(0.0);
      }
    }
    hold(0.0, 2000);
    EXPECT_EQ(plant.failed_steps(), 0U);
    return std::pair{after_max_Pa, plant.valve_yield_stress_Pa()[0]};
  };
  const auto [after_max_Pa, unipolar_Pa] = remanent_Pa(false);
  EXPECT_GT(after_max_Pa, 0.1);  // the remanence is there to remove (~1 Pa on the 5 x 5)
  EXPECT_NEAR(unipolar_Pa, after_max_Pa, 0.05 * after_max_Pa);
  const auto [again_Pa, degaussed_Pa] = remanent_Pa(true);
  std::printf(
      "remanent yield at 0 A: %.3f Pa after the maximum, %.3f Pa after on/off steps, %.3f Pa after "
      "an alternating decay\n",
      after_max_Pa, unipolar_Pa, degaussed_Pa);
  EXPECT_EQ(again_Pa, after_max_Pa);
  EXPECT_LT(degaussed_Pa, 0.2 * after_max_Pa);
}

// A valve whose coil has settled keeps its yield without solving its magnetic circuit again, and
// the plant is the same to the last bit as one that solves every valve every substep: currents
// ramped, held, stepped down, reversed (the hysteresis' play moves) and held again, under a press.
TEST(PlantSettledFields, ReusedFieldsGiveTheSameBitsAsSolvingEverySubstep) {
  const DeviceProfile nominal = mrskin::model::default_profile();
  NetworkPlantOptions o;
  o.seed = 3;
  NetworkPlant reusing(nominal, o);
  o.reuse_settled_fields = false;
  NetworkPlant solving(nominal, o);
  const std::size_t valves = reusing.valve_yield_stress_Pa().size();
  const double max_A = nominal.coil.max_current_A;
  std::vector<double> depth(13, 0.0);
  std::vector<double> current(valves, 0.0);
  std::vector<double> y_reusing(reusing.sensor_count());
  std::vector<double> y_solving(solving.sensor_count());
  std::vector<double> f_reusing(13);
  std::vector<double> f_solving(13);
  std::size_t mismatches = 0;
  const auto run = [&](int steps) {
    for (int i = 0; i < steps; ++i) {
      depth[6] = std::min(1.5e-3, depth[6] + 1e-6);
      for (NetworkPlant* p : {&reusing, &solving}) {
        p->set_finger_indentation(depth);
        p->set_valve_currents(current);
        p->step(1e-4);
      }
      reusing.read_sensors(y_reusing);
      solving.read_sensors(y_solving);
      reusing.contact_forces(f_reusing);
      solving.contact_forces(f_solving);
      const auto same = [](std::span<const double> a, std::span<const double> b) {
        return std::equal(a.begin(), a.end(), b.begin(), b.end(), [](double x, double z) {
          return std::bit_cast<std::uint64_t>(x) == std::bit_cast<std::uint64_t>(z);
        });
      };
      mismatches += same(reusing.valve_yield_stress_Pa(), solving.valve_yield_stress_Pa()) ? 0 : 1;
      mismatches += same(y_reusing, y_solving) && same(f_reusing, f_solving) ? 0 : 1;
    }
  };
  for (std::size_t v = 0; v < valves; ++v) {
    current[v] = max_A * static_cast<double>(v + 1) / static_cast<double>(valves);
  }
  run(3000);  // 0.3 s: every coil settles (coil and eddy constants of a few ms)
  const std::uint64_t settled_solves = reusing.gap_field_solves();
  run(1000);  // held: nothing to solve
  EXPECT_EQ(reusing.gap_field_solves(), settled_solves);
  current[0] = 0.5 * current[0];
  current[1] = -0.5 * max_A;  // a degauss's reversal: the play moves
  run(2000);
  run(2000);
  EXPECT_EQ(mismatches, 0U);
  EXPECT_EQ(solving.gap_field_solves(), 8000U * valves);
  std::printf("gap-field solves over 8,000 substeps of %zu valves: %llu reusing, %llu solving\n", valves,
              static_cast<unsigned long long>(reusing.gap_field_solves()),
              static_cast<unsigned long long>(solving.gap_field_solves()));
  EXPECT_LT(reusing.gap_field_solves(), solving.gap_field_solves() / 4);
  EXPECT_EQ(reusing.failed_steps(), 0U);
}

// The exact plant, one cell of a profile pressed at a constant rate with its valves at a quarter
// of the highest current: the cell's force at the end of every millisecond, the finger's depth
// set once a millisecond (as the mock sets it once a tick).
std::vector<double> press_one_cell(const DeviceProfile& profile, NetworkPlantOptions o, int substeps_per_ms,
                                   std::size_t cell, double rate_m_per_s, int ms) {
  o.perturbation = 0.0;
  o.sensor_noise_scale = 0.0;
  o.hysteresis_scale = 0.0;
  o.command_delay_s = 0.0;
  o.substep_s = 1e-3 / substeps_per_ms;
  NetworkPlant plant(profile, o);
  const mrskin::model::DeviceModel model(profile);
  const std::size_t cells = model.layout().fluid_cell_count();
  std::vector<double> current(model.layout().valve_count(), 0.0);
  for (const std::size_t v : model.layout().valves_of_cell(cell)) {
    current[v] = 0.25 * profile.coil.max_current_A;
  }
  plant.set_valve_currents(current);
  std::vector<double> depth(cells, 0.0);
  std::vector<double> force(cells, 0.0);
  std::vector<double> out;
  for (int k = 1; k <= ms; ++k) {
    depth[cell] = rate_m_per_s * k * 1e-3;
    plant.set_finger_indentation(depth);
    for (int s = 0; s < substeps_per_ms; ++s) {
      plant.step(o.substep_s);
    }
    plant.contact_forces(force);
    out.push_back(force[cell]);
  }
  EXPECT_EQ(plant.failed_steps(), 0U);
  return out;
}

// The discrete gradient is not L-stable: on fingertip-16x16, whose cells empty through an open
// passage in 3.5 us, a 0.1 ms substep rang at its Nyquist rate (a neighbour's pressure +3307,
// -2835, +2939 ... Pa, substep to substep) and left the pressed cell in a spurious locked state at
// under half its force. automatic integrates such a unit by backward Euler, which at 0.1 ms keeps
// to a 1 us discrete-gradient reference; the default 5x5 (1.7 s) keeps the discrete gradient.
TEST(PlantIntegration, AStiffUnitsPressedCellKeepsToAFineStepsForce) {
  const DeviceProfile fingertip = mrskin::model::load_profile("fingertip-16x16");
  EXPECT_LT(mrskin::model::DeviceModel(fingertip).cell_open_drain_time_s(), 1e-5);
  EXPECT_GT(mrskin::model::DeviceModel(mrskin::model::default_profile()).cell_open_drain_time_s(), 1.0);
  EXPECT_TRUE(NetworkPlant(fingertip, NetworkPlantOptions{}).network().options().backward_euler);
  EXPECT_FALSE(NetworkPlant(mrskin::model::default_profile(), NetworkPlantOptions{})
                   .network()
                   .options()
                   .backward_euler);

  constexpr std::size_t kCell = 59;  // the demo's deepest
  constexpr double kRate_m_per_s = 0.2e-3;
  constexpr int kMs = 60;
  NetworkPlantOptions discrete_gradient;
  discrete_gradient.integration = NetworkPlantOptions::Integration::discrete_gradient;
  const std::vector<double> reference =
      press_one_cell(fingertip, discrete_gradient, 1000, kCell, kRate_m_per_s, kMs);
  const std::vector<double> automatic =
      press_one_cell(fingertip, NetworkPlantOptions{}, 10, kCell, kRate_m_per_s, kMs);
  const std::vector<double> ringing =
      press_one_cell(fingertip, discrete_gradient, 10, kCell, kRate_m_per_s, kMs);
  double worst_automatic = 0.0;
  double worst_ringing = 0.0;
  for (int k = 10; k < kMs; ++k) {
    worst_automatic = std::max(worst_automatic, std::fabs(automatic[k] / reference[k] - 1.0));
    worst_ringing = std::max(worst_ringing, std::fabs(ringing[k] / reference[k] - 1.0));
  }
  std::printf(
      "fingertip cell %zu pressed at %.1f mm/s, force at %d ms: %.3f mN (1 us reference), %.3f mN "
      "(0.1 ms automatic), %.3f mN (0.1 ms discrete gradient); worst after 10 ms %.2f %% and %.1f %%\n",
      kCell, kRate_m_per_s * 1e3, kMs, 1e3 * reference.back(), 1e3 * automatic.back(), 1e3 * ringing.back(),
      100 * worst_automatic, 100 * worst_ringing);
  EXPECT_LT(worst_automatic, 0.02);
  EXPECT_GT(worst_ringing, 0.3);  // what automatic avoids
}

TEST(PlantIntegration, ASubstepThatIsNotPositiveAndFiniteIsRefused) {
  for (const double substep_s :
       {0.0, -1e-4, std::numeric_limits<double>::quiet_NaN(), std::numeric_limits<double>::infinity()}) {
    NetworkPlantOptions o;
    o.substep_s = substep_s;
    EXPECT_THROW(NetworkPlant(mrskin::model::default_profile(), o), mrskin::InvalidArgument) << substep_s;
  }
}

TEST(PlantHotPath, SteppingDoesNotAllocate) {
  NetworkPlant plant(mrskin::model::default_profile(), NetworkPlantOptions{});
  std::vector<double> depth(13, 0.0);
  std::vector<double> current(12, 0.02);
  std::vector<double> y(plant.sensor_count());
  std::vector<double> f(13);
  plant.step(1e-4);
  const auto before = mrskin::test::allocation_count();
  for (int i = 0; i < 500; ++i) {
    depth[6] = 4e-3 * std::sin(i * 0.01);
    plant.set_finger_indentation(depth);
    plant.set_valve_currents(current);
    plant.step(1e-4);
    plant.read_sensors(y);
    plant.contact_forces(f);
  }
  EXPECT_EQ(mrskin::test::allocation_count(), before);
}

}  // namespace
