// A session with one device: handshake at construction (throws on failure), then
// allocation-free, non-throwing calls for the tick: poll(), send_valve_currents().
// The session mirrors the device's operating state (DISABLED, ENABLED, PAUSED, FAULT),
// keeps a ring log of recent traffic that freezes on a fault, reconnects after an unplug
// with backoff, and counts everything that went wrong.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/export.hpp"
#include "mrskin/driver/histogram.hpp"
#include "mrskin/driver/model/profile.hpp"
#include "mrskin/driver/transport.hpp"
#include "mrskin/protocol/messages.hpp"
#include "mrskin/protocol/packet.hpp"
#include "mrskin/protocol/units.hpp"
#include "mrskin/protocol/usb.hpp"

namespace mrskin {

enum class DeviceState : std::uint8_t { disabled = 0, enabled = 1, paused = 2, fault = 3 };
MRSKIN_DRIVER_API const char* to_string(DeviceState s) noexcept;
MRSKIN_DRIVER_API const char* fault_name(std::uint8_t fault_code) noexcept;

// What the device said about itself, in SI units, plus its configuration memory.
struct DeviceInfo {
  int protocol_major = 0;
  int protocol_minor = 0;
  std::string firmware;  // "MAJOR.MINOR.PATCH"
  std::uint32_t serial = 0;
  int rows = 0;
  int cols = 0;
  std::size_t fluid_cells = 0;
  std::size_t valves = 0;
  std::size_t sensors = 0;
  double current_lsb_A = 0.0;
  double max_current_A = 0.0;
  double sensor_lsb = 0.0;      // in the sensor's SI unit
  std::string sensor_quantity;  // "displacement", "force" or "pressure"
  std::string sensor_unit;      // "m", "N" or "Pa"
  double heartbeat_timeout_s = 0.0;
  double telemetry_rate_hz = 0.0;
  // Protocol 1.2, USB: the reports the unit declared (UsbSlots), which this session packs up to;
  // nullopt until it does (and from a 1.1 unit): full speed, 64-byte reports, is assumed.
  std::optional<protocol::UsbInterruptSlots> usb_slots;
  // Protocol 1.2: the unit's declared sensor deadband (SensorDeadband), in sensor counts (each
  // sensor_lsb); 0 when it declared none (and from a 1.1 unit). A reading may be this stale.
  int sensor_deadband_counts = 0;
  std::string profile;      // profile text stored on the device (DeviceSession::profile() parses it)
  std::string calibration;  // calibration text stored on the device (versioned)
};

struct SessionOptions {
  // Multiplies every timeout below (handshake, heartbeat period, reconnect backoff):
  // raise it in slow environments such as a VM. open_device() also reads
  // MRSKIN_TIME_SCALE from the environment.
  double time_scale = 1.0;
  Duration handshake_timeout = std::chrono::milliseconds(500);
  Duration handshake_retry = std::chrono::milliseconds(50);
  Duration heartbeat_period = std::chrono::milliseconds(20);
  Duration reconnect_backoff_min = std::chrono::milliseconds(10);
  Duration reconnect_backoff_max = std::chrono::milliseconds(1000);
  Duration telemetry_timeout = std::chrono::milliseconds(50);
  // Read profile and calibration during the handshake; the configuration read fails with
  // Timeout when no chunk arrives within handshake_timeout.
  bool read_configuration = true;
  // Protocol 1.2 on a bus whose every slot carries a sample (full-speed USB at 1 kHz): read the
  // configuration in chunks that fit beside a sample (14 bytes for the 5x5), which displace no
  // sample but take one sample each: about 0.3 s at 1 kHz, and as long as a lagging unit (a
  // simulation on a loaded machine: seconds) takes to send them. Off: full 48-byte chunks in
  // reports of their own, each taking a sample's slot.
  bool config_reads_beside_telemetry = true;
  std::size_t ring_log_packets = 256;  // N of the ring log (1..65536)
  // The protocol minor version this host declares in its IdentifyRequest, 0..kVersionMinor:
  // 1 makes it a 1.1 host (no packed reports either way), for tests against older peers.
  std::uint8_t protocol_minor = protocol::kVersionMinor;
};

// Counters the session keeps; read from the tick thread or after it stops.
struct SessionCounters {
  std::uint64_t sent = 0;  // packets
  std::uint64_t send_would_block = 0;
  std::uint64_t received = 0;
  std::uint64_t telemetry = 0;
  std::uint64_t crc_errors = 0;
  std::uint64_t decode_errors = 0;  // all decode failures, CRC included
  std::uint64_t sequence_gaps = 0;
  std::uint64_t duplicates = 0;  // same sequence number twice in a row
  std::uint64_t heartbeats = 0;
  std::uint64_t invalid_commands = 0;
  std::uint64_t telemetry_timeouts = 0;
  std::uint64_t disconnects = 0;
  std::uint64_t reconnects = 0;
  std::uint64_t faults = 0;
  std::uint64_t reseeds = 0;            // explicit enables that re-seeded the command state
  std::uint64_t state_retries = 0;      // state requests sent again: no status confirmed them
  std::uint64_t identity_changes = 0;   // another unit answered a reconnect: refused
  std::uint64_t reports_sent = 0;       // datagrams (HID reports, CAN FD frames) that carried them
  std::uint64_t reports_received = 0;   // ... and that brought the received packets
  DurationHistogram round_trip;         // heartbeat sent -> its echo received
  std::int64_t last_round_trip_ns = 0;  // the latest of those, ns
};

// One packet's bytes in the ring log (a packet is at most 64 bytes, whatever the report that
// carried it); a report that did not decode keeps its first 64 bytes.
struct LoggedPacket {
  std::array<std::uint8_t, protocol::kPacketMaxBytes> bytes{};
  std::uint8_t length = 0;
};

// One packet in the ring log, as it crossed the link.
struct TrafficRecord {
  TimePoint time{};
  bool sent = false;  // host -> device
  LoggedPacket packet{};
};

// A ring-log record decoded into SI units with the device's identity (DeviceSession::decode_log).
struct LogEntry {
  TimePoint host_time{};
  bool sent = false;  // host -> device
  // "currents", "targets", "telemetry", "status", "heartbeat", "state request", "identify",
  // "identity", "config read", "config data", "config write", "config ack", "time sync",
  // or "undecodable"
  std::string_view kind = "undecodable";
  int sequence = -1;       // packet sequence number (-1: undecodable)
  std::string_view error;  // decode error ("" when the packet decoded)
  bool has_device_time = false;
  std::uint32_t device_time_us = 0;  // telemetry: device clock at sampling
  std::size_t first = 0;             // first valve (currents), cell (targets) or sensor (telemetry)
  std::vector<double> values;        // currents in A, or sensor readings in unit
  std::string_view unit;             // "A", or the sensors' SI unit
  std::vector<protocol::CellTargetSi> targets;
  std::string_view state;  // status: "DISABLED", "ENABLED", "PAUSED", "FAULT"; state request: the request
  std::string_view fault;  // status: the fault cause ("none", "heartbeat lost", ...)
  std::string detail;      // anything else, in words (flags, heartbeat counter, config key and range)
};

// The re-seeding rule of an explicit enable (docs/api.md, "Enabling re-seeds the targets"),
// shared by the session and the mock device's firmware. The fluid cells' measured displacements
// are the non-negative least-squares fit of every displacement sensor (one on a cell reads that
// cell; one under a valve reads the mean of the cells it joins): a finger only pushes, which is
// what makes 12 valve readings determine 13 cells for a press on one or a few cells (the cell
// observer's rule, without its prior). A cell's measured force is the mean of the force sensors
// on that cell, or else 0. The seeded target is offset = measured displacement, stiffness 0,
// ceiling = measured force, and the validity given. Built at setup (allocates); the rest is
// noexcept and allocation-free (one instance per thread: the fit uses the seeder's scratch).
class MRSKIN_DRIVER_API TargetSeeder {
 public:
  TargetSeeder() = default;
  explicit TargetSeeder(const model::DeviceProfile& profile);
  [[nodiscard]] std::size_t fluid_cells() const noexcept { return fit_m_.size(); }
  [[nodiscard]] double displacement_m(std::size_t cell, std::span<const double> sensors) const noexcept;
  [[nodiscard]] double force_N(std::size_t cell, std::span<const double> sensors) const noexcept;
  [[nodiscard]] protocol::CellTarget seed(std::size_t cell, std::span<const double> sensors,
                                          std::uint8_t validity_counts) const noexcept;
  // For a loop over the cells: fit once, then read each cell from that fit. displacement_m() and
  // seed() fit anew on every call, which on the 2048 cells of palm-64x64 made one enable cost
  // about 39 s (every cell a whole fit: issue 21).
  void fit_displacements(std::span<const double> sensors) const noexcept;
  [[nodiscard]] double fitted_displacement_m(std::size_t cell) const noexcept;
  [[nodiscard]] protocol::CellTarget seed_from_fit(std::size_t cell, std::span<const double> sensors,
                                                   std::uint8_t validity_counts) const noexcept;

