// DeviceSession's state and protocol logic behind its one pointer (session.hpp). Private to the
// driver: session.cpp holds the handshake and the real-time path, session_log.cpp the traffic
// log and its reports.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "mrskin/driver/session.hpp"
#include "mrskin/protocol/messages.hpp"
#include "mrskin/protocol/packet.hpp"

namespace mrskin {

class __attribute__((visibility("hidden"))) DeviceSession::Impl {
 public:
  // The public functions, as documented in session.hpp (they forward here).
  Impl(std::unique_ptr<Transport> transport, Clock& clock, SessionOptions options);
  Impl(const Impl&) = delete;
  Impl& operator=(const Impl&) = delete;
  Impl(Impl&&) = delete;
  Impl& operator=(Impl&&) = delete;
  ~Impl();
  [[nodiscard]] const DeviceInfo& info() const noexcept { return info_; }
  [[nodiscard]] const model::DeviceProfile* profile() const noexcept { return profile_.get(); }
  void set_telemetry_callback(TelemetryCallback callback, void* context) noexcept {
    telemetry_callback_ = callback;
    telemetry_context_ = context;
  }
  // The tick's calls: inlined into the public functions, so the pointer costs no call.
  [[gnu::always_inline]] inline ResultCode poll(TimePoint now) noexcept;
  [[gnu::always_inline]] inline ResultCode send_valve_currents(std::span<const double> current_A) noexcept;
  [[gnu::always_inline]] inline ResultCode send_valve_current_changes(std::span<const double> current_A,
                                                                      TimePoint now, Duration refresh_period,
                                                                      std::size_t max_refresh) noexcept;
  [[gnu::always_inline]] inline ResultCode refresh_valve_currents(TimePoint now, Duration refresh_period,
                                                                  std::size_t max_refresh) noexcept;
  [[nodiscard]] TimePoint valve_refresh_due(Duration refresh_period) const noexcept {
    return all_blocks_due_ ? TimePoint::min() : oldest_block_sent_ + refresh_period;
  }
  [[nodiscard]] std::size_t valve_current_blocks() const noexcept { return block_sent_.size(); }
  ResultCode send_cell_targets(std::uint16_t first_cell,
                               std::span<const protocol::CellTarget> targets) noexcept;
  ResultCode request_enable() noexcept;
  ResultCode request_disable() noexcept;
  ResultCode request_pause() noexcept;
  ResultCode request_estop() noexcept;
  ResultCode request_degauss() noexcept;
  void suppress_heartbeat(bool suppress) noexcept { suppress_heartbeat_ = suppress; }
  [[nodiscard]] std::span<const double> sensors() const noexcept { return sensors_; }
  [[nodiscard]] std::uint32_t sensor_device_time_us() const noexcept { return sensor_time_us_; }
  [[nodiscard]] std::span<const double> commanded_currents() const noexcept { return commanded_A_; }
  [[nodiscard]] std::span<const protocol::CellTarget> cell_targets() const noexcept { return targets_; }
  [[nodiscard]] const TargetSeeder& seeder() const noexcept { return seeder_; }
  [[nodiscard]] TimePoint last_telemetry_time() const noexcept { return last_telemetry_; }
  [[nodiscard]] DeviceState state() const noexcept { return state_; }
  [[nodiscard]] std::uint8_t fault_code() const noexcept { return fault_; }
  [[nodiscard]] bool valves_released() const noexcept { return valves_released_; }
  [[nodiscard]] bool derated() const noexcept { return derated_; }
  [[nodiscard]] Transport& transport() noexcept { return *transport_; }
  [[nodiscard]] bool degaussing() const noexcept { return degaussing_; }
  [[nodiscard]] bool connected() const noexcept { return connected_; }
  [[nodiscard]] bool packed_reports() const noexcept { return packing_; }
  [[nodiscard]] const SessionCounters& counters() const noexcept { return counters_; }
  [[nodiscard]] TransportState transport_state() const noexcept { return transport_->state(); }
  void write_calibration(std::string_view text);
  [[nodiscard]] std::vector<TrafficRecord> ring_log() const;
  [[nodiscard]] std::vector<TrafficRecord> fault_log() const;
  [[nodiscard]] TimePoint last_fault_time() const noexcept { return last_fault_time_; }
  [[nodiscard]] std::uint8_t last_fault_code() const noexcept { return last_fault_code_; }
  [[nodiscard]] std::vector<LogEntry> decode_log(const std::vector<TrafficRecord>& records) const;
  [[nodiscard]] std::string format_log(const std::vector<TrafficRecord>& records) const;
  [[nodiscard]] std::string fault_report() const;

