// Stress: 10^6 randomised steps inside the operating envelope (10^5 in unoptimised, sanitised
// builds), 10^5 random invalid inputs, and the short version of the soak (10^5 steps).
// Fixed seeds: a failure names the case and reproduces.
#include <gtest/gtest.h>

#include <array>
#include <cmath>
#include <cstdio>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "network_scenarios.hpp"

namespace {

using namespace mrskin::model;
using nettest::design_cell;
using nettest::Invariants;
using nettest::max_yield_Pa;
using nettest::model_of;

#if defined(NDEBUG) && !defined(MRSKIN_SANITIZED)
constexpr long kCases = 1'000'000;
#else
constexpr long kCases = 100'000;  // Debug or sanitizers in CI: the same cases, fewer of them
#endif

bool finite_all(std::span<const double> v) {
  for (const double x : v) {
    if (!std::isfinite(x)) {
      return false;
    }
  }
  return true;
}

// Every case: one of the implicit steppers (now and then back at rest), random yield stress on
// every valve in [0, yield at max current], a random press (per-cell depths in [0, 5 mm], or
// 1-3 spherical fingers by indentation, or now and then one finger by force up to 2 N), and a
// random dt in [1e-4, 2e-3] s. Each step must succeed and keep the invariants.
TEST(ModelNetworkStress, RandomisedStepsInsideTheEnvelopeAllSucceed) {
  const DeviceModel& m = model_of("mr-skin-5x5");
  const std::array<Stepper, 3> steppers = {Stepper::implicit_exact, Stepper::implicit_regularised,
                                           Stepper::linearly_implicit_regularised};
  std::vector<std::unique_ptr<NetworkSimulation>> sims;
  std::vector<Invariants> inv;
  for (const Stepper s : steppers) {
    NetworkOptions o;
    o.stepper = s;
    sims.push_back(std::make_unique<NetworkSimulation>(m, o));
    inv.emplace_back(*sims.back());
  }
  std::mt19937_64 rng(20240605);
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  const double tau_max = max_yield_Pa(m);
  const double depth_max = 5e-3;
  const double extent = (m.profile().cols - 1) * m.profile().cell_pitch_m;
  std::vector<double> yield(m.layout().valve_count());
  std::vector<double> depth(m.layout().fluid_cell_count());
  long failures = 0;
  long force_cases = 0;
  long iterations = 0;
  int max_iterations = 0;
  for (long k = 0; k < kCases; ++k) {
    const std::size_t which = static_cast<std::size_t>(u01(rng) * 3.0) % 3;
    NetworkSimulation& sim = *sims[which];
    if (u01(rng) < 0.002) {
      sim.reset();
      inv[which] = Invariants(sim);
    }
    for (double& y : yield) {
      y = tau_max * u01(rng);
    }
    ASSERT_EQ(sim.set_valve_yield_stress_Pa(yield), Status::ok);
    const double mode = u01(rng);
    if (mode < 0.8) {
      for (double& x : depth) {
        x = u01(rng) < 0.5 ? 0.0 : depth_max * u01(rng);
      }
      ASSERT_EQ(sim.set_cell_indentation_m(depth), Status::ok);
    } else {
      std::array<Contact, 3> cs{};
      const std::size_t n = mode < 0.99 ? 1 + static_cast<std::size_t>(u01(rng) * 3.0) % 3 : 1;
      for (std::size_t i = 0; i < n; ++i) {
        cs[i].x_m = extent * u01(rng);
        cs[i].y_m = extent * u01(rng);
        cs[i].radius_m = 5e-3 + 45e-3 * u01(rng);
        cs[i].indentation_m = -1e-3 + 6e-3 * u01(rng);
        if (mode >= 0.99) {
          cs[i].mode = Contact::Mode::force;
          cs[i].force_N = 2.0 * u01(rng);
          cs[i].x_m = m.profile().cell_pitch_m * std::round(cs[i].x_m / m.profile().cell_pitch_m);
          ++force_cases;
        }
      }
      ASSERT_EQ(sim.set_contacts(std::span<const Contact>(cs).first(n)), Status::ok);
    }
    const double dt = 1e-4 + 1.9e-3 * u01(rng);
    const Result<StepReport> r = sim.step(dt);
    if (!r.ok()) {
      if (++failures <= 5) {
        ADD_FAILURE() << "case " << k << " (" << to_string(steppers[which]) << ", dt " << dt
                      << "): " << to_string(r.status);
      }
      continue;
    }
    iterations += r.value.iterations;
    max_iterations = std::max(max_iterations, r.value.iterations);
    inv[which].check(sim);
    if (!finite_all(sim.cell_force_N()) || !finite_all(sim.cell_pressure_Pa()) ||
        !finite_all(sim.chamber_pressure_Pa()) || !finite_all(sim.cell_indentation_m())) {
      ADD_FAILURE() << "case " << k << ": non-finite state";
      ++failures;
    }
    for (const double f : sim.cell_force_N()) {
      if (f < 0.0) {
        ADD_FAILURE() << "case " << k << ": negative contact force";
        ++failures;
      }
    }
  }
  std::printf("%ld cases (%ld with a force-mode finger): %ld failures, Newton iterations mean %.2f max %d\n",
              kCases, force_cases, failures, static_cast<double>(iterations) / static_cast<double>(kCases),
              max_iterations);
  for (std::size_t s = 0; s < steppers.size(); ++s) {
    std::printf("  %-30s worst volume %.2e, worst energy gap %.2e\n", to_string(steppers[s]),
                inv[s].worst_volume_rel, inv[s].worst_energy_rel);
    EXPECT_LE(inv[s].worst_volume_rel, 1e-12);
  }
  EXPECT_EQ(failures, 0);
  EXPECT_LE(inv[0].worst_energy_rel, 1e-6);  // the discrete-gradient steppers
  EXPECT_LE(inv[1].worst_energy_rel, 1e-6);
}

// Random invalid inputs: every one is refused with its status and changes nothing.
TEST(ModelNetworkStress, RandomInvalidInputsAreRefusedExplicitly) {
  const DeviceModel& m = model_of("mr-skin-5x5");
  NetworkSimulation sim(m, NetworkOptions{});
  std::vector<double> depth(sim.fluid_cell_count(), 1e-3);
  ASSERT_EQ(sim.set_cell_indentation_m(depth), Status::ok);
  ASSERT_TRUE(sim.step(1e-3).ok());
  const double work = sim.energy().work_J;
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  const std::array<double, 5> bad = {std::nan(""), HUGE_VAL, -HUGE_VAL, -1e-9, -1e300};
  const std::array<Status, 5> bad_status = {Status::not_finite, Status::not_finite, Status::not_finite,
                                            Status::negative, Status::negative};
  std::vector<double> yield(sim.valve_count(), 10.0);
  for (int k = 0; k < 100'000; ++k) {
    const std::size_t b = static_cast<std::size_t>(u01(rng) * 5.0) % 5;
    switch (k % 4) {
      case 0: {
        std::vector<double>& v = yield;
        std::fill(v.begin(), v.end(), 10.0);
        v[static_cast<std::size_t>(u01(rng) * static_cast<double>(v.size())) % v.size()] = bad[b];
        ASSERT_EQ(sim.set_valve_yield_stress_Pa(v), bad_status[b]) << k;
        break;
      }
      case 1: {
        std::fill(depth.begin(), depth.end(), 1e-3);
        depth[static_cast<std::size_t>(u01(rng) * static_cast<double>(depth.size())) % depth.size()] = bad[b];
        ASSERT_EQ(sim.set_cell_indentation_m(depth), bad_status[b]) << k;
        break;
      }
      case 2: {
        Contact c;
        c.radius_m = 0.01;
        std::array<double*, 5> fields = {&c.x_m, &c.y_m, &c.radius_m, &c.indentation_m, &c.force_N};
        const std::size_t f = static_cast<std::size_t>(u01(rng) * 5.0) % 5;
        *fields[f] = bad[b];
        Status expect = bad_status[b];
        if (expect == Status::negative && (f == 0 || f == 1 || f == 3)) {
          expect = Status::ok;  // positions anywhere, a finger above the skin: valid
        }
        ASSERT_EQ(sim.set_contacts(std::span<const Contact>(&c, 1)), expect) << k << " field " << f;
        std::fill(depth.begin(), depth.end(), 1e-3);
        ASSERT_EQ(sim.set_cell_indentation_m(depth), Status::ok);
        break;
      }
      default: {
        const double dt = b < 3 ? bad[b] : -u01(rng);
        ASSERT_EQ(sim.step(dt).status, b < 3 ? Status::not_finite : Status::out_of_range) << k;
        break;
      }
    }
  }
  EXPECT_EQ(sim.energy().work_J, work);
  std::fill(depth.begin(), depth.end(), 1e-3);
  ASSERT_EQ(sim.set_cell_indentation_m(depth), Status::ok);
  EXPECT_TRUE(sim.step(1e-3).ok());
}

// The soak's short version (the long one is the `soak`-labelled mrskin_model_network_soak).
TEST(ModelNetworkStress, ShortSoakHasNoDriftNorNaN) {
  for (const Stepper s : {Stepper::implicit_exact, Stepper::linearly_implicit_regularised}) {
    NetworkOptions o;
    o.stepper = s;
    NetworkSimulation sim(model_of("mr-skin-5x5"), o);
    const nettest::SoakResult r = nettest::run_soak(sim, 100'000, 1e-3);
    std::printf("%-30s %ld steps: volume %.2e, energy gap %.2e, late peak change %.2e N (peak %.4f N)\n",
                to_string(s), r.steps_done, r.invariants.worst_volume_rel, r.invariants.worst_energy_rel,
                r.late_peak_change_N, r.last_peak_N);
    EXPECT_EQ(r.failure, Status::ok) << to_string(r.failure);
    EXPECT_EQ(r.steps_done, 100'000);
    EXPECT_LE(r.invariants.worst_volume_rel, 1e-12);
    if (s == Stepper::implicit_exact) {
      EXPECT_LE(r.invariants.worst_energy_rel, 1e-6);
    }
    EXPECT_LE(r.late_peak_change_N, 1e-6);
    EXPECT_LT(r.max_abs_pressure_Pa, 1e5);
  }
}

}  // namespace
