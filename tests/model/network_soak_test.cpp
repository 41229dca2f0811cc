// Soak (label `soak`, outside the default and CI runs: `ctest --preset soak`): 10^7 steps of
// periodic press/hold/release per stepper, without NaN, with volume and energy kept, and on a
// periodic orbit that does not drift (each cycle's peak force equal to the last one's).
#include <gtest/gtest.h>

#include <cstdio>

#include "network_scenarios.hpp"

namespace {

using namespace mrskin::model;

TEST(ModelNetworkSoak, TenMillionStepsWithoutDriftNorNaN) {
  constexpr long kSteps = 10'000'000;
  for (const Stepper s : {Stepper::implicit_exact, Stepper::linearly_implicit_regularised}) {
    NetworkOptions o;
    o.stepper = s;
    NetworkSimulation sim(nettest::model_of("mr-skin-5x5"), o);
    const nettest::SoakResult r = nettest::run_soak(sim, kSteps, 1e-3);
    std::printf("%-30s %ld steps: volume %.2e, energy gap %.2e, late peak change %.2e N (peak %.4f N)\n",
                to_string(s), r.steps_done, r.invariants.worst_volume_rel, r.invariants.worst_energy_rel,
                r.late_peak_change_N, r.last_peak_N);
    EXPECT_EQ(r.failure, Status::ok) << to_string(r.failure);
    EXPECT_EQ(r.steps_done, kSteps);
    EXPECT_LE(r.invariants.worst_volume_rel, 1e-12);
    if (s == Stepper::implicit_exact) {
      EXPECT_LE(r.invariants.worst_energy_rel, 1e-6);
    }
    EXPECT_LE(r.late_peak_change_N, 1e-6);
    EXPECT_LT(r.max_abs_pressure_Pa, 1e5);
  }
}

}  // namespace
