#include "mrskin/driver/session.hpp"

#include <algorithm>
#include <cmath>
#include <string>

#include "mrskin/protocol/packet.hpp"
#include "mrskin/protocol/units.hpp"

namespace mrskin {
namespace proto = mrskin::protocol;

const char* to_string(DeviceState s) noexcept {
  switch (s) {
    case DeviceState::disabled:
      return "DISABLED";
    case DeviceState::enabled:
      return "ENABLED";
    case DeviceState::paused:
      return "PAUSED";
    case DeviceState::fault:
      return "FAULT";
  }
  return "UNKNOWN";
}

const char* fault_name(std::uint8_t fault_code) noexcept {
  switch (static_cast<proto::FaultCode>(fault_code)) {
    case proto::FaultCode::none:
      return "none";
    case proto::FaultCode::heartbeat_lost:
      return "heartbeat lost";
    case proto::FaultCode::overtemperature:
      return "coil overtemperature";
    case proto::FaultCode::overcurrent:
      return "overcurrent";
    case proto::FaultCode::sensor_fault:
      return "sensor fault";
    case proto::FaultCode::bus_off:
      return "bus off";
    case proto::FaultCode::estop:
      return "emergency stop";
    case proto::FaultCode::internal:
      return "internal error";
  }
  return "unknown fault";
}

DeviceSession::DeviceSession(std::unique_ptr<Transport> transport, Clock& clock, SessionOptions options)
    : transport_(std::move(transport)), clock_(clock), options_(options) {
  if (!transport_ || transport_->state() != TransportState::open) {
    throw DeviceNotFound(std::string("no device answers on ") +
                         (transport_ ? std::string(transport_->uri()) : std::string("(null transport)")) +
                         ": check the cable and the URI (mrskinctl list shows what is attached)");
  }
  if (send_packet(proto::IdentifyRequest{}) != ResultCode::ok) {
    throw DeviceNotFound(std::string("cannot send to ") + std::string(transport_->uri()) +
                         ": the link is down or its queue is full");
  }
  const TimePoint deadline = clock_.now() + options_.handshake_timeout;
  bool identified = false;
  while (!identified) {
    Datagram d;
    const ResultCode rc = transport_->receive(d);
    if (rc == ResultCode::ok) {
      const proto::PacketDecoded p =
          proto::decode_packet(std::span<const std::uint8_t>(d.bytes.data(), d.length));
      if (p.error == proto::Error::wrong_version) {
        throw ProtocolMismatch("device on " + std::string(transport_->uri()) + " speaks protocol v" +
                               std::to_string(p.peer_version) + ", this library speaks v" +
                               std::to_string(proto::kVersionMajor) +
                               ": update the device firmware or use a matching mrskin release");
      }
      if (p.error != proto::Error::ok) {
        ++counters_.decode_errors;
        continue;
      }
      if (const auto* id = std::get_if<proto::Identity>(&p.message)) {
        if (id->proto_major != proto::kVersionMajor) {
          throw ProtocolMismatch("device reports protocol v" + std::to_string(id->proto_major) + "." +
                                 std::to_string(id->proto_minor) + ", this library speaks v" +
                                 std::to_string(proto::kVersionMajor) + "." +
                                 std::to_string(proto::kVersionMinor) +
                                 ": update the device firmware or use a matching mrskin release");
        }
        info_.protocol_major = id->proto_major;
        info_.protocol_minor = id->proto_minor;
        info_.firmware = std::to_string(id->fw_major) + "." + std::to_string(id->fw_minor) + "." +
                         std::to_string(id->fw_patch);
        info_.serial = id->serial;
        info_.rows = id->rows;
        info_.cols = id->cols;
        info_.fluid_cells = id->fluid_cells;
        info_.valves = id->valves;
        info_.sensors = id->sensors;
        info_.current_lsb_A = static_cast<double>(id->current_lsb_nA) * 1e-9;
        info_.max_current_A = info_.current_lsb_A * id->current_max_counts;
        info_.sensor_lsb = static_cast<double>(id->sensor_lsb_nano) * 1e-9;
        info_.heartbeat_timeout_s = id->heartbeat_timeout_ms * 1e-3;
        info_.telemetry_rate_hz = id->telemetry_rate_hz;
        current_lsb_nA_ = id->current_lsb_nA;
        current_max_counts_ = id->current_max_counts;
        sensor_lsb_ = info_.sensor_lsb;
        identified = true;
      }
      continue;
    }
    if (rc == ResultCode::disconnected) {
      throw DeviceNotFound("device on " + std::string(transport_->uri()) +
                           " disconnected during the handshake");
    }
    if (clock_.now() >= deadline) {
      throw Timeout("device on " + std::string(transport_->uri()) + " did not identify within " +
                    std::to_string(to_seconds(options_.handshake_timeout)) +
                    " s: check power, firmware and that no other process owns it");
    }
    clock_.sleep_until(clock_.now() + std::chrono::microseconds(200));
  }
  sensors_.assign(info_.sensors, 0.0);
  current_counts_.assign(info_.valves, 0);
  next_heartbeat_ = clock_.now();
}

DeviceSession::~DeviceSession() {
  // Leave the unit safe: release valves; the device's watchdog covers a crash.
  (void)request_disable();
}

ResultCode DeviceSession::send_packet(const proto::Message& message) noexcept {
  Datagram d;
  const auto r = proto::encode_packet(message, tx_sequence_, d.bytes);
  if (r.error != proto::Error::ok) {
    ++counters_.invalid_commands;
    return ResultCode::invalid_value;
  }
  const ResultCode rc = transport_->send(std::span<const std::uint8_t>(d.bytes.data(), r.bytes));
  if (rc == ResultCode::ok) {
    ++tx_sequence_;
    ++counters_.sent;
  } else if (rc == ResultCode::would_block) {
    ++counters_.send_would_block;
  }
  return rc;
}

void DeviceSession::handle(const Datagram& d) noexcept {
  const proto::PacketDecoded p =
      proto::decode_packet(std::span<const std::uint8_t>(d.bytes.data(), d.length));
  if (p.error != proto::Error::ok) {
    ++counters_.decode_errors;
    return;
  }
  ++counters_.received;
  if (rx_last_sequence_ >= 0 && p.sequence != static_cast<std::uint8_t>(rx_last_sequence_ + 1)) {
    ++counters_.sequence_gaps;
  }
  rx_last_sequence_ = p.sequence;
  if (const auto* t = std::get_if<proto::Telemetry>(&p.message)) {
    ++counters_.telemetry;
    sensor_time_us_ = t->device_time_us;
    for (std::size_t i = 0; i < t->count; ++i) {
      const std::size_t s = t->first + i;
      if (s < sensors_.size()) {
        sensors_[s] = static_cast<double>(t->counts[i]) * sensor_lsb_;
      }
    }
  } else if (const auto* s = std::get_if<proto::Status>(&p.message)) {
    state_ = static_cast<DeviceState>(s->state);
    fault_ = s->fault;
    valves_released_ = (s->flags & proto::kFlagValvesReleased) != 0;
  }
}

ResultCode DeviceSession::poll(TimePoint now) noexcept {
  Datagram d;
  ResultCode rc = ResultCode::ok;
  for (;;) {
    rc = transport_->receive(d);
    if (rc != ResultCode::ok) {
      break;
    }
    handle(d);
  }
  if (rc == ResultCode::disconnected) {
    return rc;
  }
  if (!suppress_heartbeat_ && now >= next_heartbeat_) {
    next_heartbeat_ = now + options_.heartbeat_period;
    if (send_packet(proto::Heartbeat{heartbeat_counter_}) == ResultCode::ok) {
      ++heartbeat_counter_;
      ++counters_.heartbeats;
    }
  }
  return state_ == DeviceState::fault ? ResultCode::device_fault : ResultCode::ok;
}

ResultCode DeviceSession::send_valve_currents(std::span<const double> current_A) noexcept {
  if (current_A.size() != current_counts_.size()) {
    ++counters_.invalid_commands;
    return ResultCode::invalid_value;
  }
  proto::Identity scale;
  scale.current_lsb_nA = current_lsb_nA_;
  scale.current_max_counts = current_max_counts_;
  for (std::size_t v = 0; v < current_A.size(); ++v) {
    const auto q = proto::quantize_current(current_A[v], scale);
    if (q.error != proto::Error::ok) {
      ++counters_.invalid_commands;
      return ResultCode::invalid_value;
    }
    current_counts_[v] = q.counts;
  }
  for (std::size_t first = 0; first < current_counts_.size(); first += proto::kMaxValveCurrents) {
    proto::ValveCurrents m;
    m.first = static_cast<std::uint16_t>(first);
    m.count = static_cast<std::uint8_t>(std::min(proto::kMaxValveCurrents, current_counts_.size() - first));
    std::copy_n(current_counts_.begin() + static_cast<std::ptrdiff_t>(first), m.count, m.counts.begin());
    const ResultCode rc = send_packet(m);
    if (rc != ResultCode::ok) {
      return rc;
    }
  }
  return ResultCode::ok;
}

ResultCode DeviceSession::request_enable() noexcept {
  return send_packet(proto::StateRequest{static_cast<std::uint8_t>(proto::StateRequestCode::enable)});
}
ResultCode DeviceSession::request_disable() noexcept {
  return send_packet(proto::StateRequest{static_cast<std::uint8_t>(proto::StateRequestCode::disable)});
}
ResultCode DeviceSession::request_estop() noexcept {
  return send_packet(proto::StateRequest{static_cast<std::uint8_t>(proto::StateRequestCode::estop)});
}

}  // namespace mrskin