 private:
  struct Term {
    std::size_t sensor = 0;  // or row, or cell (see the vector it is in)
    double weight = 0.0;
  };
  static double sum(std::span<const Term> terms, std::span<const double> sensors) noexcept;
  void fit(std::span<const double> sensors) const noexcept;
  std::vector<std::size_t> row_sensor_;  // displacement sensor of each fit row
  std::vector<std::size_t> cell_begin_;  // cells + 1 offsets into cell_rows_
  std::vector<Term> cell_rows_;          // the rows reading a cell, with their weights
  std::vector<double> cell_norm2_;
  mutable std::vector<double> fit_m_;       // scratch: the last fit, per cell
  mutable std::vector<double> residual_m_;  // scratch: per row
  std::vector<std::size_t> force_begin_;
  std::vector<Term> force_;
};

// Called on the tick thread for every telemetry packet, inside poll(); must not block. A poll()
// from inside it reads nothing and returns would_block (the packet it is handed is still in use).
struct TelemetryView {
  std::uint32_t device_time_us = 0;
  std::size_t first = 0;
  std::span<const double> values;  // SI
};
using TelemetryCallback = void (*)(void* context, const TelemetryView& view) noexcept;

class MRSKIN_DRIVER_API DeviceSession {
 public:
  // Runs the handshake on transport. Throws ProtocolMismatch (both versions named),
  // Timeout, DeviceNotFound when the transport is down, or InvalidArgument when the profile
  // stored on the device is invalid or disagrees with its identity.
  DeviceSession(std::unique_ptr<Transport> transport, Clock& clock, SessionOptions options = {});
  DeviceSession(const DeviceSession&) = delete;
  DeviceSession& operator=(const DeviceSession&) = delete;
  DeviceSession(DeviceSession&&) = delete;
  DeviceSession& operator=(DeviceSession&&) = delete;
  ~DeviceSession();

