// Carlson fluid fits, the magnetic circuit (saturation, hysteresis) and the coil's dynamics.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <random>

#include "mrskin/driver/model/coil.hpp"
#include "mrskin/driver/model/fluid.hpp"
#include "mrskin/driver/model/magnetic.hpp"

namespace {

using namespace mrskin::model;

TEST(ModelFluid, CarlsonYieldStressAtTheBriefsFields) {
  const FluidParams f;  // MRF-132DG class, phi = 0.32, hydrocarbon
  // The product brief's check values: about 0.3 kPa at 1 kA/m, 3 at 10, 27 at 100, 41 at 200.
  EXPECT_NEAR(yield_stress_Pa(f, 1e3).value, 300.0, 10.0);
  EXPECT_NEAR(yield_stress_Pa(f, 1e4).value, 3000.0, 100.0);
  EXPECT_NEAR(yield_stress_Pa(f, 1e5).value, 27e3, 500.0);
  EXPECT_NEAR(yield_stress_Pa(f, 2e5).value, 41e3, 500.0);
  EXPECT_EQ(yield_stress_Pa(f, 0.0).value, 0.0);
  EXPECT_EQ(yield_stress_Pa(f, -1e4).value, yield_stress_Pa(f, 1e4).value);  // even in H
  EXPECT_NEAR(saturated_yield_stress_Pa(f), 271700.0 * std::pow(0.32, 1.5239), 1e-9);
  // Water carrier: Carlson's C = 1.16 scales the whole curve.
  FluidParams water = f;
  water.carrier_factor = 1.16;
  EXPECT_NEAR(yield_stress_Pa(water, 5e4).value / yield_stress_Pa(f, 5e4).value, 1.16, 1e-12);
}

TEST(ModelFluid, FluxDensityFitLimitsAndInverse) {
  const FluidParams f;
  // Low field: B = mu0 (1 + 1.91 phi^1.133 * 10.97) H.
  const double mu_r0 = 1.0 + 1.91 * std::pow(0.32, 1.133) * 10.97;
  EXPECT_NEAR(fluid_flux_density_T(f, 1e-3).value / (kMu0_H_per_m * 1e-3), mu_r0, 1e-6);
  EXPECT_NEAR(fluid_permeability_H_per_m(f, 0.0) / kMu0_H_per_m, mu_r0, 1e-12);
  // High field: the particles saturate and B - mu0 H -> 1.91 phi^1.133.
  EXPECT_NEAR(fluid_flux_density_T(f, 1e7).value - kMu0_H_per_m * 1e7, 1.91 * std::pow(0.32, 1.133), 1e-9);
  EXPECT_EQ(fluid_flux_density_T(f, -3e4).value, -fluid_flux_density_T(f, 3e4).value);
  for (const double h : {1e-3, 1.0, 300.0, 1e4, 2e5, 1e7}) {
    const double b = fluid_flux_density_T(f, h).value;
    EXPECT_NEAR(fluid_field_for_flux_density_A_per_m(f, b).value / h, 1.0, 1e-12) << h;
  }
  for (const double tau : {1.0, 100.0, 3e4}) {
    const double h = field_for_yield_stress_A_per_m(f, tau).value;
    EXPECT_NEAR(yield_stress_Pa(f, h).value / tau, 1.0, 1e-12);
  }
  EXPECT_EQ(field_for_yield_stress_A_per_m(f, 1e6).status, Status::out_of_range);
  EXPECT_EQ(yield_stress_Pa(f, std::nan("")).status, Status::not_finite);
}

MagneticCircuitParams low_carbon_steel_circuit() {
  MagneticCircuitParams m;
  m.turns = 200;
  m.fluid_gap_m = 0.5e-3;
  m.spacer_gap_m = 0.0;
  m.pole_area_m2 = 7.2e-4;
  m.steel_path_length_m = 0.06;
  m.steel_area_m2 = 1.44e-4;  // the core neck saturates first
  m.steel.saturation_polarization_T = 2.0;
  m.steel.initial_relative_permeability = 2000.0;
  return m;
}

TEST(ModelMagnetic, LinearLimitIsTheReluctanceFormulaNotEq2) {
  const FluidParams f;
  const MagneticCircuitParams m = low_carbon_steel_circuit();
  const double i = 1e-4;  // far below saturation of both fluid and steel
  const GapField g = gap_field(m, f, i).value;
  const double mu_f = fluid_permeability_H_per_m(f, 0.0);
  const double mu_s = kMu0_H_per_m * m.steel.initial_relative_permeability;
  // B_gap = N I / (g / mu_f + l_s A_p / (mu_s A_s)) (flux continuity puts A_p / A_s on the steel).
  const double expected =
      m.turns * i /
      (m.fluid_gap_m / mu_f + m.steel_path_length_m * m.pole_area_m2 / (mu_s * m.steel_area_m2));
  EXPECT_NEAR(g.flux_density_T / expected, 1.0, 1e-4);
  // H in the fluid is N I / g times the gap's share of the reluctance (here the narrow core
  // neck takes two thirds); with an ideal core it is N I / g.
  const double gap_share =
      (m.fluid_gap_m / mu_f) /
      (m.fluid_gap_m / mu_f + m.steel_path_length_m * m.pole_area_m2 / (mu_s * m.steel_area_m2));
  EXPECT_NEAR(g.field_A_per_m / (m.turns * i / m.fluid_gap_m), gap_share, 1e-4);
  MagneticCircuitParams ideal = m;
  ideal.steel_area_m2 = 10 * m.pole_area_m2;
  ideal.steel.initial_relative_permeability = 1e6;
  EXPECT_NEAR(gap_field(ideal, f, i).value.field_A_per_m / (m.turns * i / m.fluid_gap_m), 1.0, 1e-3);
  // The paper's Eq. 2 (mu0 n I per unit length...) has no gap in it at all: it is not this.
  EXPECT_GT(std::fabs(g.flux_density_T - kMu0_H_per_m * m.turns * i) / g.flux_density_T, 0.5);
  // Ampere's law closes: N I = H_f g + H_s l_s.
  EXPECT_NEAR(g.field_A_per_m * m.fluid_gap_m + g.steel_field_A_per_m * m.steel_path_length_m, m.turns * i,
              1e-12 * m.turns * i);
}

TEST(ModelMagnetic, SteelSaturatesAndTheGapFieldStopsFollowingTheCurrent) {
  const FluidParams f;
  const MagneticCircuitParams m = low_carbon_steel_circuit();
  const GapField lo = gap_field(m, f, 0.1).value;
  const GapField hi = gap_field(m, f, 20.0).value;
  EXPECT_LT(lo.steel_polarization_fraction, 0.9);
  EXPECT_GT(hi.steel_polarization_fraction, 0.98);
  EXPECT_LT(hi.steel_flux_density_T, 2.0 + kMu0_H_per_m * hi.steel_field_A_per_m + 1e-9);
  // 200x the current gives far less than 200x the gap flux once the neck saturates.
  EXPECT_LT(hi.flux_density_T / lo.flux_density_T, 20.0);
  // Monotone in current, odd in current.
  double prev = -1.0;
  for (int k = 0; k <= 100; ++k) {
    const double b = gap_field(m, f, 0.2 * k).value.flux_density_T;
    EXPECT_GT(b, prev);
    prev = b;
  }
  EXPECT_NEAR(gap_field(m, f, -3.0).value.flux_density_T, -gap_field(m, f, 3.0).value.flux_density_T, 1e-15);
}

TEST(ModelMagnetic, HysteresisLeavesARemanentFieldAndIsOptional) {
  const FluidParams f;
  MagneticCircuitParams m = low_carbon_steel_circuit();
  m.steel.coercivity_A_per_m = 100.0;  // low-carbon steel
  HysteresisState s;
  const GapField up = gap_field_hysteretic(m, f, 2.0, s).value;
  const GapField back = gap_field_hysteretic(m, f, 0.0, s).value;
  EXPECT_GT(up.flux_density_T, back.flux_density_T);
  // Remanence: with the play at its edge p = H_s + H_c and a near-linear core, the circuit
  // (H_s l_s + H_f g = 0) leaves H_f = k H_c l_s / (l_s + g k), k = mu_s A_s / (mu_f A_p):
  // about 4 kA/m, i.e. over 1 kPa of yield stress, with no current at all.
  const double k = kMu0_H_per_m * m.steel.initial_relative_permeability * m.steel_area_m2 /
                   (fluid_permeability_H_per_m(f, back.field_A_per_m) * m.pole_area_m2);
  const double h_rem =
      k * m.steel.coercivity_A_per_m * m.steel_path_length_m / (m.steel_path_length_m + m.fluid_gap_m * k);
  EXPECT_NEAR(back.field_A_per_m / h_rem, 1.0, 0.05);  // core and fluid are only nearly linear
  EXPECT_GT(back.yield_stress_Pa, 1000.0);
  // A negative current of about H_c l_s / N clears it.
  HysteresisState s2 = s;
  const GapField cleared =
      gap_field_hysteretic(m, f, -m.steel.coercivity_A_per_m * m.steel_path_length_m / m.turns, s2).value;
  EXPECT_LT(std::fabs(cleared.field_A_per_m), 0.05 * back.field_A_per_m);
  // Without coercivity the hysteretic solve equals the anhysteretic one, state or not.
  m.steel.coercivity_A_per_m = 0.0;
  HysteresisState s3{123.0};
  EXPECT_NEAR(gap_field_hysteretic(m, f, 1.0, s3).value.flux_density_T,
              gap_field(m, f, 1.0).value.flux_density_T, 1e-15);
}

TEST(ModelMagnetic, ZeroFieldInductance) {
  const FluidParams f;
  MagneticCircuitParams m = low_carbon_steel_circuit();
  const double r = zero_field_reluctance_per_H(m, f);
  EXPECT_NEAR(zero_field_inductance_H(m, f), m.turns * m.turns / r, 1e-15);
  // The small-signal inductance is the flux linkage slope: N dPhi/dI at I -> 0.
  const double di = 1e-6;
  const double phi = gap_field(m, f, di).value.flux_density_T * m.pole_area_m2;
  EXPECT_NEAR(m.turns * phi / di / zero_field_inductance_H(m, f), 1.0, 1e-4);
}

CoilParams coil() {
  CoilParams c;
  c.resistance_ohm = 1.0;
  c.inductance_H = 1e-3;
  c.supply_voltage_V = 12.0;
  c.max_current_A = 0.5;
  c.current_resolution_A = 125e-6;
  c.driver_bandwidth_Hz = 1000.0;
  c.eddy_time_constant_s = 5e-3;
  return c;
}

TEST(ModelCoil, CurrentLoopIsFirstOrderAtItsBandwidth) {
  const CoilParams c = coil();
  const double tau = current_loop_time_constant_s(c);
  EXPECT_NEAR(tau, 1.0 / (2 * kPi * 1000.0), 1e-15);
  EXPECT_NEAR(coil_time_constant_s(c), tau + 5e-3, 1e-15);
  EXPECT_NEAR(open_loop_time_constant_s(c), 1e-3, 1e-15);
  // Small step (the supply never limits it): I(tau) = 63.2 % of the step.
  const CoilState s = coil_step(c, CoilState{}, 0.01, tau).value;
  EXPECT_NEAR(s.current_A / 0.01, 1.0 - std::exp(-1.0), 1e-12);
  // Splitting the interval changes nothing (exact integration).
  CoilState a{};
  for (int k = 0; k < 10; ++k) {
    a = coil_step(c, a, 0.01, tau / 10).value;
  }
  EXPECT_NEAR(a.current_A, s.current_A, 1e-15);
}

TEST(ModelCoil, SupplyLimitsTheSlewOfALargeStep) {
  CoilParams c = coil();
  c.supply_voltage_V = 1.0;  // 0.5 A step wants 3.1 kA/s: the rail gives at most 1 kA/s
  const double dt = 1e-4;
  const CoilState s = coil_step(c, CoilState{}, 0.5, dt).value;
  // On the rail: I = V/R (1 - e^{-t R / L}).
  EXPECT_NEAR(s.current_A, 1.0 * (1.0 - std::exp(-dt * 1000.0)), 1e-12);
  // Eventually it reaches the command.
  CoilState t{};
  for (int k = 0; k < 200; ++k) {
    t = coil_step(c, t, 0.5, 1e-4).value;
  }
  EXPECT_NEAR(t.current_A, 0.5, 1e-6);
}

TEST(ModelCoil, EddyCurrentsLagTheField) {
  const CoilParams c = coil();
  CoilState s{};
  for (int k = 0; k < 5; ++k) {  // 5 ms: the current has settled, the field has not
    s = coil_step(c, s, 0.2, 1e-3).value;
  }
  EXPECT_NEAR(s.current_A, 0.2, 1e-9);
  EXPECT_LT(s.field_current_A, 0.2 * 0.7);
  EXPECT_GT(s.field_current_A, 0.2 * 0.5);
  for (int k = 0; k < 50; ++k) {
    s = coil_step(c, s, 0.2, 1e-3).value;
  }
  EXPECT_NEAR(s.field_current_A, 0.2, 1e-5);
}

// The observer steps every moving coil by one tick with the decays computed once: the result must
// be coil_step's to the bit, on the linear loop, on the supply's rail and with no eddy lag.
TEST(ModelCoil, PrecomputedDecaysStepBitForBitAsCoilStep) {
  CoilParams slow_supply = coil();
  slow_supply.supply_voltage_V = 1.0;  // large steps ride the rail first
  CoilParams no_eddy = coil();
  no_eddy.eddy_time_constant_s = 0.0;
  std::mt19937_64 rng(11);
  std::uniform_real_distribution<double> command(-0.5, 0.5);
  int rail_steps = 0;
  for (const CoilParams& c : {coil(), slow_supply, no_eddy}) {
    for (const double dt : {1e-4, 1e-3, 2.5e-3}) {
      const CoilDecay decay = coil_decay(c, dt);
      CoilState a{};
      CoilState b{};
      for (int k = 0; k < 400; ++k) {
        const double cmd = k % 7 == 0 ? 0.0 : command(rng);
        const Result<CoilState> by_dt = coil_step(c, a, cmd, dt);
        const Result<CoilState> by_decay = coil_step(c, b, cmd, decay);
        ASSERT_EQ(by_dt.status, by_decay.status);
        ASSERT_EQ(by_dt.value.current_A, by_decay.value.current_A) << "step " << k;
        ASSERT_EQ(by_dt.value.field_current_A, by_decay.value.field_current_A) << "step " << k;
        const double linear_A = cmd + (a.current_A - cmd) * decay.loop;
        rail_steps += by_dt.value.current_A != linear_A ? 1 : 0;
        a = by_dt.value;
        b = by_decay.value;
      }
    }
  }
  EXPECT_GT(rail_steps, 50) << "the slow supply's rail must be exercised";
  // Errors as coil_step's.
  EXPECT_EQ(coil_step(coil(), CoilState{}, 0.6, coil_decay(coil(), 1e-3)).status, Status::out_of_range);
  EXPECT_EQ(coil_step(coil(), CoilState{}, std::nan(""), coil_decay(coil(), 1e-3)).status,
            Status::not_finite);
}

TEST(ModelCoil, BadCommandsAreExplicitErrors) {
  const CoilParams c = coil();
  EXPECT_EQ(coil_step(c, CoilState{}, 0.6, 1e-3).status, Status::out_of_range);
  EXPECT_EQ(coil_step(c, CoilState{}, -0.6, 1e-3).status, Status::out_of_range);
  // A bipolar driver reverses the current (degauss): the same lag the other way.
  EXPECT_EQ(coil_step(c, CoilState{}, -0.1, 1e-3).status, Status::ok);
  EXPECT_LT(coil_step(c, CoilState{}, -0.1, 1e-3).value.current_A, 0.0);
  EXPECT_EQ(coil_step(c, CoilState{}, 0.1, -1e-3).status, Status::negative);
  EXPECT_EQ(coil_step(c, CoilState{}, std::nan(""), 1e-3).status, Status::not_finite);
  EXPECT_STREQ(check_coil(c), "");
  CoilParams weak = c;
  weak.supply_voltage_V = 0.1;
  EXPECT_NE(std::string(check_coil(weak)).find("supply_voltage_V"), std::string::npos);
}

}  // namespace
