// A session with one device: handshake at construction (throws on failure), then
// allocation-free, non-throwing calls for the tick: poll(), send_valve_currents().
#pragma once

#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/transport.hpp"
#include "mrskin/protocol/messages.hpp"

namespace mrskin {

enum class DeviceState : std::uint8_t { disabled = 0, enabled = 1, paused = 2, fault = 3 };
const char* to_string(DeviceState s) noexcept;
const char* fault_name(std::uint8_t fault_code) noexcept;

// What the device said about itself, in SI units.
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
  double sensor_lsb = 0.0;  // in the sensor's SI unit
  double heartbeat_timeout_s = 0.0;
  double telemetry_rate_hz = 0.0;
};

struct SessionOptions {
  Duration handshake_timeout = std::chrono::milliseconds(500);
  Duration heartbeat_period = std::chrono::milliseconds(20);
};

// Counters the session keeps; read from the tick thread or after it stops.
struct SessionCounters {
  std::uint64_t sent = 0;
  std::uint64_t send_would_block = 0;
  std::uint64_t received = 0;
  std::uint64_t telemetry = 0;
  std::uint64_t decode_errors = 0;
  std::uint64_t sequence_gaps = 0;
  std::uint64_t heartbeats = 0;
  std::uint64_t invalid_commands = 0;
};

class DeviceSession {
 public:
  // Runs the handshake on transport. Throws ProtocolMismatch (both versions named),
  // Timeout, or DeviceNotFound when the transport is down.
  DeviceSession(std::unique_ptr<Transport> transport, Clock& clock, SessionOptions options = {});
  DeviceSession(const DeviceSession&) = delete;
  DeviceSession& operator=(const DeviceSession&) = delete;
  DeviceSession(DeviceSession&&) = delete;
  DeviceSession& operator=(DeviceSession&&) = delete;
  ~DeviceSession();

  [[nodiscard]] const DeviceInfo& info() const noexcept { return info_; }

  // --- real-time path: no allocation, no exceptions, no blocking -----------------------
  // Drains received packets and sends the heartbeat when due.
  ResultCode poll(TimePoint now) noexcept;
  // Per-valve coil currents, A. Refuses NaN/Inf/out-of-range with invalid_value and sends
  // nothing in that case.
  ResultCode send_valve_currents(std::span<const double> current_A) noexcept;
  ResultCode request_enable() noexcept;
  ResultCode request_disable() noexcept;
  ResultCode request_estop() noexcept;
  // Stops heartbeats (used to test the device's watchdog).
  void suppress_heartbeat(bool suppress) noexcept { suppress_heartbeat_ = suppress; }

  // Latest sensor values in SI, one per sensor, and their device timestamp.
  [[nodiscard]] std::span<const double> sensors() const noexcept { return sensors_; }
  [[nodiscard]] std::uint32_t sensor_device_time_us() const noexcept { return sensor_time_us_; }
  [[nodiscard]] DeviceState state() const noexcept { return state_; }
  [[nodiscard]] std::uint8_t fault_code() const noexcept { return fault_; }
  [[nodiscard]] bool valves_released() const noexcept { return valves_released_; }
  [[nodiscard]] const SessionCounters& counters() const noexcept { return counters_; }
  [[nodiscard]] TransportState transport_state() const noexcept { return transport_->state(); }

 private:
  ResultCode send_packet(const protocol::Message& message) noexcept;
  void handle(const Datagram& d) noexcept;

  std::unique_ptr<Transport> transport_;
  Clock& clock_;
  SessionOptions options_;
  DeviceInfo info_;
  std::vector<double> sensors_;
  std::vector<std::uint16_t> current_counts_;
  std::uint32_t sensor_time_us_ = 0;
  DeviceState state_ = DeviceState::disabled;
  std::uint8_t fault_ = 0;
  bool valves_released_ = true;
  bool suppress_heartbeat_ = false;
  TimePoint next_heartbeat_{};
  std::uint16_t heartbeat_counter_ = 0;
  std::uint8_t tx_sequence_ = 0;
  int rx_last_sequence_ = -1;
  SessionCounters counters_;
  std::uint32_t current_lsb_nA_ = 0;
  std::uint16_t current_max_counts_ = 0;
  double sensor_lsb_ = 0.0;
};

}  // namespace mrskin