  [[nodiscard]] const DeviceInfo& info() const noexcept;
  // The profile read from the device, parsed (nullptr with read_configuration = false).
  [[nodiscard]] const model::DeviceProfile* profile() const noexcept;
  void set_telemetry_callback(TelemetryCallback callback, void* context) noexcept;

  // --- real-time path: no allocation, no exceptions, no blocking -----------------------
  // Drains received packets, sends the heartbeat when due, reconnects after an unplug.
  // Returns disconnected while the link is down, device_fault while the device is in FAULT,
  // would_block when called from inside the telemetry callback (nothing is read).
  ResultCode poll(TimePoint now) noexcept;
  // Per-valve coil currents, A. Refuses NaN/Inf/out-of-range with invalid_value and sends
  // nothing in that case.
  ResultCode send_valve_currents(std::span<const double> current_A) noexcept;
  // The same command for a host that commands every tick, with less on the bus: the valves go in
  // blocks of protocol::kMaxValveCurrents, and a block goes only when its counts differ from those
  // last sent in it, or when it went unsent for refresh_period (the cure for a lost frame; the
  // unit's watchdog runs on the heartbeat). At most max_refresh such refreshes go per call, taken
  // in turn, so refreshing a large grid spreads over the ticks. Every block goes on the first
  // command, after a reconnect and after a failed send. Refuses as send_valve_currents.
  ResultCode send_valve_current_changes(std::span<const double> current_A, TimePoint now,
                                        Duration refresh_period, std::size_t max_refresh) noexcept;
  // The refresh of send_valve_current_changes alone, for a tick whose currents equal the last
  // command's (nothing is quantised or compared again). Nothing goes before the first command.
  ResultCode refresh_valve_currents(TimePoint now, Duration refresh_period, std::size_t max_refresh) noexcept;
  // When the block sent longest ago falls due for its refresh (TimePoint::min() while every block
  // is due): a host whose currents did not change need not call before then.
  [[nodiscard]] TimePoint valve_refresh_due(Duration refresh_period) const noexcept;
  // The blocks the valves go in: ceil(valves / protocol::kMaxValveCurrents).
  [[nodiscard]] std::size_t valve_current_blocks() const noexcept;
  // Per-cell impedance targets (wire counts; see protocol/units.hpp for SI conversion).
  ResultCode send_cell_targets(std::uint16_t first_cell,
                               std::span<const protocol::CellTarget> targets) noexcept;
  // Leaves DISABLED, PAUSED or a latched FAULT, and re-seeds the command state from the
  // measured state (docs/api.md): the valve currents become 0 A, the targets of the cells the
  // host has targeted become TargetSeeder::seed() of the latest telemetry, and both are sent
  // right after the state request, so no stale command is resumed. The firmware does the same.
  // Each request_*() state request is repeated every handshake_retry (at most 10 times) until
  // a status confirms the state, or a new FAULT overrides it: a lossy link cannot eat an enable.
  ResultCode request_enable() noexcept;
  ResultCode request_disable() noexcept;
  ResultCode request_pause() noexcept;
  ResultCode request_estop() noexcept;
  // Protocol 1.1: asks a disabled device to degauss its cores with a decaying alternating
  // current (bipolar coil drivers only); degaussing() is true while it runs.
  ResultCode request_degauss() noexcept;
  // Stops heartbeats (used to test the device's watchdog).
  void suppress_heartbeat(bool suppress) noexcept;

