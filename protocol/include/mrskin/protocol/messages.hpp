// Protocol v1: the logical message set, defined once for every bus.
// Fields hold wire counts (integers); SI conversion lives in units.hpp.
// docs/protocol.md is the normative description of every byte.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <variant>

#include "mrskin/protocol/export.hpp"

namespace mrskin::protocol {

inline constexpr std::uint8_t kVersionMajor = 1;
// 1.1: StateRequest degauss, Status flag degaussing. 1.2: packed reports (packed_report.hpp),
// UsbSlots, a USB unit's declared report size and rate, delta blocks on classic CAN (can.hpp) and
// SensorDeadband, a unit's declared sensor deadband.
inline constexpr std::uint8_t kVersionMinor = 2;

enum class MessageType : std::uint8_t {
  identify_request = 0x01,
  identity = 0x02,
  usb_slots = 0x03,        // 1.2
  sensor_deadband = 0x04,  // 1.2
  valve_currents = 0x10,
  cell_targets = 0x11,
  telemetry = 0x20,
  time_sync = 0x21,
  status = 0x30,
  heartbeat = 0x31,
  state_request = 0x32,
  config_read = 0x40,
  config_data = 0x41,
  config_write = 0x42,
  config_ack = 0x43,
};

// Value domains, identical on every framing (classic CAN packs them in 12 bits).
inline constexpr std::uint16_t kCurrentCountMax = 4095;
inline constexpr std::int16_t kSensorCountMin = -2048;
inline constexpr std::int16_t kSensorCountMax = 2047;
inline constexpr std::uint16_t kStiffnessCountMax = 16383;  // 14 bit
inline constexpr std::uint16_t kOffsetCountMax = 4095;      // 12 bit
inline constexpr std::uint16_t kCeilingCountMax = 4095;     // 12 bit
inline constexpr std::uint8_t kValidityCountMax = 63;       // 6 bit
inline constexpr std::uint16_t kCellIndexMaxCan = 255;      // classic CAN addresses 256 cells

// Capacity of one message (bounded by the 58-byte packet payload).
inline constexpr std::size_t kMaxValveCurrents = 27;
inline constexpr std::size_t kMaxTelemetryValues = 25;
inline constexpr std::size_t kMaxCellTargets = 7;
inline constexpr std::size_t kMaxConfigBytes = 48;

struct IdentifyRequest {
  std::uint8_t host_major = kVersionMajor;
  std::uint8_t host_minor = kVersionMinor;
  bool operator==(const IdentifyRequest&) const = default;
};

enum class SensorQuantity : std::uint8_t { displacement_m = 0, force_N = 1, pressure_Pa = 2 };

struct Identity {
  std::uint8_t proto_major = kVersionMajor;
  std::uint8_t proto_minor = kVersionMinor;
  std::uint8_t fw_major = 0;
  std::uint8_t fw_minor = 0;
  std::uint8_t fw_patch = 0;
  std::uint8_t rows = 0;
  std::uint8_t cols = 0;
  std::uint16_t fluid_cells = 0;
  std::uint16_t valves = 0;
  std::uint16_t sensors = 0;
  std::uint32_t serial = 0;
  std::uint32_t current_lsb_nA = 0;        // coil current per count, nA
  std::uint16_t current_max_counts = 0;    // device's highest allowed count, <= 4095
  std::uint8_t sensor_quantity = 0;        // SensorQuantity
  std::uint32_t sensor_lsb_nano = 0;       // sensor LSB in 1e-9 of its SI unit
  std::uint16_t heartbeat_timeout_ms = 0;  // device releases valves after this silence
  std::uint16_t telemetry_rate_hz = 0;
  bool operator==(const Identity&) const = default;
};

struct ValveCurrents {
  std::uint16_t first = 0;  // index of the first valve
  std::uint8_t count = 0;   // 1..kMaxValveCurrents
  std::array<std::uint16_t, kMaxValveCurrents> counts{};
  bool operator==(const ValveCurrents&) const = default;
};

// Impedance target of one fluid cell: F = stiffness * (x - offset), capped at ceiling,
// valid for validity after receipt (0 = release now).
struct CellTarget {
  std::uint16_t stiffness = 0;  // 2 N/m per count, 14 bit
  std::uint16_t offset = 0;     // 2 um per count, 12 bit
  std::uint16_t ceiling = 0;    // 1 mN per count, 12 bit
  std::uint8_t validity = 0;    // 10 ms per count, 6 bit
  bool operator==(const CellTarget&) const = default;
};

struct CellTargets {
  std::uint16_t first = 0;
  std::uint8_t count = 0;  // 1..kMaxCellTargets
  std::array<CellTarget, kMaxCellTargets> targets{};
  bool operator==(const CellTargets&) const = default;
};

struct Telemetry {
  std::uint32_t device_time_us = 0;  // device clock at sampling, wraps after 71.6 min
  std::uint16_t first = 0;           // index of the first sensor
  std::uint8_t count = 0;            // 1..kMaxTelemetryValues
  std::array<std::int16_t, kMaxTelemetryValues> counts{};
  bool operator==(const Telemetry&) const = default;
};

// Classic CAN only: stamps the sensor blocks that share its rolling counter.
struct TimeSync {
  std::uint32_t device_time_us = 0;
  bool operator==(const TimeSync&) const = default;
};

enum class DeviceState : std::uint8_t { disabled = 0, enabled = 1, paused = 2, fault = 3 };
enum class FaultCode : std::uint8_t {
  none = 0,
  heartbeat_lost = 1,
  overtemperature = 2,
  overcurrent = 3,
  sensor_fault = 4,
  bus_off = 5,
  estop = 6,
  internal = 7,
};
enum StatusFlags : std::uint8_t {
  kFlagValvesReleased = 1U << 0U,
  kFlagDerated = 1U << 1U,
  kFlagCalibrated = 1U << 2U,
  kFlagDegaussing = 1U << 3U,  // 1.1: a degauss cycle is running (StateRequestCode::degauss)
};

struct Status {
  std::uint8_t state = 0;  // DeviceState
  std::uint8_t fault = 0;  // FaultCode
  std::uint16_t fault_detail = 0;
  std::uint8_t flags = 0;  // StatusFlags
  bool operator==(const Status&) const = default;
};

struct Heartbeat {
  std::uint16_t counter = 0;
  bool operator==(const Heartbeat&) const = default;
};

// degauss (1.1): a disabled device with a bipolar coil driver runs a decaying alternating current
// through every coil and stays disabled; a device without one ignores it (no degaussing flag).
enum class StateRequestCode : std::uint8_t { disable = 0, enable = 1, pause = 2, estop = 3, degauss = 4 };
struct StateRequest {
  std::uint8_t request = 0;  // StateRequestCode
  bool operator==(const StateRequest&) const = default;
};

// Configuration memory is a set of keyed blobs read and written in chunks.
enum class ConfigKey : std::uint16_t { profile = 0x0001, calibration = 0x0002 };

struct ConfigRead {
  std::uint16_t key = 0;
  std::uint16_t offset = 0;
  std::uint8_t length = 0;  // 1..kMaxConfigBytes
  bool operator==(const ConfigRead&) const = default;
};

struct ConfigChunk {
  std::uint16_t key = 0;
  std::uint16_t offset = 0;
  std::uint16_t total = 0;  // whole blob length
  std::uint8_t length = 0;  // 0..kMaxConfigBytes
  std::array<std::uint8_t, kMaxConfigBytes> bytes{};
  bool operator==(const ConfigChunk&) const = default;
};
struct ConfigData : ConfigChunk {
  bool operator==(const ConfigData&) const = default;
};
struct ConfigWrite : ConfigChunk {
  bool operator==(const ConfigWrite&) const = default;
};

enum class ConfigStatus : std::uint8_t { ok = 0, bad_key = 1, bad_range = 2, rejected = 3, busy = 4 };
struct ConfigAck {
  std::uint16_t key = 0;
  std::uint16_t offset = 0;
  std::uint8_t status = 0;  // ConfigStatus
  bool operator==(const ConfigAck&) const = default;
};

// 1.2, USB only: what the unit's interrupt endpoints carry each way, at most reports_per_interval
// reports of at most report_bytes bytes every interval_us (usb.hpp, UsbInterruptSlots). A 1.2 unit
// sends it right after its Identity once the host said 1.2; until it comes (and from a 1.1 unit)
// the host assumes full speed: one 64-byte report a 1 ms frame. Packets stay at most 64 bytes; a
// larger report carries several, packed (packed_report.hpp).
struct UsbSlots {
  std::uint16_t report_bytes = 64;        // 64..1024
  std::uint8_t reports_per_interval = 1;  // 1..3
  std::uint16_t interval_us = 1000;       // 125, 250, 500 or 1000
  bool operator==(const UsbSlots&) const = default;
};
inline constexpr std::uint16_t kUsbSlotsMinReportBytes = 64;
inline constexpr std::uint16_t kUsbSlotsMaxReportBytes = 1024;
inline constexpr std::uint8_t kUsbSlotsMaxReportsPerInterval = 3;

// 1.2, any bus: the unit sends a block of sensor readings (kCanValuesPerBlock of them, the blocks
// of classic CAN's frames, on every bus) with the values it last sent in that block while every
// reading of the block lies within `counts` of them, so that classic CAN's delta blocks can leave
// it out. A 1.2 unit with a deadband sends this right after its Identity (and UsbSlots) once the
// host said 1.2, and applies the deadband only then; a unit without one sends nothing, and a 1.1
// host gets every reading as sampled. A host reads a repeat within the band as no evidence of a
// stuck sensor, and its readings as up to `counts` stale.
struct SensorDeadband {
  std::uint8_t counts = 0;  // 0 (none) .. kSensorDeadbandMaxCounts
  bool operator==(const SensorDeadband&) const = default;
};
inline constexpr std::uint8_t kSensorDeadbandMaxCounts = 100;

using Message = std::variant<IdentifyRequest, Identity, ValveCurrents, CellTargets, Telemetry, TimeSync,
                             Status, Heartbeat, StateRequest, ConfigRead, ConfigData, ConfigWrite, ConfigAck,
                             UsbSlots, SensorDeadband>;

MRSKIN_PROTOCOL_API MessageType type_of(const Message& m) noexcept;

}  // namespace mrskin::protocol
