// The bus budget (bus_budget.hpp) against loads worked by hand from the frame and report rules of
// docs/protocol.md, "Cost": the 5x5 at 1 and 10 kHz on every bus, packing, the grids classic CAN
// cannot address, and the highest rate that fits.
#include "mrskin/protocol/bus_budget.hpp"

#include <gtest/gtest.h>

#include "mrskin/protocol/can.hpp"

namespace mrskin::protocol {
namespace {

CyclicTraffic grid_5x5(double update_rate_hz, bool packed) {
  CyclicTraffic t;
  t.valves = 12;
  t.sensors = 12;
  t.update_rate_hz = update_rate_hz;
  t.packed = packed;
  return t;
}

TEST(ProtocolBusBudget, ClassicCanFullUpdateOfThe5x5IsTheHandWorkedLoad) {
  // Per 1 ms: 3 valve blocks, 1 TimeSync and 3 sensor blocks; a heartbeat at 50 Hz and a status at
  // 10 Hz; no echo on CAN. Every single frame has 8 data bytes (counter and CRC-8 included):
  // 135 bits, 135 us at 1 Mbit/s.
  const BusBudget b = compute_bus_budget(default_bus_spec(BusKind::can_classic), grid_5x5(1000.0, false));
  const double frame8_s = can_frame_time_worst_case_s(8, false, 1e6, 5e6);
  EXPECT_DOUBLE_EQ(frame8_s, 135e-6);
  const double h2d = (3 * 1000 + 50) * frame8_s;
  const double d2h = (4 * 1000 + 10) * frame8_s;
  EXPECT_NEAR(b.host_to_device.load, h2d, 1e-12);
  EXPECT_NEAR(b.device_to_host.load, d2h, 1e-12);
  EXPECT_DOUBLE_EQ(b.host_to_device.units_per_s, 3050.0);
  EXPECT_DOUBLE_EQ(b.device_to_host.units_per_s, 4010.0);
  EXPECT_TRUE(b.one_bus);
  EXPECT_NEAR(b.load(), 0.9531, 1e-4);  // the Cost section's 95.3 %
  EXPECT_TRUE(b.fits());
  EXPECT_FALSE(b.fits(0.8));
}

TEST(ProtocolBusBudget, FullSpeedHidNeedsPackingForThe5x5At1kHz) {
  const BusSpec fs = default_bus_spec(BusKind::hid_full_speed);
  // One packet a report: heartbeats (50 Hz) take reports of their own beside 1000 updates, and
  // status (10 Hz) and echoes (50 Hz) beside 1000 samples: 1.05 and 1.06 reports a frame.
  const BusBudget unpacked = compute_bus_budget(fs, grid_5x5(1000.0, false));
  EXPECT_DOUBLE_EQ(unpacked.host_to_device.slot_fraction, 1.05);
  EXPECT_DOUBLE_EQ(unpacked.device_to_host.slot_fraction, 1.06);
  EXPECT_FALSE(unpacked.fits());
  // Packed (1.2): currents 33 B + heartbeat 8 B, telemetry 37 B + status 11 B or echo 8 B, each
  // in one 64-byte report: one report a frame, and the bytes well within 80 %.
  const BusBudget packed = compute_bus_budget(fs, grid_5x5(1000.0, true));
  EXPECT_DOUBLE_EQ(packed.host_to_device.slot_fraction, 1.0);
  EXPECT_DOUBLE_EQ(packed.device_to_host.slot_fraction, 1.0);
  EXPECT_DOUBLE_EQ(packed.host_to_device.bytes_per_s, 1000 * 33.0 + 50 * 8.0);
  EXPECT_DOUBLE_EQ(packed.device_to_host.bytes_per_s, 1000 * 37.0 + 10 * 11.0 + 50 * 8.0);
  EXPECT_NEAR(packed.load(), (1000 * 37.0 + 10 * 11.0 + 50 * 8.0) / 64000.0, 1e-12);
  EXPECT_TRUE(packed.fits(0.8));
  // The device's own traffic fills the slots whatever the loop's rate: nothing fits unpacked.
  EXPECT_EQ(highest_update_rate_hz(fs, grid_5x5(1000.0, false)), 0.0);
  EXPECT_EQ(highest_update_rate_hz(fs, grid_5x5(1000.0, true)), 1000.0);
}

TEST(ProtocolBusBudget, At10kHzOnlyHighSpeedCarriesThe5x5) {
  for (const bool packed : {false, true}) {
    EXPECT_FALSE(compute_bus_budget(default_bus_spec(BusKind::hid_full_speed), grid_5x5(1e4, packed)).fits());
    EXPECT_FALSE(compute_bus_budget(default_bus_spec(BusKind::can_classic), grid_5x5(1e4, packed)).fits());
    EXPECT_FALSE(compute_bus_budget(default_bus_spec(BusKind::can_fd), grid_5x5(1e4, packed)).fits());
    EXPECT_TRUE(
        compute_bus_budget(default_bus_spec(BusKind::hid_high_speed), grid_5x5(1e4, packed)).fits(0.8));
  }
}

TEST(ProtocolBusBudget, TheHighestRateIsTheLastThatFits) {
  const BusSpec can = default_bus_spec(BusKind::can_classic);
  const double hz = highest_update_rate_hz(can, grid_5x5(1000.0, false));
  EXPECT_GT(hz, 1000.0);
  EXPECT_TRUE(compute_bus_budget(can, grid_5x5(hz, false)).fits());
  EXPECT_FALSE(compute_bus_budget(can, grid_5x5(hz + 1.0, false)).fits());
  // At 80 % the loop must slow below 1 kHz.
  EXPECT_LT(highest_update_rate_hz(can, grid_5x5(1000.0, false), 0.8), 1000.0);
}

TEST(ProtocolBusBudget, GridsAClassicCanNodeCannotAddressAreNotEncodable) {
  CyclicTraffic t;
  t.valves = 128;  // a 16x16: 16 blocks of 4 is one node's limit
  t.sensors = 128;
  const BusBudget b = compute_bus_budget(default_bus_spec(BusKind::can_classic), t);
  EXPECT_FALSE(b.encodable);
  EXPECT_NE(b.why_not.find("64 valves"), std::string::npos) << b.why_not;
  EXPECT_FALSE(b.fits());
  EXPECT_EQ(highest_update_rate_hz(default_bus_spec(BusKind::can_classic), t), 0.0);
  // High-speed HID carries it packed at 1 kHz within 80 %; a 64x64 too.
  t.packed = true;
  EXPECT_TRUE(compute_bus_budget(default_bus_spec(BusKind::hid_high_speed), t).fits(0.8));
  t.valves = t.sensors = 2048;
  EXPECT_TRUE(compute_bus_budget(default_bus_spec(BusKind::hid_high_speed), t).fits(0.8));
}

// A configuration reply beside a sample in one report: the bytes hand-counted from the framing
// (4-byte header, 2-byte CRC; Telemetry 7 + 2 a value, ConfigData 7 + n).
TEST(ProtocolBusBudget, ConfigBytesBesideTheTelemetryAreWhatTheReportLeaves) {
  // 5x5: 12 sensors, 6 + 7 + 24 = 37 bytes; 64 - 37 - 13 = 14.
  EXPECT_EQ(config_bytes_beside_telemetry(12, 64), 14U);
  // 25 values fill 63 bytes: no reply fits beside them.
  EXPECT_EQ(config_bytes_beside_telemetry(25, 64), 0U);
  // No sensors: the report's room, capped at one chunk.
  EXPECT_EQ(config_bytes_beside_telemetry(0, 64), kMaxConfigBytes);
  // 26 values: a 63-byte packet, then a 15-byte one in the next report; 64 - 15 - 13 = 36.
  EXPECT_EQ(config_bytes_beside_telemetry(26, 64), 36U);
  // 256 sensors in 1024-byte reports: ten 63-byte packets and one of 6 + 7 + 12 = 25 share one.
  EXPECT_EQ(config_bytes_beside_telemetry(256, 1024), kMaxConfigBytes);
}

}  // namespace
}  // namespace mrskin::protocol