  // Latest sensor values in SI, one per sensor, and their device timestamp.
  [[nodiscard]] std::span<const double> sensors() const noexcept;
  [[nodiscard]] std::uint32_t sensor_device_time_us() const noexcept;
  // The command state as last sent (or re-seeded): per-valve currents in A, per-cell targets.
  [[nodiscard]] std::span<const double> commanded_currents() const noexcept;
  [[nodiscard]] std::span<const protocol::CellTarget> cell_targets() const noexcept;
  [[nodiscard]] const TargetSeeder& seeder() const noexcept;
  [[nodiscard]] TimePoint last_telemetry_time() const noexcept;
  [[nodiscard]] DeviceState state() const noexcept;
  [[nodiscard]] std::uint8_t fault_code() const noexcept;
  [[nodiscard]] bool valves_released() const noexcept;
  [[nodiscard]] bool derated() const noexcept;
  // The transport underneath, for a host that lends its device to another session
  // (mrskin-bridged's lease): only while nothing polls or sends through this session.
  [[nodiscard]] Transport& transport() noexcept;
  // Protocol 1.1: a degauss cycle is running (request_degauss), per the device's last Status.
  [[nodiscard]] bool degaussing() const noexcept;
  [[nodiscard]] bool connected() const noexcept;
  // Protocol 1.2: host and device both declared 1.2, so each report (HID report, CAN FD frame)
  // carries several packets: the heartbeat rides with the valve currents (docs/protocol.md).
  [[nodiscard]] bool packed_reports() const noexcept;
  [[nodiscard]] const SessionCounters& counters() const noexcept;
  [[nodiscard]] TransportState transport_state() const noexcept;

  // --- off the tick thread -------------------------------------------------------------
  // Writes the calibration into the device's configuration memory and reads it back
  // (info().calibration then holds it). Call between ticks, like the constructor: blocks up
  // to handshake_timeout without progress. The device takes it only while not ENABLED and
  // only with a "version = N" line above the stored calibration's. Throws InvalidArgument
  // (too long, version not above the stored one), Error (device ENABLED or refusing),
  // Timeout, DeviceNotFound (link down).
  void write_calibration(std::string_view text);

  // The last N packets, oldest first (allocates).
  [[nodiscard]] std::vector<TrafficRecord> ring_log() const;
  // The ring log as it was when the last fault arrived (empty if none).
  [[nodiscard]] std::vector<TrafficRecord> fault_log() const;
  // When the last fault arrived, and its cause (fault code; 0 if none so far).
  [[nodiscard]] TimePoint last_fault_time() const noexcept;
  [[nodiscard]] std::uint8_t last_fault_code() const noexcept;
  // Records decoded into SI units with this device's identity (allocates).
  [[nodiscard]] std::vector<LogEntry> decode_log(const std::vector<TrafficRecord>& records) const;
  // Human-readable dump, one record per line: host time, direction, kind, device time,
  // currents in A, sensor readings in their unit, targets, state and fault cause (allocates).
  [[nodiscard]] std::string format_log(const std::vector<TrafficRecord>& records) const;
  // The last fault (cause, time, state now) followed by format_log(fault_log()); "" if no fault.
  [[nodiscard]] std::string fault_report() const;

 private:
  // Everything else lives behind one pointer (driver/src/session_impl.hpp): a console linked
  // against this header keeps its ABI when the session's state changes (docs/api.md, "ABI").
  class Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace mrskin
