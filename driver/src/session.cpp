#include "mrskin/driver/session.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <string>

#include "mrskin/protocol/packet.hpp"
#include "mrskin/protocol/units.hpp"

namespace mrskin {
namespace proto = mrskin::protocol;

namespace {
constexpr std::size_t kRingCapacity = 256;

Duration scaled(Duration d, double scale) noexcept {
  return Duration{static_cast<Duration::rep>(static_cast<double>(d.count()) * scale)};
}
}  // namespace

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
    : transport_(std::move(transport)),
      clock_(clock),
      options_(options),
      ring_(kRingCapacity),
      fault_ring_(kRingCapacity) {
  if (!(options_.time_scale >= 1.0 && options_.time_scale <= 1000.0)) {
    throw InvalidArgument(fmt::format("time scale {} is outside [1, 1000]", options_.time_scale));
  }
  options_.handshake_timeout = scaled(options_.handshake_timeout, options_.time_scale);
  options_.handshake_retry = scaled(options_.handshake_retry, options_.time_scale);
  options_.heartbeat_period = scaled(options_.heartbeat_period, options_.time_scale);
  options_.reconnect_backoff_min = scaled(options_.reconnect_backoff_min, options_.time_scale);
  options_.reconnect_backoff_max = scaled(options_.reconnect_backoff_max, options_.time_scale);
  options_.telemetry_timeout = scaled(options_.telemetry_timeout, options_.time_scale);
  if (!transport_ || transport_->state() != TransportState::open) {
    throw DeviceNotFound(fmt::format(
        "no device answers on {}: check the cable and the URI (mrskinctl list shows what is attached)",
        transport_ ? std::string(transport_->uri()) : std::string("(null transport)")));
  }
  const TimePoint deadline = clock_.now() + options_.handshake_timeout;
  await_identity(deadline);
  if (options_.read_configuration) {
    info_.profile = read_config(proto::ConfigKey::profile, deadline);
    info_.calibration = read_config(proto::ConfigKey::calibration, deadline);
  }
  sensors_.assign(info_.sensors, 0.0);
  current_counts_.assign(info_.valves, 0);
  next_heartbeat_ = clock_.now();
  last_telemetry_ = clock_.now();
}

DeviceSession::~DeviceSession() {
  // Leave the unit safe: release valves; the device's watchdog covers a crash.
  (void)request_disable();
}

void DeviceSession::apply_identity(const proto::Identity& id) {
  if (id.proto_major != proto::kVersionMajor) {
    throw ProtocolMismatch(fmt::format(
        "device on {} reports protocol v{}.{}, this library speaks v{}.{}: update the device firmware or use "
        "a "
        "matching mrskin release",
        transport_->uri(), id.proto_major, id.proto_minor, proto::kVersionMajor, proto::kVersionMinor));
  }
  info_.protocol_major = id.proto_major;
  info_.protocol_minor = id.proto_minor;
  info_.firmware = fmt::format("{}.{}.{}", id.fw_major, id.fw_minor, id.fw_patch);
  info_.serial = id.serial;
  info_.rows = id.rows;
  info_.cols = id.cols;
  info_.fluid_cells = id.fluid_cells;
  info_.valves = id.valves;
  info_.sensors = id.sensors;
  info_.current_lsb_A = static_cast<double>(id.current_lsb_nA) * 1e-9;
  info_.max_current_A = info_.current_lsb_A * id.current_max_counts;
  info_.sensor_lsb = static_cast<double>(id.sensor_lsb_nano) * 1e-9;
  info_.heartbeat_timeout_s = id.heartbeat_timeout_ms * 1e-3;
  info_.telemetry_rate_hz = id.telemetry_rate_hz;
  current_lsb_nA_ = id.current_lsb_nA;
  current_max_counts_ = id.current_max_counts;
  sensor_lsb_ = info_.sensor_lsb;
}

void DeviceSession::await_identity(TimePoint deadline) {
  TimePoint next_request = clock_.now();
  for (;;) {
    const TimePoint now = clock_.now();
    if (now >= next_request) {
      // Repeated, since a lossy link may eat the request or the answer.
      if (send_packet(proto::IdentifyRequest{}) == ResultCode::disconnected) {
        throw DeviceNotFound(
            fmt::format("device on {} disconnected during the handshake", transport_->uri()));
      }
      next_request = now + options_.handshake_retry;
    }
    Datagram d;
    const ResultCode rc = transport_->receive(d);
    if (rc == ResultCode::ok) {
      log(d, false, now);
      const proto::PacketDecoded p =
          proto::decode_packet(std::span<const std::uint8_t>(d.bytes.data(), d.length));
      if (p.error == proto::Error::wrong_version) {
        throw ProtocolMismatch(fmt::format(
            "device on {} speaks protocol v{}, this library speaks v{}: update the device firmware or use a "
            "matching mrskin release",
            transport_->uri(), p.peer_version, proto::kVersionMajor));
      }
      if (p.error != proto::Error::ok) {
        ++counters_.decode_errors;
        counters_.crc_errors += p.error == proto::Error::bad_crc ? 1U : 0U;
        continue;
      }
      if (const auto* id = std::get_if<proto::Identity>(&p.message)) {
        apply_identity(*id);
        return;
      }
      continue;
    }
    if (rc == ResultCode::disconnected) {
      throw DeviceNotFound(fmt::format("device on {} disconnected during the handshake", transport_->uri()));
    }
    if (now >= deadline) {
      throw Timeout(
          fmt::format("device on {} did not identify within {:.3f} s: check power, firmware and that no "
                      "other process owns it "
                      "(raise the time scale in slow environments)",
                      transport_->uri(), to_seconds(options_.handshake_timeout)));
    }
    clock_.sleep_until(now + std::chrono::microseconds(200));
  }
}

std::string DeviceSession::read_config(proto::ConfigKey key, TimePoint deadline) {
  std::string text;
  std::uint16_t offset = 0;
  for (;;) {
    proto::ConfigRead request;
    request.key = static_cast<std::uint16_t>(key);
    request.offset = offset;
    request.length = static_cast<std::uint8_t>(proto::kMaxConfigBytes);
    config_reply_ready_ = false;
    config_ack_ready_ = false;
    (void)send_packet(request);
    TimePoint retry = clock_.now() + options_.handshake_retry;
    while (!config_reply_ready_ && !config_ack_ready_) {
      const TimePoint now = clock_.now();
      Datagram d;
      if (transport_->receive(d) == ResultCode::ok) {
        handle(d, now);
        continue;
      }
      if (now >= deadline) {
        throw Timeout(fmt::format("device on {} did not return its configuration (key {}) in time",
                                  transport_->uri(), static_cast<int>(key)));
      }
      if (now >= retry) {
        (void)send_packet(request);
        retry = now + options_.handshake_retry;
      }
      clock_.sleep_until(now + std::chrono::microseconds(200));
    }
    if (config_ack_ready_) {
      throw Error(fmt::format("device on {} refused to read configuration key {} (status {})",
                              transport_->uri(), static_cast<int>(key), config_ack_.status));
    }
    if (config_reply_.key != request.key || config_reply_.offset != offset) {
      continue;  // a stale answer to an earlier retry
    }
    text.append(config_reply_.bytes.begin(), config_reply_.bytes.begin() + config_reply_.length);
    offset = static_cast<std::uint16_t>(offset + config_reply_.length);
    if (offset >= config_reply_.total || config_reply_.length == 0) {
      return text;
    }
  }
}

void DeviceSession::log(const Datagram& d, bool sent, TimePoint now) noexcept {
  TrafficRecord& r = ring_[ring_next_];
  r.time = now;
  r.sent = sent;
  r.datagram = d;
  ring_next_ = (ring_next_ + 1) % ring_.size();
  ring_size_ = std::min(ring_size_ + 1, ring_.size());
}

ResultCode DeviceSession::send_packet(const proto::Message& message) noexcept {
  Datagram d;
  const auto r = proto::encode_packet(message, tx_sequence_, d.bytes);
  if (r.error != proto::Error::ok) {
    ++counters_.invalid_commands;
    return ResultCode::invalid_value;
  }
  d.length = static_cast<std::uint8_t>(r.bytes);
  const ResultCode rc = transport_->send(std::span<const std::uint8_t>(d.bytes.data(), r.bytes));
  if (rc == ResultCode::ok) {
    ++tx_sequence_;
    ++counters_.sent;
    log(d, true, clock_.now());
  } else if (rc == ResultCode::would_block) {
    ++counters_.send_would_block;
  }
  return rc;
}

void DeviceSession::handle(const Datagram& d, TimePoint now) noexcept {
  log(d, false, now);
  const proto::PacketDecoded p =
      proto::decode_packet(std::span<const std::uint8_t>(d.bytes.data(), d.length));
  if (p.error != proto::Error::ok) {
    ++counters_.decode_errors;
    counters_.crc_errors += p.error == proto::Error::bad_crc ? 1U : 0U;
    return;
  }
  ++counters_.received;
  if (rx_last_sequence_ >= 0) {
    const auto expected = static_cast<std::uint8_t>(rx_last_sequence_ + 1);
    if (p.sequence == static_cast<std::uint8_t>(rx_last_sequence_)) {
      ++counters_.duplicates;
      return;  // a repeated packet carries nothing new
    }
    if (p.sequence != expected) {
      ++counters_.sequence_gaps;
    }
  }
  rx_last_sequence_ = p.sequence;
  if (const auto* t = std::get_if<proto::Telemetry>(&p.message)) {
    ++counters_.telemetry;
    sensor_time_us_ = t->device_time_us;
    last_telemetry_ = now;
    telemetry_timed_out_ = false;
    const std::size_t first = std::min<std::size_t>(t->first, sensors_.size());
    const std::size_t count = std::min<std::size_t>(t->count, sensors_.size() - first);
    for (std::size_t i = 0; i < count; ++i) {
      sensors_[first + i] = static_cast<double>(t->counts[i]) * sensor_lsb_;
    }
    if (telemetry_callback_ != nullptr && count > 0) {
      telemetry_callback_(
          telemetry_context_,
          TelemetryView{t->device_time_us, first, std::span<const double>(&sensors_[first], count)});
    }
  } else if (const auto* s = std::get_if<proto::Status>(&p.message)) {
    const auto state = static_cast<DeviceState>(s->state);
    if (state == DeviceState::fault && state_ != DeviceState::fault) {
      ++counters_.faults;
      fault_ring_ = ring_;  // same size: copies into the preallocated buffers
      fault_ring_size_ = ring_size_;
      fault_ring_next_ = ring_next_;
    }
    state_ = state;
    fault_ = s->fault;
    valves_released_ = (s->flags & proto::kFlagValvesReleased) != 0;
    derated_ = (s->flags & proto::kFlagDerated) != 0;
  } else if (const auto* h = std::get_if<proto::Heartbeat>(&p.message)) {
    const TimePoint sent = heartbeat_sent_[h->counter % heartbeat_sent_.size()];
    if (sent.count() != 0 && now >= sent) {
      counters_.round_trip.add((now - sent).count());
    }
  } else if (const auto* cd = std::get_if<proto::ConfigData>(&p.message)) {
    config_reply_ = *cd;
    config_reply_ready_ = true;
  } else if (const auto* ca = std::get_if<proto::ConfigAck>(&p.message)) {
    config_ack_ = *ca;
    config_ack_ready_ = true;
  } else if (const auto* id = std::get_if<proto::Identity>(&p.message)) {
    if (identify_pending_ && id->proto_major == proto::kVersionMajor) {
      identify_pending_ = false;
      connected_ = true;
      ++counters_.reconnects;
      backoff_ = Duration{0};
      rx_last_sequence_ = -1;
      // Keep the configuration: return to the state the host had asked for.
      if (wanted_state_ == DeviceState::enabled) {
        (void)request_enable();
      }
    }
  }
}

ResultCode DeviceSession::poll(TimePoint now) noexcept {
  if (transport_->state() != TransportState::open) {
    if (connected_) {
      connected_ = false;
      identify_pending_ = false;
      ++counters_.disconnects;
      backoff_ = options_.reconnect_backoff_min;
      next_reconnect_ = now + backoff_;
    }
    return ResultCode::disconnected;
  }
  if (!connected_) {
    // Link is back: identify again, with exponential backoff between attempts.
    if (now >= next_reconnect_) {
      identify_pending_ = true;
      rx_last_sequence_ = -1;
      (void)send_packet(proto::IdentifyRequest{});
      backoff_ = std::min(backoff_ * 2, options_.reconnect_backoff_max);
      next_reconnect_ = now + backoff_;
    }
  }
  Datagram d;
  for (;;) {
    const ResultCode rc = transport_->receive(d);
    if (rc != ResultCode::ok) {
      break;
    }
    handle(d, now);
  }
  if (!connected_) {
    return ResultCode::disconnected;
  }
  if (!telemetry_timed_out_ && now - last_telemetry_ > options_.telemetry_timeout) {
    telemetry_timed_out_ = true;
    ++counters_.telemetry_timeouts;
  }
  if (!suppress_heartbeat_ && now >= next_heartbeat_) {
    next_heartbeat_ = now + options_.heartbeat_period;
    heartbeat_sent_[heartbeat_counter_ % heartbeat_sent_.size()] = now;
    if (send_packet(proto::Heartbeat{heartbeat_counter_}) == ResultCode::ok) {
      ++counters_.heartbeats;
    }
    ++heartbeat_counter_;
  }
  return state_ == DeviceState::fault ? ResultCode::device_fault : ResultCode::ok;
}

ResultCode DeviceSession::send_valve_currents(std::span<const double> current_A) noexcept {
  if (current_A.size() != current_counts_.size()) {
    ++counters_.invalid_commands;
    return ResultCode::invalid_value;
  }
  if (!connected_) {
    return ResultCode::disconnected;
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

ResultCode DeviceSession::send_cell_targets(std::uint16_t first_cell,
                                            std::span<const proto::CellTarget> targets) noexcept {
  if (first_cell + targets.size() > info_.fluid_cells) {
    ++counters_.invalid_commands;
    return ResultCode::invalid_value;
  }
  for (std::size_t done = 0; done < targets.size(); done += proto::kMaxCellTargets) {
    proto::CellTargets m;
    m.first = static_cast<std::uint16_t>(first_cell + done);
    m.count = static_cast<std::uint8_t>(std::min(proto::kMaxCellTargets, targets.size() - done));
    std::copy_n(targets.begin() + static_cast<std::ptrdiff_t>(done), m.count, m.targets.begin());
    const ResultCode rc = send_packet(m);
    if (rc != ResultCode::ok) {
      return rc;
    }
  }
  return ResultCode::ok;
}

ResultCode DeviceSession::request_enable() noexcept {
  wanted_state_ = DeviceState::enabled;
  return send_packet(proto::StateRequest{static_cast<std::uint8_t>(proto::StateRequestCode::enable)});
}
ResultCode DeviceSession::request_disable() noexcept {
  wanted_state_ = DeviceState::disabled;
  return send_packet(proto::StateRequest{static_cast<std::uint8_t>(proto::StateRequestCode::disable)});
}
ResultCode DeviceSession::request_pause() noexcept {
  wanted_state_ = DeviceState::paused;
  return send_packet(proto::StateRequest{static_cast<std::uint8_t>(proto::StateRequestCode::pause)});
}
ResultCode DeviceSession::request_estop() noexcept {
  wanted_state_ = DeviceState::disabled;
  return send_packet(proto::StateRequest{static_cast<std::uint8_t>(proto::StateRequestCode::estop)});
}

std::vector<TrafficRecord> DeviceSession::ring_log() const {
  std::vector<TrafficRecord> out;
  out.reserve(ring_size_);
  const std::size_t start = (ring_next_ + ring_.size() - ring_size_) % ring_.size();
  for (std::size_t i = 0; i < ring_size_; ++i) {
    out.push_back(ring_[(start + i) % ring_.size()]);
  }
  return out;
}

std::vector<TrafficRecord> DeviceSession::fault_log() const {
  std::vector<TrafficRecord> out;
  out.reserve(fault_ring_size_);
  const std::size_t start = (fault_ring_next_ + fault_ring_.size() - fault_ring_size_) % fault_ring_.size();
  for (std::size_t i = 0; i < fault_ring_size_; ++i) {
    out.push_back(fault_ring_[(start + i) % fault_ring_.size()]);
  }
  return out;
}

std::string DeviceSession::format_log(const std::vector<TrafficRecord>& records) {
  std::string out;
  for (const TrafficRecord& r : records) {
    const proto::PacketDecoded p =
        proto::decode_packet(std::span<const std::uint8_t>(r.datagram.bytes.data(), r.datagram.length));
    out += fmt::format("{:14.6f} {} type 0x{:02x} seq {:3} {}:", to_seconds(r.time), r.sent ? "tx" : "rx",
                       r.datagram.length > 1 ? r.datagram.bytes[1] : 0, p.sequence,
                       p.error == proto::Error::ok ? "ok" : std::string(proto::to_string(p.error)));
    for (std::size_t i = 0; i < r.datagram.length; ++i) {
      out += fmt::format(" {:02x}", r.datagram.bytes[i]);
    }
    out += '\n';
  }
  return out;
}

}  // namespace mrskin