 private:
  // Sends message as one packet. With packed reports agreed, it joins the report being filled
  // (sent first when the packet does not fit), which goes out now unless hold: then the next
  // send_packet() without hold, flush_report() or the next poll() sends it.
  ResultCode send_packet(const protocol::Message& message, bool hold = false) noexcept;
  ResultCode flush_report() noexcept;
  void drop_report() noexcept;
  void handle(const Datagram& d, TimePoint now) noexcept;
  // The packets of a 1.2 report (or of its part after a reconnect's Identity), in order.
  void handle_packed(std::span<const std::uint8_t> bytes, TimePoint now) noexcept;
  void handle_packet(const protocol::PacketDecoded& p, TimePoint now) noexcept;
  void log(std::span<const std::uint8_t> bytes, bool sent, TimePoint now) noexcept;
  void log(const Datagram& d, bool sent, TimePoint now) noexcept {
    log(std::span<const std::uint8_t>(d.bytes.data(), d.length), sent, now);
  }
  void apply_identity(const protocol::Identity& id);
  void apply_usb_slots(const protocol::UsbSlots& declared) noexcept;
  [[nodiscard]] bool same_unit(const protocol::Identity& id) const noexcept;
  std::string read_config(protocol::ConfigKey key);
  // The bytes a configuration read asks for at a time: docs/protocol.md, "Configuration reads
  // beside the telemetry".
  [[nodiscard]] std::size_t config_chunk_bytes() const;
  [[nodiscard]] std::size_t config_window() const;  // configuration chunks in flight
  void await_config_ack(std::uint16_t offset);
  ResultCode send_state_request(protocol::StateRequestCode request) noexcept;
  void await_identity(TimePoint deadline);
  void load_profile();
  void reseed_and_send() noexcept;
  // Quantises the blocks of current_A that differ bitwise from the last command (every block when
  // quantised_valid_ is false), all before any is kept, so a refused command changes nothing;
  // block_go_[b] = 2 for each block whose counts changed, else 0.
  [[gnu::always_inline]] inline ResultCode quantise_changed_blocks(
      std::span<const double> current_A) noexcept;
  // Marks for sending (block_go_ = 2) up to max_refresh blocks unsent for refresh_period.
  [[gnu::always_inline]] inline void select_refresh(TimePoint now, Duration refresh_period,
                                                    std::size_t max_refresh) noexcept;
  // Sends the blocks with block_go_ set, in order, held in the report; records what went.
  [[gnu::always_inline]] inline ResultCode send_blocks(TimePoint now) noexcept;

  std::unique_ptr<Transport> transport_;
  Clock& clock_;
  SessionOptions options_;
  DeviceInfo info_;
  protocol::Identity identity_{};
  std::unique_ptr<model::DeviceProfile> profile_;
  TargetSeeder seeder_;
  std::vector<double> sensors_;
  Datagram rx_datagram_;  // poll's receive buffer...
  bool polling_ = false;  // ...in use: poll() is running (its telemetry callback may not re-enter)
  struct ClearOnExit {    // poll's: polling_ false again on every return
    explicit ClearOnExit(bool& flag) noexcept : flag_(flag) {}
    ~ClearOnExit() { flag_ = false; }
    ClearOnExit(const ClearOnExit&) = delete;
    ClearOnExit& operator=(const ClearOnExit&) = delete;
    ClearOnExit(ClearOnExit&&) = delete;
    ClearOnExit& operator=(ClearOnExit&&) = delete;

