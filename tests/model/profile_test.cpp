// Profiles: the shipped files load and describe the devices they claim to; bad files are
// rejected with the field and the reason named.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <regex>
#include <sstream>
#include <string>

#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/model/device_model.hpp"

namespace {

using namespace mrskin::model;

const std::string kDir = MRSKIN_TEST_PROFILE_DIR;

std::string read(const std::string& name) {
  std::ifstream in(kDir + "/" + name + ".toml");
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

TEST(ModelProfile, DefaultIsThePapers5x5) {
  const DeviceProfile p = load_profile(kDir + "/mr-skin-5x5.toml");
  EXPECT_EQ(p.name, "mr-skin-5x5");
  const DeviceModel m(p);
  EXPECT_EQ(m.layout().fluid_cell_count(), 13u);
  EXPECT_EQ(m.layout().valve_count(), 12u);
  ASSERT_EQ(p.sensors.size(), 12u);
  for (const SensorSpec& s : p.sensors) {
    EXPECT_EQ(s.quantity, SensorQuantity::displacement);
    EXPECT_EQ(s.place, PlaceKind::valve);
    EXPECT_EQ((s.row + s.col) % 2, 1);  // under a valve cell
    EXPECT_GT(s.resolution, 0.0);
  }
  // Chamber topology: one passage per (valve, adjacent fluid cell) + one per edge valve to the
  // reservoir: 4 x 4 interior + 8 x 3 edge + 8 reservoir = 48 links.
  EXPECT_EQ(p.links.size(), 48u);
  // Corner cells touch 2 valves, edge cells 3, inner cells 4.
  EXPECT_EQ(m.branch_count(m.fluid_cell_index(0, 0).value), 2u);
  EXPECT_EQ(m.branch_count(m.fluid_cell_index(0, 2).value), 3u);
  EXPECT_EQ(m.branch_count(m.fluid_cell_index(2, 2).value), 4u);
  // Paper values kept: 0.121 mm skin, 40 mm cell depth, 24.01 mm valve length, 30 mm depth.
  EXPECT_DOUBLE_EQ(p.membrane.thickness_m, 0.121e-3);
  EXPECT_DOUBLE_EQ(p.cell_depth_m, 0.040);
  EXPECT_DOUBLE_EQ(p.valve.length_m, 24.01e-3);
  EXPECT_DOUBLE_EQ(p.valve.width_m, 0.030);
  // The coil inductance in the file is the circuit's own (within 10 %).
  EXPECT_NEAR(p.coil.inductance_H / zero_field_inductance_H(p.magnetic, p.fluid), 1.0, 0.1);
  // Reynolds number at a fingertip's flows is about 1, far from 2300.
  EXPECT_LT(m.valve_law().reynolds_number(1e-5), 100.0);
}

TEST(ModelProfile, DefaultProfileIsFoundByName) {
  const DeviceProfile p = default_profile();
  EXPECT_EQ(p.name, kDefaultProfileName);
  EXPECT_THROW(load_profile("no-such-profile-xyz"), mrskin::InvalidArgument);
}

TEST(ModelProfile, FingertipAndPalmGrids) {
  for (const auto& [name, rows, cols] :
       {std::tuple{"fingertip-16x16", 16, 16}, std::tuple{"palm-64x64", 64, 64}}) {
    const DeviceProfile p = load_profile(kDir + "/" + name + ".toml");
    const DeviceModel m(p);
    EXPECT_EQ(p.rows, rows);
    EXPECT_EQ(p.cols, cols);
    EXPECT_EQ(m.layout().fluid_cell_count() + m.layout().valve_count(),
              static_cast<std::size_t>(rows * cols));
    EXPECT_FALSE(p.sensors.empty());
    // Its own design point: the design force is inside the envelope and reached below max current.
    const std::size_t c = m.fluid_cell_index(p.design.row, p.design.col).value;
    const CellEnvelope e = m.envelope(c, p.design.indentation_m, 0.0).value;
    EXPECT_LT(e.force_min_N, p.design.force_range_N) << name;
    EXPECT_GT(e.force_max_N, p.design.force_range_N) << name;
    const double frac = m.current_for_force_A(c, p.design.indentation_m, 0.0, p.design.force_range_N).value /
                        p.coil.max_current_A;
    EXPECT_GT(frac, 0.6) << name;
    EXPECT_LT(frac, 0.95) << name;
  }
}

TEST(ModelProfile, PaperTable4ProfileLoads) {
  const DeviceModel m(load_profile(kDir + "/paper-table4.toml"));
  EXPECT_DOUBLE_EQ(m.profile().valve.gap_m, 0.5e-3);
  EXPECT_DOUBLE_EQ(m.profile().coil.max_current_A, 2.0);
}

// Replaces the first occurrence of `from` in the default profile's text.
std::string mutate(const std::string& from, const std::string& to) {
  std::string t = read("mr-skin-5x5");
  const auto pos = t.find(from);
  EXPECT_NE(pos, std::string::npos) << from;
  return t.replace(pos, from.size(), to);
}

void expect_rejected(const std::string& text, const std::string& needle) {
  try {
    (void)parse_profile(text, "bad.toml");
    ADD_FAILURE() << "accepted; expected an error mentioning: " << needle;
  } catch (const mrskin::InvalidArgument& e) {
    EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
    EXPECT_EQ(std::string(e.what()).rfind("bad.toml", 0), 0u) << e.what();
  }
}

TEST(ModelProfile, BadProfilesNameTheFieldAndTheReason) {
  expect_rejected(mutate("gap_m = 1.0e-3", "gap_m = -1.0e-3"), "[valve] gap_m: must be > 0");
  expect_rejected(mutate("gap_m = 1.0e-3", "gap_m = \"wide\""), "[valve] gap_m: must be a number");
  expect_rejected(mutate("gap_m = 1.0e-3", "gap_mm = 1.0"), "[valve] gap_m: missing");
  expect_rejected(mutate("width_m = 0.030", "width_m = 0.030\nwidht_m = 1.0"),
                  "[valve] widht_m: unknown key");
  expect_rejected(mutate("gap_m = 1.0e-3", "gap_m = 10.0e-3"), "[valve] gap_m: the slot law needs");
  expect_rejected(mutate("rows = 5", "rows = 0"), "[grid] rows: must be in 1..255");
  expect_rejected(mutate("rows = 5", "rows = 5.5"), "[grid] rows: must be an integer");
  expect_rejected(mutate("volume_fraction = 0.32", "volume_fraction = 0.9"), "[fluid] volume_fraction");
  expect_rejected(mutate("poisson_ratio = 0.5", "poisson_ratio = 0.7"), "[membrane] poisson_ratio");
  expect_rejected(mutate("turns = 20", "turns = 0"), "[magnetic] turns");
  expect_rejected(mutate("max_current_A = 0.1", "max_current_A = 0.1e3"), "[coil] supply_voltage_V");
  expect_rejected(mutate("current_resolution_A = 25.0e-6", "current_resolution_A = 1.0e-6"),
                  "[coil] current_resolution_A: max_current_A / resolution exceeds the 4095 counts");
  expect_rejected(mutate("topology = \"chamber\"", "topology = \"mesh\""), "[hydraulics] topology");
  expect_rejected(mutate("unit = \"m\"", "unit = \"mm\""), "[sensors] unit: must be \"m\"");
  expect_rejected(mutate("quantity = \"displacement\"", "quantity = \"strain\""), "[sensors] quantity");
  expect_rejected(mutate("cell = \"2,2\"", "cell = \"2,3\""), "[design] cell: \"2,3\" is not a fluid cell");
  expect_rejected(mutate("format_version = 1", "format_version = 2"), "[profile] format_version");
  expect_rejected(mutate("[grid]", "[grid\n"), "bad.toml:");
  expect_rejected(mutate("finger_radius_m = 6.0e-3", "finger_radius_m = 1.0e-6"),
                  "[contact] finger_radius_m");
  expect_rejected(mutate("viscosity_Pa_s = 0.112", "viscosity_Pa_s = nan"),
                  "[fluid] viscosity_Pa_s: must be finite");
  expect_rejected(read("mr-skin-5x5") + "\n[interface]\nbus = \"usb\"\n",
                  "[interface] bus: \"usb\" is not \"hid-fs\", \"hid-hs\", \"can\", \"canfd\" or \"none\"");
  expect_rejected(read("mr-skin-5x5") + "\n[interface]\nbitrate = 1\n", "[interface] bitrate: unknown key");
}

// [interface] bus: the bus a unit is built with, hid-fs unless the profile says otherwise.
TEST(ModelProfile, TheInterfaceNamesTheBus) {
  EXPECT_EQ(parse_profile(read("mr-skin-5x5"), "5x5").bus, mrskin::protocol::BusKind::hid_full_speed);
  EXPECT_EQ(load_profile("fingertip-16x16").bus, mrskin::protocol::BusKind::hid_high_speed);
  EXPECT_EQ(load_profile("palm-64x64").bus, mrskin::protocol::BusKind::hid_high_speed);
  EXPECT_FALSE(parse_profile(read("mr-skin-5x5") + "\n[interface]\nbus = \"none\"\n", "t").bus.has_value());
  EXPECT_EQ(parse_profile(read("mr-skin-5x5") + "\n[interface]\nbus = \"canfd\"\n", "t").bus,
            mrskin::protocol::BusKind::can_fd);
}

TEST(ModelProfile, ExplicitGraphAndSensors) {
  // A 1 x 3 strip: cells (0,0) and (0,2) around one valve, listed by hand, with a pressure
  // sensor per fluid cell: a different unit is a different profile, not different code.
  std::string t = read("mr-skin-5x5");
  t = std::regex_replace(t, std::regex("rows = 5"), "rows = 1");
  t = std::regex_replace(t, std::regex("cols = 5"), "cols = 3");
  t = std::regex_replace(t, std::regex("topology = \"chamber\""), "topology = \"explicit\"");
  t = std::regex_replace(t, std::regex("reservoir = \"edge_valves\""), "reservoir = \"none\"");
  t = std::regex_replace(t, std::regex("cell = \"2,2\""), "cell = \"0,0\"");
  t = std::regex_replace(t,
                         std::regex("generate = \"under_valves\"\nquantity = \"displacement\"\nunit = \"m\""),
                         "generate = \"per_fluid_cell\"\nquantity = \"pressure\"\nunit = \"Pa\"");
  t += "\n[[hydraulics.link]]\nfrom = \"cell 0,0\"\nto = \"chamber 0,1\"\nvalve = \"0,1\"\n"
       "[[hydraulics.link]]\nfrom = \"chamber 0,1\"\nto = \"cell 0,2\"\nvalve = \"0,1\"\n"
       "[[sensors.sensor]]\nquantity = \"force\"\nunit = \"N\"\nplace = \"cell 0,2\"\nresolution = 1e-3\n"
       "noise_std = 2e-3\n";
  const DeviceProfile p = parse_profile(t, "strip.toml");
  EXPECT_EQ(p.links.size(), 2u);
  ASSERT_EQ(p.sensors.size(), 3u);
  EXPECT_EQ(p.sensors[0].quantity, SensorQuantity::pressure);
  EXPECT_EQ(p.sensors[2].quantity, SensorQuantity::force);
  EXPECT_EQ(p.sensors[2].place, PlaceKind::fluid_cell);
  const DeviceModel m(p);
  // Cell (0,0) -> chamber -> cell (0,2): two passages in series.
  EXPECT_NEAR(m.valve_network_pressure_uniform_Pa(0, 0.0, 10.0).value,
              2 * m.valve_law().yield_pressure_Pa(10.0), 1e-9);
  // A cell with no link is rejected.
  const std::string lonely = std::regex_replace(t, std::regex("to = \"cell 0,2\""), "to = \"reservoir\"");
  expect_rejected(lonely, "fluid cell 0,2 has no link");
  expect_rejected(t + "[[hydraulics.link]]\nfrom = \"chamber 0,1\"\nto = \"chamber 0,1\"\nvalve = \"none\"\n",
                  "joins a node to itself");
  expect_rejected(t + "[[hydraulics.link]]\nfrom = \"cell 0,1\"\nto = \"reservoir\"\nvalve = \"none\"\n",
                  "\"cell 0,1\" is not a fluid cell");
}

}  // namespace
