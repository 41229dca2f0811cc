// A unit's calibration: parsing, round trip, what it changes in a profile, and the factory
// measurement of a perturbed plant (the mock stores it; the bridge applies it).
#include "mrskin/driver/model/calibration.hpp"

#include <gtest/gtest.h>

#include <string>
#include <vector>

#include "mrskin/driver/errors.hpp"
#include "mrskin/sim/network_plant.hpp"

namespace {

using namespace mrskin::model;

const std::string kDir = MRSKIN_TEST_PROFILE_DIR;

TEST(ModelCalibration, RoundTripsThroughItsText) {
  Calibration c;
  c.version = 7;
  c.serial = 0xBEEF;
  c.profile = "mr-skin-5x5";
  c.viscosity_scale = 1.031;
  c.yield_scale = 0.962;
  c.membrane_modulus_scale = 1.084;
  c.membrane_pretension_scale = 0.931;
  c.reservoir_compliance_scale = 1.102;
  c.turns_scale = 1.05;
  c.gap_scale = 0.991;
  c.valve_yield_gain = {1.02, 0.97, 1.1};
  c.sensor_offset = {1.25e-7, -3.5e-8};
  const Calibration back = parse_calibration(format_calibration(c), "test", 3, 2);
  EXPECT_EQ(back.sensor_offset, c.sensor_offset);
  EXPECT_EQ(back.sensor_offset_unit, "m");
  EXPECT_EQ(back.version, 7);
  EXPECT_EQ(back.serial, 0xBEEFU);
  EXPECT_EQ(back.profile, "mr-skin-5x5");
  EXPECT_DOUBLE_EQ(back.viscosity_scale, 1.031);
  EXPECT_DOUBLE_EQ(back.membrane_pretension_scale, 0.931);
  EXPECT_EQ(back.valve_yield_gain, c.valve_yield_gain);
  EXPECT_DOUBLE_EQ(back.valve_gain(1), 0.97);
}

TEST(ModelCalibration, AcceptsTheOlderOneNumberForm) {
  const Calibration c = parse_calibration("version = 2\nvalve_yield_gain = 1.0\n", "test", 12);
  EXPECT_DOUBLE_EQ(c.valve_gain(11), 1.0);
  EXPECT_DOUBLE_EQ(c.membrane_modulus_scale, 1.0);
}

TEST(ModelCalibration, RefusesWhatCannotBeAUnit) {
  EXPECT_THROW(parse_calibration("valve_yield_gain = 1.0\n", "t"), mrskin::InvalidArgument);  // no version
  EXPECT_THROW(parse_calibration("version = 1\nyield_scale = 3.0\n", "t"), mrskin::InvalidArgument);
  EXPECT_THROW(parse_calibration("version = 1\nyield_scale = nan\n", "t"), mrskin::InvalidArgument);
  // Integers only, in range (the calibration fuzzer: a float version of 2.4e75 was cast to an
  // integer, undefined behaviour; a serial beyond 32 bits wrapped).
  EXPECT_THROW(parse_calibration("version = 2.4e75\n", "t"), mrskin::InvalidArgument);
  EXPECT_THROW(parse_calibration("version = 2.0\n", "t"), mrskin::InvalidArgument);
  EXPECT_THROW(parse_calibration("version = 1\nserial = 4294967296\n", "t"), mrskin::InvalidArgument);
  EXPECT_THROW(parse_calibration("version = 1\nserial = -1\n", "t"), mrskin::InvalidArgument);
  EXPECT_EQ(parse_calibration("version = 1\nserial = 4294967295\n", "t").serial, 4294967295U);
  EXPECT_THROW(parse_calibration("version = 1\nvalve_yield_gain = [1.0, 1.0]\n", "t", 12),
               mrskin::InvalidArgument);
  EXPECT_THROW(parse_calibration("version = [\n", "t"), mrskin::InvalidArgument);
  EXPECT_THROW(parse_calibration("version = 1\nsensor_offset_m = [0.0, nan]\n", "t"),
               mrskin::InvalidArgument);
  EXPECT_THROW(parse_calibration("version = 1\nsensor_offset_m = [0.0]\n", "t", 0, 12),
               mrskin::InvalidArgument);
  EXPECT_THROW(parse_calibration("version = 1\nsensor_offset_m = [0.0]\nsensor_offset_n = [0.0]\n", "t"),
               mrskin::InvalidArgument);
  try {
    parse_calibration("version = 1\ngap_scale = 0.1\n", "calibration on unit 7");
    FAIL();
  } catch (const mrskin::InvalidArgument& e) {
    EXPECT_NE(std::string(e.what()).find("gap_scale"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("calibration on unit 7"), std::string::npos) << e.what();
  }
}

TEST(ModelCalibration, MeasuringAPerturbedPlantRecoversItsParameters) {
  const DeviceProfile nominal = load_profile(kDir + "/mr-skin-5x5.toml");
  mrskin::sim::NetworkPlantOptions o;
  o.seed = 4;
  const mrskin::sim::NetworkPlant plant(nominal, o);
  const DeviceProfile& truth = plant.true_profile();
  // An exact factory: applying its calibration to the nominal gives the plant's parameters.
  const Calibration exact = measure_calibration(nominal, truth, plant.valve_yield_gain(), 0.0, 1);
  const DeviceProfile applied = apply_calibration(nominal, exact);
  EXPECT_NEAR(applied.membrane.youngs_modulus_Pa / truth.membrane.youngs_modulus_Pa, 1.0, 1e-12);
  EXPECT_NEAR(applied.membrane.pretension_N_per_m / truth.membrane.pretension_N_per_m, 1.0, 1e-12);
  EXPECT_NEAR(applied.fluid.viscosity_Pa_s / truth.fluid.viscosity_Pa_s, 1.0, 1e-12);
  EXPECT_NEAR(applied.fluid.carrier_factor / truth.fluid.carrier_factor, 1.0, 1e-12);
  EXPECT_NEAR(applied.valve.gap_m / truth.valve.gap_m, 1.0, 1e-12);
  EXPECT_EQ(applied.magnetic.turns, truth.magnetic.turns);
  ASSERT_EQ(exact.valve_yield_gain.size(), plant.valve_yield_gain().size());
  for (std::size_t v = 0; v < exact.valve_yield_gain.size(); ++v) {
    EXPECT_DOUBLE_EQ(exact.valve_gain(v), plant.valve_yield_gain()[v]);
  }
  // A real one is off by its measurement spread, and the perturbation is not negligible.
  const Calibration measured = measure_calibration(nominal, truth, plant.valve_yield_gain(), 0.01, 1);
  const double ratio = measured.membrane_modulus_scale / exact.membrane_modulus_scale;
  EXPECT_NEAR(ratio, 1.0, 0.05);
  EXPECT_NE(ratio, 1.0);
  bool perturbed = false;
  for (const double g : exact.valve_yield_gain) {
    perturbed = perturbed || std::abs(g - 1.0) > 0.01;
  }
  EXPECT_TRUE(perturbed);
}

}  // namespace
