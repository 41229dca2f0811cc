// The bus budget: what a unit's cyclic traffic needs of its bus, each direction, computed from
// the packets and frames the encoders make of it (encode_packet, encode_can, encode_canfd), so a
// rate the bus cannot carry is refused before the loop starts (docs/protocol.md, "Bus budget").
// Pure arithmetic, no I/O: the driver's session, the mock's bus model and the load table share it.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>

#include "mrskin/protocol/export.hpp"
#include "mrskin/protocol/usb.hpp"

namespace mrskin::protocol {

enum class BusKind : std::uint8_t { hid_full_speed, hid_high_speed, can_classic, can_fd };
inline constexpr std::size_t kBusKindCount = 4;

// "hid-fs", "hid-hs", "can", "canfd": the mock URI's bus= names.
MRSKIN_PROTOCOL_API const char* to_string(BusKind kind) noexcept;

struct BusSpec {
  BusKind kind = BusKind::hid_full_speed;
  UsbInterruptSlots usb = kUsbFullSpeedSlots;  // the USB buses: the endpoints' declared slots
  double nominal_bitrate_bit_per_s = 1e6;      // CAN
  double data_bitrate_bit_per_s = 5e6;         // CAN FD's data phase
};

// The usual spec of each kind: full-speed slots; high speed 3 reports a 125 us microframe, of
// 64 bytes with protocol 1.1 (packed = false: it declares nothing) and of up to 1024 with 1.2;
// classic CAN at 1 Mbit/s, CAN FD at 1/5 Mbit/s.
MRSKIN_PROTOCOL_API BusSpec default_bus_spec(BusKind kind, bool packed = true) noexcept;

// A unit's cyclic traffic. The host sends every valve's current at update_rate_hz (the loop's
// rate: the worst case, every tick changes them) and a Heartbeat at heartbeat_hz; the device
// sends every sensor at telemetry_rate_hz (its Identity's rate), a Status at status_hz and, on the
// packet framings, echoes each Heartbeat. packed: several packets share a report or an FD frame
// (protocol 1.2, agreed both ways); otherwise one packet a report or frame.
struct CyclicTraffic {
  std::size_t valves = 0;
  std::size_t sensors = 0;
  double update_rate_hz = 1000.0;
  double telemetry_rate_hz = 1000.0;
  double heartbeat_hz = 50.0;
  double status_hz = 10.0;
  bool packed = false;
};

struct DirectionLoad {
  double load = 0.0;           // USB: packet bytes over the bytes the slots carry; CAN: bus time
  double units_per_s = 0.0;    // reports or frames
  double bytes_per_s = 0.0;    // packet bytes (USB), data bytes (CAN)
  double slot_fraction = 0.0;  // USB: reports over the slots (above 1 they queue); CAN: = load
};

struct MRSKIN_PROTOCOL_API BusBudget {
  bool encodable = true;  // false: the grid has no form on this bus (more values than it addresses)
  std::string why_not;    // ...and why
  bool one_bus = false;   // CAN: both directions share the bus's time
  DirectionLoad host_to_device;
  DirectionLoad device_to_host;
  // The load a warning looks at (above 80 %): on USB the busier direction's bytes (each direction
  // has its own slots); on CAN both directions' time (one bus). Infinite when not encodable.
  [[nodiscard]] double load() const noexcept;
  // Within max_load, and on USB no more reports than slots either way (a report never shares a
  // slot: beyond them reports queue and are dropped, whatever their bytes).
  [[nodiscard]] bool fits(double max_load = 1.0) const noexcept;
};

MRSKIN_PROTOCOL_API BusBudget compute_bus_budget(const BusSpec& bus, const CyclicTraffic& traffic) noexcept;

// The highest update (loop) rate, to 1 Hz, whose budget fits within max_load with the rest of
// traffic as given (the device's telemetry keeps its own rate); 0 when even 1 Hz does not fit
// (the device's own traffic is too much for the bus).
MRSKIN_PROTOCOL_API double highest_update_rate_hz(const BusSpec& bus, CyclicTraffic traffic,
                                                  double max_load = 1.0) noexcept;

// Protocol 1.2 on a USB bus whose every slot carries a telemetry sample (full speed at 1 kHz):
// the ConfigData bytes that fit in a sample's last report beside its Telemetry packets (sensors
// values, report_bytes-byte reports), at most kMaxConfigBytes, 0 when none fit. A host reads its
// configuration in chunks of this size, so that each reply can ride with a sample instead of
// taking the sample's slot (docs/protocol.md, "Configuration reads beside the telemetry").
MRSKIN_PROTOCOL_API std::size_t config_bytes_beside_telemetry(std::size_t sensors,
                                                              std::size_t report_bytes) noexcept;

}  // namespace mrskin::protocol