   private:
    bool& flag_;
  };
  std::vector<std::uint16_t> current_counts_;
  std::vector<std::uint16_t> pending_counts_;  // send_valve_currents: all quantised before any is kept
  std::vector<double> commanded_A_;
  std::vector<double> quantised_A_;  // the currents current_counts_ were quantised from, bitwise...
  bool quantised_valid_ = false;     // ...while they still are (a reseed or a new scale: no)
  bool currents_commanded_ = false;  // the host has sent currents since the handshake
  // The valves go in blocks of kMaxValveCurrents: per block when it was last sent.
  std::vector<TimePoint> block_sent_;
  std::vector<std::uint8_t> block_go_;  // per block, this send: 2 goes
  TimePoint oldest_block_sent_{};
  std::size_t refresh_cursor_ = 0;            // the block the next refresh looks at first
  bool all_blocks_due_ = true;                // the unit's currents are unknown: every block goes next
  bool counts_changed_since_reseed_ = false;  // some count may be non-zero since the last reseed
  std::vector<protocol::CellTarget> targets_;
  std::vector<std::uint8_t> targeted_;  // per cell: the host has targeted it
  std::uint32_t sensor_time_us_ = 0;
  TimePoint last_telemetry_{};
  bool telemetry_timed_out_ = false;
  DeviceState state_ = DeviceState::disabled;
  DeviceState wanted_state_ = DeviceState::disabled;
  std::uint8_t fault_ = 0;
  bool valves_released_ = true;
  bool degaussing_ = false;
  bool derated_ = false;
  bool suppress_heartbeat_ = false;
  bool state_request_pending_ = false;
  std::uint8_t pending_request_ = 0;
  int state_retries_left_ = 0;
  TimePoint next_state_retry_{};
  bool connected_ = true;
  bool identify_pending_ = false;
  TimePoint next_reconnect_{};
  Duration backoff_{};
  TimePoint next_heartbeat_{};
  std::uint16_t heartbeat_counter_ = 0;
  std::array<TimePoint, 64> heartbeat_sent_{};
  std::uint8_t tx_sequence_ = 0;
  // Protocol 1.2 packed reports: agreed when the device's Identity says 1.2 and this host is 1.2.
  bool packing_ = false;
  std::array<std::uint8_t, kMaxDatagramBytes> report_{};
  // The bytes of report_ a report may use: 64 (full speed) until the unit declares more (UsbSlots).
  std::size_t report_capacity_ = protocol::kHidReportBytes;
  std::size_t report_used_ = 0;
  std::size_t report_packets_ = 0;
  // Where each packet of the report ends (a packet has at least a header and a CRC).
  std::array<std::uint16_t, kMaxDatagramBytes / (protocol::kPacketHeaderBytes + protocol::kPacketCrcBytes)>
      report_ends_{};
  int rx_last_sequence_ = -1;
  SessionCounters counters_;
  std::uint32_t current_lsb_nA_ = 0;
  std::uint16_t current_max_counts_ = 0;
  double sensor_lsb_ = 0.0;
  TelemetryCallback telemetry_callback_ = nullptr;
  void* telemetry_context_ = nullptr;
  std::vector<TrafficRecord> ring_;
  std::size_t ring_next_ = 0;
  std::size_t ring_size_ = 0;
  std::vector<TrafficRecord> fault_ring_;
  std::size_t fault_ring_size_ = 0;
  std::size_t fault_ring_next_ = 0;
  TimePoint last_fault_time_{};
  std::uint8_t last_fault_code_ = 0;
  // The configuration blob being read at setup (chunks may arrive in any order).
  struct ConfigTransfer {
    bool active = false;
    std::uint16_t key = 0;
    std::size_t chunk = protocol::kMaxConfigBytes;  // bytes a read asks for (config_chunk_bytes)
    int total = -1;                                 // unknown until the first chunk
    std::string text;
    std::vector<std::uint8_t> have;  // per chunk
    std::size_t received = 0;
    bool progress = false;
    bool acked = false;  // a ConfigAck for key arrived
    std::uint16_t ack_offset = 0;
    std::uint8_t ack_status = 0;
  };
  ConfigTransfer config_;
};

}  // namespace mrskin
