#include "mrskin/driver/session.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <string>

#include "mrskin/driver/layout.hpp"
#include "mrskin/protocol/packed_report.hpp"
#include "mrskin/protocol/packet.hpp"
#include "mrskin/protocol/units.hpp"
#include "session_impl.hpp"
#include "session_names.hpp"

namespace mrskin {
namespace proto = mrskin::protocol;
using session_names::config_key_name;
using session_names::config_status_name;
using session_names::quantity_name;
using session_names::quantity_unit;

namespace {

std::uint16_t clamp_counts(double value, double lsb, std::uint16_t max_counts) noexcept {
  if (!(value > 0.0)) {
    return 0;  // also NaN
  }
  return static_cast<std::uint16_t>(std::min(std::nearbyint(value / lsb), static_cast<double>(max_counts)));
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

// --- TargetSeeder ---------------------------------------------------------------------------

TargetSeeder::TargetSeeder(const model::DeviceProfile& profile) {
  const GridLayout layout(profile.rows, profile.cols);
  const std::size_t cells = layout.fluid_cell_count();
  std::vector<std::vector<Term>> rows_of_cell(cells);
  for (std::size_t s = 0; s < profile.sensors.size(); ++s) {
    const model::SensorSpec& spec = profile.sensors[s];
    if (spec.quantity != model::SensorQuantity::displacement || spec.place == model::PlaceKind::reservoir) {
      continue;
    }
    const std::size_t row = row_sensor_.size();
    row_sensor_.push_back(s);
    if (spec.place == model::PlaceKind::fluid_cell && spec.index < cells) {
      rows_of_cell[spec.index].push_back({row, 1.0});
    } else if (spec.place == model::PlaceKind::valve && spec.index < layout.valve_count()) {
      const std::vector<std::size_t>& joined = layout.cells_of_valve(spec.index);
      const double w = 1.0 / static_cast<double>(joined.size());
      for (const std::size_t c : joined) {
        rows_of_cell[c].push_back({row, w});
      }
    }
  }
  cell_begin_.assign(1, 0);
  force_begin_.assign(1, 0);
  for (std::size_t c = 0; c < cells; ++c) {
    double norm2 = 0.0;
    for (const Term& t : rows_of_cell[c]) {
      cell_rows_.push_back(t);
      norm2 += t.weight * t.weight;
    }
    cell_begin_.push_back(cell_rows_.size());
    cell_norm2_.push_back(norm2);
    const std::size_t before = force_.size();
    for (std::size_t s = 0; s < profile.sensors.size(); ++s) {
      const model::SensorSpec& spec = profile.sensors[s];
      if (spec.quantity == model::SensorQuantity::force && spec.place == model::PlaceKind::fluid_cell &&
          spec.index == c) {
        force_.push_back({s, 1.0});
      }
    }
    for (std::size_t i = before; i < force_.size(); ++i) {
      force_[i].weight = 1.0 / static_cast<double>(force_.size() - before);
    }
    force_begin_.push_back(force_.size());
  }
  fit_m_.assign(cells, 0.0);
  residual_m_.assign(row_sensor_.size(), 0.0);
}

double TargetSeeder::sum(std::span<const Term> terms, std::span<const double> sensors) noexcept {
  double total = 0.0;
  for (const Term& t : terms) {
    if (t.sensor < sensors.size()) {
      total += t.weight * sensors[t.sensor];
    }
  }
  return total;
}

void TargetSeeder::fit(std::span<const double> sensors) const noexcept {
  // Projected coordinate descent on 1/2 |H d - y|^2, d >= 0, from d = 0.
  constexpr int kSweeps = 200;
  std::fill(fit_m_.begin(), fit_m_.end(), 0.0);
  for (std::size_t r = 0; r < residual_m_.size(); ++r) {
    const double y = row_sensor_[r] < sensors.size() ? sensors[row_sensor_[r]] : 0.0;
    residual_m_[r] = std::isfinite(y) ? -y : 0.0;
  }
  for (int sweep = 0; sweep < kSweeps; ++sweep) {
    for (std::size_t c = 0; c < fit_m_.size(); ++c) {
      if (cell_norm2_[c] <= 0.0) {
        continue;
      }
      double gradient = 0.0;
      for (std::size_t e = cell_begin_[c]; e < cell_begin_[c + 1]; ++e) {
        gradient += cell_rows_[e].weight * residual_m_[cell_rows_[e].sensor];
      }
      const double next = std::max(0.0, fit_m_[c] - gradient / cell_norm2_[c]);
      const double delta = next - fit_m_[c];
      if (delta != 0.0) {
        for (std::size_t e = cell_begin_[c]; e < cell_begin_[c + 1]; ++e) {
          residual_m_[cell_rows_[e].sensor] += cell_rows_[e].weight * delta;
        }
        fit_m_[c] = next;
      }
    }
  }
}

double TargetSeeder::displacement_m(std::size_t cell, std::span<const double> sensors) const noexcept {
  if (cell >= fit_m_.size()) {
    return 0.0;
  }
  fit(sensors);
  return fit_m_[cell];
}

void TargetSeeder::fit_displacements(std::span<const double> sensors) const noexcept { fit(sensors); }

double TargetSeeder::fitted_displacement_m(std::size_t cell) const noexcept {
  return cell < fit_m_.size() ? fit_m_[cell] : 0.0;
}

double TargetSeeder::force_N(std::size_t cell, std::span<const double> sensors) const noexcept {
  if (cell + 1 >= force_begin_.size()) {
    return 0.0;
  }
  return sum(
      std::span<const Term>(force_).subspan(force_begin_[cell], force_begin_[cell + 1] - force_begin_[cell]),
      sensors);
}

proto::CellTarget TargetSeeder::seed(std::size_t cell, std::span<const double> sensors,
                                     std::uint8_t validity_counts) const noexcept {
  if (cell < fit_m_.size()) {
    fit(sensors);
  }
  return seed_from_fit(cell, sensors, validity_counts);
}

proto::CellTarget TargetSeeder::seed_from_fit(std::size_t cell, std::span<const double> sensors,
                                              std::uint8_t validity_counts) const noexcept {
  proto::CellTarget t;
  t.stiffness = 0;
  t.offset = clamp_counts(fitted_displacement_m(cell), proto::kOffsetLsb_m, proto::kOffsetCountMax);
  t.ceiling = clamp_counts(force_N(cell, sensors), proto::kCeilingLsb_N, proto::kCeilingCountMax);
  t.validity = std::min(validity_counts, proto::kValidityCountMax);
  return t;
}

// --- DeviceSession: setup -------------------------------------------------------------------

DeviceSession::Impl::Impl(std::unique_ptr<Transport> transport, Clock& clock, SessionOptions options)
    : transport_(std::move(transport)), clock_(clock), options_(options) {
  if (!(options_.time_scale >= 1.0 && options_.time_scale <= 1000.0)) {
    throw InvalidArgument(fmt::format("time scale {} is outside [1, 1000]", options_.time_scale));
  }
  if (options_.ring_log_packets < 1 || options_.ring_log_packets > 65536) {
    throw InvalidArgument(
        fmt::format("ring log of {} packets is outside 1..65536: set SessionOptions::ring_log_packets",
                    options_.ring_log_packets));
  }
  if (options_.protocol_minor > proto::kVersionMinor) {
    throw InvalidArgument(fmt::format("protocol minor version {} is above this library's {}.{}",
                                      options_.protocol_minor, proto::kVersionMajor, proto::kVersionMinor));
  }
  ring_.resize(options_.ring_log_packets);
  fault_ring_.resize(options_.ring_log_packets);
  options_.handshake_timeout = scaled_duration(options_.handshake_timeout, options_.time_scale);
  options_.handshake_retry = scaled_duration(options_.handshake_retry, options_.time_scale);
  options_.heartbeat_period = scaled_duration(options_.heartbeat_period, options_.time_scale);
  options_.reconnect_backoff_min = scaled_duration(options_.reconnect_backoff_min, options_.time_scale);
  options_.reconnect_backoff_max = scaled_duration(options_.reconnect_backoff_max, options_.time_scale);
  options_.telemetry_timeout = scaled_duration(options_.telemetry_timeout, options_.time_scale);
  if (!transport_ || transport_->state() != TransportState::open) {
    throw DeviceNotFound(fmt::format(
        "no device answers on {}: check the cable and the URI (mrskinctl list shows what is attached)",
        transport_ ? std::string(transport_->uri()) : std::string("(null transport)")));
  }
  await_identity(clock_.now() + options_.handshake_timeout);
  if (options_.read_configuration) {
    info_.profile = read_config(proto::ConfigKey::profile);
    info_.calibration = read_config(proto::ConfigKey::calibration);
    load_profile();
  }
  sensors_.assign(info_.sensors, 0.0);
  current_counts_.assign(info_.valves, 0);
  pending_counts_.assign(info_.valves, 0);
  commanded_A_.assign(info_.valves, 0.0);
  quantised_A_.assign(info_.valves, 0.0);
  const std::size_t blocks = (info_.valves + proto::kMaxValveCurrents - 1) / proto::kMaxValveCurrents;
  block_sent_.assign(blocks, TimePoint{});
  block_go_.assign(blocks, 0);
  targets_.assign(info_.fluid_cells, proto::CellTarget{});
  targeted_.assign(info_.fluid_cells, 0);
  next_heartbeat_ = clock_.now();
  last_telemetry_ = clock_.now();
}

DeviceSession::Impl::~Impl() {
  // Leave the unit safe: release valves; the device's watchdog covers a crash.
  (void)request_disable();
}

void DeviceSession::Impl::apply_identity(const proto::Identity& id) {
  if (id.proto_major != proto::kVersionMajor) {
    throw ProtocolMismatch(fmt::format(
        "device on {} reports protocol v{}.{}, this library speaks v{}.{}: update the device "
        "firmware or use a matching mrskin release",
        transport_->uri(), id.proto_major, id.proto_minor, proto::kVersionMajor, proto::kVersionMinor));
  }
  identity_ = id;
  packing_ = proto::reads_packed_reports(proto::kVersionMajor, options_.protocol_minor) &&
             proto::reads_packed_reports(id.proto_major, id.proto_minor);
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
  info_.sensor_quantity = quantity_name(id.sensor_quantity);
  info_.sensor_unit = quantity_unit(id.sensor_quantity);
  info_.heartbeat_timeout_s = id.heartbeat_timeout_ms * 1e-3;
  info_.telemetry_rate_hz = id.telemetry_rate_hz;
  current_lsb_nA_ = id.current_lsb_nA;
  current_max_counts_ = id.current_max_counts;
  quantised_valid_ = false;  // a new scale: the last command's counts are not these currents' counts
  all_blocks_due_ = true;
  sensor_lsb_ = info_.sensor_lsb;
}

// A USB unit's declared reports (1.2): this session's reports grow to their size. Only once 1.2 is
// agreed (a unit sends it only then) and never on CAN, whose frames hold 64 bytes.
void DeviceSession::Impl::apply_usb_slots(const proto::UsbSlots& declared) noexcept {
  const std::optional<proto::BusSpec> bus = transport_->bus();
  const bool can = bus && (bus->kind == proto::BusKind::can_classic || bus->kind == proto::BusKind::can_fd);
  if (!packing_ || can) {
    return;
  }
  info_.usb_slots = proto::usb_interrupt_slots(declared);
  report_capacity_ = std::min<std::size_t>(declared.report_bytes, report_.size());
}

bool DeviceSession::Impl::same_unit(const proto::Identity& id) const noexcept {
  return id.serial == identity_.serial && id.rows == identity_.rows && id.cols == identity_.cols &&
         id.fluid_cells == identity_.fluid_cells && id.valves == identity_.valves &&
         id.sensors == identity_.sensors && id.current_lsb_nA == identity_.current_lsb_nA &&
         id.current_max_counts == identity_.current_max_counts &&
         id.sensor_quantity == identity_.sensor_quantity && id.sensor_lsb_nano == identity_.sensor_lsb_nano;
}

void DeviceSession::Impl::await_identity(TimePoint deadline) {
  TimePoint next_request = clock_.now();
  for (;;) {
    const TimePoint now = clock_.now();
    if (now >= next_request) {
      // Repeated, since a lossy link may eat the request or the answer.
      if (send_packet(proto::IdentifyRequest{proto::kVersionMajor, options_.protocol_minor}) ==
          ResultCode::disconnected) {
        throw DeviceNotFound(
            fmt::format("device on {} disconnected during the handshake", transport_->uri()));
      }
      next_request = now + options_.handshake_retry;
    }
    Datagram d;
    const ResultCode rc = transport_->receive(d);
    if (rc == ResultCode::ok) {
      const std::span<const std::uint8_t> bytes(d.bytes.data(), d.length);
      proto::PacketWalker walker(bytes);
      proto::PacketDecoded p;
      if (!walker.next(p)) {
        p = proto::decode_first_packet(bytes);  // an empty report: its error
      }
      if (p.error == proto::Error::wrong_version) {
        log(d, false, now);
        throw ProtocolMismatch(fmt::format(
            "device on {} speaks protocol v{}, this library speaks v{}: update the device firmware or use a "
            "matching mrskin release",
            transport_->uri(), p.peer_version, proto::kVersionMajor));
      }
      if (p.error != proto::Error::ok) {
        log(d, false, now);
        ++counters_.decode_errors;
        counters_.crc_errors += p.error == proto::Error::bad_crc ? 1U : 0U;
        continue;
      }
      if (const auto* id = std::get_if<proto::Identity>(&p.message)) {
        apply_identity(*id);
        if (packing_) {
          // A 1.2 unit packs the first status (or more) behind the Identity: this session's
          // first traffic, in sequence after the Identity.
          // The Identity, then the rest as a report of its own.
          const std::size_t head = walker.offset();
          log(bytes.first(head), false, now);
          rx_last_sequence_ = p.sequence;
          if (head < bytes.size() && bytes[head] != 0x00) {
            handle_packed(bytes.subspan(head), now);
          }
        } else {
          log(d, false, now);
        }
        return;
      }
      log(d, false, now);
      continue;
    }
    if (rc == ResultCode::disconnected) {
      throw DeviceNotFound(fmt::format("device on {} disconnected during the handshake", transport_->uri()));
    }
    if (now >= deadline) {
      throw Timeout(
          fmt::format("device on {} did not identify within {:.3f} s: check power, firmware and that no "
                      "other process owns it (raise the time scale in slow environments)",
                      transport_->uri(), to_seconds(options_.handshake_timeout)));
    }
    clock_.sleep_until(now + std::chrono::microseconds(200));
  }
}

void DeviceSession::Impl::load_profile() {
  try {
    profile_ = std::make_unique<model::DeviceProfile>(
        model::parse_profile(info_.profile, fmt::format("profile stored on {}", transport_->uri())));
  } catch (const InvalidArgument& e) {
    throw InvalidArgument(
        fmt::format("{}: the device's configuration memory holds a bad profile; write a "
                    "valid one to it (mrskinctl calibrate) or service the unit",
                    e.what()));
  }
  const model::DeviceProfile& p = *profile_;
  const GridLayout layout(p.rows, p.cols);
  const double lsb_A = info_.current_lsb_A;
  std::string mismatch;
  if (p.rows != info_.rows || p.cols != info_.cols) {
    mismatch = fmt::format("grid {} x {} in the profile, {} x {} in the identity", p.rows, p.cols, info_.rows,
                           info_.cols);
  } else if (layout.fluid_cell_count() != info_.fluid_cells || layout.valve_count() != info_.valves) {
    mismatch = fmt::format("{} fluid cells and {} valves in the profile, {} and {} in the identity",
                           layout.fluid_cell_count(), layout.valve_count(), info_.fluid_cells, info_.valves);
  } else if (p.sensors.size() != info_.sensors) {
    mismatch = fmt::format("{} sensors in the profile, {} in the identity", p.sensors.size(), info_.sensors);
  } else if (std::abs(p.coil.max_current_A - info_.max_current_A) > lsb_A ||
             std::abs(p.coil.current_resolution_A - lsb_A) > 1e-9) {
    mismatch = fmt::format(
        "current range {} A in steps of {} A in the profile, {} A in steps of {} A in the identity",
        p.coil.max_current_A, p.coil.current_resolution_A, info_.max_current_A, lsb_A);
  }
  if (!mismatch.empty()) {
    throw InvalidArgument(
        fmt::format("device on {} disagrees with the profile it stores ({}): the unit's "
                    "configuration memory needs servicing",
                    transport_->uri(), mismatch));
  }
  seeder_ = TargetSeeder(p);
}

// --- DeviceSession: the tick ----------------------------------------------------------------

void DeviceSession::Impl::log(std::span<const std::uint8_t> bytes, bool sent, TimePoint now) noexcept {
  TrafficRecord& r = ring_[ring_next_];
  r.time = now;
  r.sent = sent;
  r.packet.length = static_cast<std::uint8_t>(std::min(bytes.size(), r.packet.bytes.size()));
  std::copy_n(bytes.begin(), r.packet.length, r.packet.bytes.begin());
  ring_next_ = (ring_next_ + 1) % ring_.size();
  ring_size_ = std::min(ring_size_ + 1, ring_.size());
}

ResultCode DeviceSession::Impl::send_packet(const proto::Message& message, bool hold) noexcept {
  if (packing_) {
    const std::span<std::uint8_t> report = std::span<std::uint8_t>(report_).first(report_capacity_);
    proto::EncodeResult r = proto::append_packet(message, tx_sequence_, report, report_used_);
    if (r.error == proto::Error::short_buffer && report_used_ > 0) {
      // Full: the report goes as it is, this packet starts the next one.
      if (const ResultCode rc = flush_report(); rc != ResultCode::ok) {
        return rc;
      }
      r = proto::append_packet(message, tx_sequence_, report, report_used_);
    }
    if (r.error != proto::Error::ok) {
      ++counters_.invalid_commands;
      return ResultCode::invalid_value;
    }
    report_used_ += r.bytes;
    report_ends_[report_packets_++] = static_cast<std::uint16_t>(report_used_);
    ++tx_sequence_;
    return hold ? ResultCode::ok : flush_report();
  }
  Datagram d;
  const auto r = proto::encode_packet(message, tx_sequence_, d.bytes);
  if (r.error != proto::Error::ok) {
    ++counters_.invalid_commands;
    return ResultCode::invalid_value;
  }
  d.length = static_cast<std::uint16_t>(r.bytes);
  const ResultCode rc = transport_->send(std::span<const std::uint8_t>(d.bytes.data(), r.bytes));
  if (rc == ResultCode::ok) {
    ++tx_sequence_;
    ++counters_.sent;
    ++counters_.reports_sent;
    log(d, true, clock_.now());
  } else if (rc == ResultCode::would_block) {
    ++counters_.send_would_block;
  }
  return rc;
}

ResultCode DeviceSession::Impl::flush_report() noexcept {
  if (report_used_ == 0) {
    return ResultCode::ok;
  }
  const ResultCode rc = transport_->send(std::span<const std::uint8_t>(report_.data(), report_used_));
  if (rc == ResultCode::ok) {
    counters_.sent += report_packets_;
    ++counters_.reports_sent;
    const TimePoint now = clock_.now();
    std::size_t begin = 0;
    for (std::size_t i = 0; i < report_packets_; ++i) {
      // The ring log keeps packets, as the log's decoder reads them.
      log(std::span<const std::uint8_t>(report_).subspan(begin, report_ends_[i] - begin), true, now);
      begin = report_ends_[i];
    }
    report_used_ = report_packets_ = 0;
    return rc;
  }
  if (rc == ResultCode::would_block) {
    ++counters_.send_would_block;
  }
  drop_report();
  return rc;
}

void DeviceSession::Impl::drop_report() noexcept {
  // Never sent: the device must see no gap in the sequence.
  tx_sequence_ = static_cast<std::uint8_t>(tx_sequence_ - report_packets_);
  report_used_ = report_packets_ = 0;
}

void DeviceSession::Impl::handle(const Datagram& d, TimePoint now) noexcept {
  const std::span<const std::uint8_t> bytes(d.bytes.data(), d.length);
  ++counters_.reports_received;
  if (packing_) {
    handle_packed(bytes, now);
    return;
  }
  proto::PacketWalker walker(bytes);
  proto::PacketDecoded p;
  if (!walker.next(p) || p.error != proto::Error::ok || !std::holds_alternative<proto::Identity>(p.message)) {
    log(d, false, now);
    handle_packet(proto::decode_first_packet(bytes), now);
    return;
  }
  // A reconnect's Identity may agree on 1.2: then the packets the unit packed behind it (its
  // UsbSlots, a status) are read too.
  const std::size_t head = walker.offset();
  log(bytes.first(head), false, now);
  handle_packet(p, now);
  if (packing_ && head < bytes.size() && bytes[head] != 0x00) {
    handle_packed(bytes.subspan(head), now);
  }
}

void DeviceSession::Impl::handle_packed(std::span<const std::uint8_t> bytes, TimePoint now) noexcept {
  // Every packet of the report, each logged on its own; a broken one ends the walk.
  proto::PacketWalker walker(bytes);
  proto::PacketDecoded p;
  std::size_t begin = 0;
  bool any = false;
  while (walker.next(p)) {
    any = true;
    const std::size_t end = walker.broken() ? bytes.size() : walker.offset();
    log(bytes.subspan(begin, end - begin), false, now);
    begin = end;
    handle_packet(p, now);
  }
  if (!any) {
    log(bytes, false, now);
    handle_packet(proto::decode_first_packet(bytes), now);  // an empty report: counted undecodable
  }
}

void DeviceSession::Impl::handle_packet(const proto::PacketDecoded& p, TimePoint now) noexcept {
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
    if (state_request_pending_ &&
        (state == wanted_state_ || (state == DeviceState::fault && state_ != DeviceState::fault))) {
      state_request_pending_ = false;  // confirmed, or a new fault overrides the request
    }
    if (state == DeviceState::fault && state_ != DeviceState::fault) {
      ++counters_.faults;
      last_fault_time_ = now;
      last_fault_code_ = s->fault;
      std::copy(ring_.begin(), ring_.end(), fault_ring_.begin());  // same size: no allocation
      fault_ring_size_ = ring_size_;
      fault_ring_next_ = ring_next_;
    }
    if (state == DeviceState::enabled && state_ != DeviceState::enabled && counts_changed_since_reseed_) {
      all_blocks_due_ = true;  // the unit zeroed its currents as it enabled, maybe after these went
    }
    state_ = state;
    fault_ = s->fault;
    valves_released_ = (s->flags & proto::kFlagValvesReleased) != 0;
    derated_ = (s->flags & proto::kFlagDerated) != 0;
    degaussing_ = (s->flags & proto::kFlagDegaussing) != 0;
  } else if (const auto* h = std::get_if<proto::Heartbeat>(&p.message)) {
    const TimePoint sent = heartbeat_sent_[h->counter % heartbeat_sent_.size()];
    if (sent.count() != 0 && now >= sent) {
      counters_.round_trip.add((now - sent).count());
      counters_.last_round_trip_ns = (now - sent).count();
    }
  } else if (const auto* cd = std::get_if<proto::ConfigData>(&p.message)) {
    ConfigTransfer& c = config_;
    if (!c.active || cd->key != c.key) {
      return;  // a late answer to a finished read
    }
    if (c.total < 0) {
      c.total = cd->total;  // setup only: the one allocation of the transfer
      c.text.assign(cd->total, '\0');
      c.have.assign((cd->total + c.chunk - 1) / c.chunk, 0);
    }
    const std::size_t index = cd->offset / c.chunk;
    const std::size_t expected = std::min<std::size_t>(
        c.chunk, static_cast<std::size_t>(c.total) - std::min<std::size_t>(cd->offset, c.total));
    if (cd->total != c.total || cd->offset % c.chunk != 0 || index >= c.have.size() ||
        cd->length != expected || c.have[index] != 0) {
      return;
    }
    std::copy_n(cd->bytes.begin(), cd->length, c.text.begin() + cd->offset);
    c.have[index] = 1;
    ++c.received;
    c.progress = true;
  } else if (const auto* us = std::get_if<proto::UsbSlots>(&p.message)) {
    apply_usb_slots(*us);
  } else if (const auto* sd = std::get_if<proto::SensorDeadband>(&p.message)) {
    if (packing_) {  // a unit declares it only once 1.2 is agreed
      info_.sensor_deadband_counts = sd->counts;
    }
  } else if (const auto* ca = std::get_if<proto::ConfigAck>(&p.message)) {
    if (config_.active && ca->key == config_.key) {
      config_.acked = true;
      config_.ack_offset = ca->offset;
      config_.ack_status = ca->status;
    }
  } else if (const auto* id = std::get_if<proto::Identity>(&p.message)) {
    if (identify_pending_ && id->proto_major == proto::kVersionMajor) {
      identify_pending_ = false;
      if (!same_unit(*id)) {
        ++counters_.identity_changes;  // not our unit: stay disconnected, the host must reopen
        return;
      }
      connected_ = true;
      packing_ = proto::reads_packed_reports(proto::kVersionMajor, options_.protocol_minor) &&
                 proto::reads_packed_reports(id->proto_major, id->proto_minor);
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

ResultCode DeviceSession::Impl::poll(TimePoint now) noexcept {
  if (polling_) {
    return ResultCode::would_block;  // from the telemetry callback: rx_datagram_ is being read
  }
  polling_ = true;
  const ClearOnExit clear(polling_);
  if (transport_->state() != TransportState::open) {
    if (connected_) {
      connected_ = false;
      identify_pending_ = false;
      packing_ = false;  // the unit reboots: it packs again only after the next handshake
      drop_report();
      report_capacity_ = proto::kHidReportBytes;  // until it declares its reports again
      info_.usb_slots.reset();
      info_.sensor_deadband_counts = 0;  // until it declares one again
      all_blocks_due_ = true;            // a rebooted unit's currents are not the ones last sent
      ++counters_.disconnects;
      backoff_ = options_.reconnect_backoff_min;
      next_reconnect_ = now + backoff_;
    }
    return ResultCode::disconnected;
  }
  // A heartbeat held by the last poll() that no valve currents came to ride with.
  (void)flush_report();
  if (!connected_ && counters_.identity_changes == 0) {
    // Link is back: identify again, with exponential backoff between attempts.
    if (now >= next_reconnect_) {
      identify_pending_ = true;
      rx_last_sequence_ = -1;
      (void)send_packet(proto::IdentifyRequest{proto::kVersionMajor, options_.protocol_minor});
      next_reconnect_ = now + backoff_;
      backoff_ = std::min(backoff_ * 2, options_.reconnect_backoff_max);
    }
  }
  Datagram& d = rx_datagram_;  // a member: a datagram on the stack was zeroed every poll
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
  if (state_request_pending_ && now >= next_state_retry_) {
    if (state_retries_left_ > 0) {
      --state_retries_left_;
      ++counters_.state_retries;
      next_state_retry_ = now + options_.handshake_retry;
      (void)send_packet(proto::StateRequest{pending_request_});
    } else {
      state_request_pending_ = false;  // the device does not take it: state() tells the host
    }
  }
  if (!suppress_heartbeat_ && now >= next_heartbeat_) {
    next_heartbeat_ = now + options_.heartbeat_period;
    heartbeat_sent_[heartbeat_counter_ % heartbeat_sent_.size()] = now;
    // Held with packed reports: it rides with the valve currents the tick sends next.
    if (send_packet(proto::Heartbeat{heartbeat_counter_}, /*hold=*/true) == ResultCode::ok) {
      ++counters_.heartbeats;
    }
    ++heartbeat_counter_;
  }
  return state_ == DeviceState::fault ? ResultCode::device_fault : ResultCode::ok;
}

ResultCode DeviceSession::Impl::send_cell_targets(std::uint16_t first_cell,
                                                  std::span<const proto::CellTarget> targets) noexcept {
  if (first_cell + targets.size() > info_.fluid_cells) {
    ++counters_.invalid_commands;
    return ResultCode::invalid_value;
  }
  for (std::size_t i = 0; i < targets.size(); ++i) {
    targets_[first_cell + i] = targets[i];
    targeted_[first_cell + i] = 1;
  }
  for (std::size_t done = 0; done < targets.size(); done += proto::kMaxCellTargets) {
    proto::CellTargets m;
    m.first = static_cast<std::uint16_t>(first_cell + done);
    m.count = static_cast<std::uint8_t>(std::min(proto::kMaxCellTargets, targets.size() - done));
    std::copy_n(targets.begin() + static_cast<std::ptrdiff_t>(done), m.count, m.targets.begin());
    const ResultCode rc = send_packet(m, /*hold=*/true);
    if (rc != ResultCode::ok) {
      drop_report();
      return rc;
    }
  }
  return flush_report();
}

void DeviceSession::Impl::reseed_and_send() noexcept {
  ++counters_.reseeds;
  quantised_valid_ = false;
  std::fill(current_counts_.begin(), current_counts_.end(), std::uint16_t{0});
  std::fill(commanded_A_.begin(), commanded_A_.end(), 0.0);
  counts_changed_since_reseed_ = false;
  if (currents_commanded_) {
    for (std::size_t first = 0; first < current_counts_.size(); first += proto::kMaxValveCurrents) {
      proto::ValveCurrents m;
      m.first = static_cast<std::uint16_t>(first);
      m.count = static_cast<std::uint8_t>(std::min(proto::kMaxValveCurrents, current_counts_.size() - first));
      (void)send_packet(m, /*hold=*/true);  // all zero: released until the host commands again
    }
  }
  // Targets: one message per run of targeted cells, at most kMaxCellTargets long.
  proto::CellTargets m;
  seeder_.fit_displacements(sensors_);  // once for every cell
  for (std::size_t c = 0; c <= targets_.size(); ++c) {
    const bool take = c < targets_.size() && targeted_[c] != 0;
    if (take) {
      targets_[c] = seeder_.seed_from_fit(c, sensors_, targets_[c].validity);
      if (m.count == 0) {
        m.first = static_cast<std::uint16_t>(c);
      }
      m.targets[m.count++] = targets_[c];
    }
    if (m.count > 0 && (!take || m.count == proto::kMaxCellTargets)) {
      (void)send_packet(m, /*hold=*/true);
      m.count = 0;
    }
  }
  (void)flush_report();
}

ResultCode DeviceSession::Impl::send_state_request(proto::StateRequestCode request) noexcept {
  pending_request_ = static_cast<std::uint8_t>(request);
  state_request_pending_ = true;
  state_retries_left_ = 10;
  next_state_retry_ = clock_.now() + options_.handshake_retry;
  return send_packet(proto::StateRequest{pending_request_});
}

ResultCode DeviceSession::Impl::request_enable() noexcept {
  wanted_state_ = DeviceState::enabled;
  const ResultCode rc = send_state_request(proto::StateRequestCode::enable);
  if (rc == ResultCode::ok) {
    reseed_and_send();
  }
  return rc;
}
ResultCode DeviceSession::Impl::request_disable() noexcept {
  wanted_state_ = DeviceState::disabled;
  return send_state_request(proto::StateRequestCode::disable);
}
ResultCode DeviceSession::Impl::request_pause() noexcept {
  wanted_state_ = DeviceState::paused;
  return send_state_request(proto::StateRequestCode::pause);
}
ResultCode DeviceSession::Impl::request_degauss() noexcept {
  // The device stays disabled; a device without a bipolar driver ignores it (no degaussing flag).
  wanted_state_ = DeviceState::disabled;
  return send_state_request(proto::StateRequestCode::degauss);
}
ResultCode DeviceSession::Impl::request_estop() noexcept {
  wanted_state_ = DeviceState::disabled;  // FAULT (e-stop) confirms it
  return send_state_request(proto::StateRequestCode::estop);
}

void DeviceSession::Impl::await_config_ack(std::uint16_t offset) {
  TimePoint last_progress = clock_.now();
  while (!config_.acked || config_.ack_offset != offset) {
    const TimePoint now = clock_.now();
    Datagram d;
    const ResultCode rc = transport_->receive(d);
    if (rc == ResultCode::ok) {
      handle(d, now);
      continue;
    }
    if (rc == ResultCode::disconnected) {
      config_.active = false;
      throw DeviceNotFound(
          fmt::format("device on {} disconnected while its configuration was written", transport_->uri()));
    }
    if (now - last_progress > options_.handshake_timeout) {
      config_.active = false;
      throw Timeout(fmt::format("device on {} did not acknowledge its configuration write within {:.3f} s",
                                transport_->uri(), to_seconds(options_.handshake_timeout)));
    }
    clock_.sleep_until(now + std::chrono::microseconds(200));
  }
}

void DeviceSession::Impl::write_calibration(std::string_view text) {
  constexpr std::size_t chunk = proto::kMaxConfigBytes;
  if (text.empty() || text.size() > 4096) {
    throw InvalidArgument(fmt::format(
        "a calibration of {} bytes cannot be stored: the configuration memory takes 1..4096", text.size()));
  }
  if (!connected_ || transport_->state() != TransportState::open) {
    throw DeviceNotFound(fmt::format(
        "device on {} is not connected: reconnect before writing its calibration", transport_->uri()));
  }
  const auto key = static_cast<std::uint16_t>(proto::ConfigKey::calibration);
  for (std::size_t offset = 0; offset < text.size(); offset += chunk) {
    proto::ConfigWrite w;
    w.key = key;
    w.offset = static_cast<std::uint16_t>(offset);
    w.total = static_cast<std::uint16_t>(text.size());
    w.length = static_cast<std::uint8_t>(std::min(chunk, text.size() - offset));
    std::copy_n(text.begin() + static_cast<std::ptrdiff_t>(offset), w.length, w.bytes.begin());
    auto status = proto::ConfigStatus::ok;
    for (int attempt = 0;; ++attempt) {
      config_ = ConfigTransfer{};
      config_.active = true;
      config_.key = key;
      (void)send_packet(w);
      try {
        await_config_ack(w.offset);
        status = static_cast<proto::ConfigStatus>(config_.ack_status);
        break;
      } catch (const Timeout&) {
        if (attempt == 3) {
          throw;
        }  // the chunk or its ack was lost: the device takes a repeated chunk again
      }
    }
    config_.active = false;
    if (status == proto::ConfigStatus::busy) {
      throw Error(fmt::format("device on {} is ENABLED: disable it before writing its calibration",
                              transport_->uri()));
    }
    if (status == proto::ConfigStatus::rejected) {
      throw InvalidArgument(fmt::format(
          "device on {} refused the calibration: it needs a \"version = N\" line with N above the stored "
          "calibration's",
          transport_->uri()));
    }
    if (status != proto::ConfigStatus::ok) {
      throw Error(
          fmt::format("device on {} refused calibration bytes {}..{} ({}): write again from the start",
                      transport_->uri(), offset, offset + w.length, config_status_name(config_.ack_status)));
    }
  }
  std::string stored = read_config(proto::ConfigKey::calibration);
  if (stored != text) {
    throw Error(
        fmt::format("device on {} stored a different calibration than was written ({} bytes read back, "
                    "{} written): write it again",
                    transport_->uri(), stored.size(), text.size()));
  }
  info_.calibration = std::move(stored);
}

// --- the public face: one pointer to the state ---------------------------------------------

DeviceSession::DeviceSession(std::unique_ptr<Transport> transport, Clock& clock, SessionOptions options)
    : impl_(std::make_unique<Impl>(std::move(transport), clock, options)) {}
DeviceSession::~DeviceSession() = default;
const DeviceInfo& DeviceSession::info() const noexcept { return impl_->info(); }
const model::DeviceProfile* DeviceSession::profile() const noexcept { return impl_->profile(); }
void DeviceSession::set_telemetry_callback(TelemetryCallback callback, void* context) noexcept {
  impl_->set_telemetry_callback(callback, context);
}
ResultCode DeviceSession::poll(TimePoint now) noexcept { return impl_->poll(now); }
ResultCode DeviceSession::send_cell_targets(std::uint16_t first_cell,
                                            std::span<const protocol::CellTarget> targets) noexcept {
  return impl_->send_cell_targets(first_cell, targets);
}
ResultCode DeviceSession::request_enable() noexcept { return impl_->request_enable(); }
ResultCode DeviceSession::request_disable() noexcept { return impl_->request_disable(); }
ResultCode DeviceSession::request_pause() noexcept { return impl_->request_pause(); }
ResultCode DeviceSession::request_estop() noexcept { return impl_->request_estop(); }
ResultCode DeviceSession::request_degauss() noexcept { return impl_->request_degauss(); }
void DeviceSession::suppress_heartbeat(bool suppress) noexcept { impl_->suppress_heartbeat(suppress); }
std::span<const double> DeviceSession::sensors() const noexcept { return impl_->sensors(); }
std::uint32_t DeviceSession::sensor_device_time_us() const noexcept { return impl_->sensor_device_time_us(); }
std::span<const double> DeviceSession::commanded_currents() const noexcept {
  return impl_->commanded_currents();
}
std::span<const protocol::CellTarget> DeviceSession::cell_targets() const noexcept {
  return impl_->cell_targets();
}
const TargetSeeder& DeviceSession::seeder() const noexcept { return impl_->seeder(); }
TimePoint DeviceSession::last_telemetry_time() const noexcept { return impl_->last_telemetry_time(); }
DeviceState DeviceSession::state() const noexcept { return impl_->state(); }
std::uint8_t DeviceSession::fault_code() const noexcept { return impl_->fault_code(); }
bool DeviceSession::valves_released() const noexcept { return impl_->valves_released(); }
bool DeviceSession::derated() const noexcept { return impl_->derated(); }
Transport& DeviceSession::transport() noexcept { return impl_->transport(); }
bool DeviceSession::degaussing() const noexcept { return impl_->degaussing(); }
bool DeviceSession::connected() const noexcept { return impl_->connected(); }
bool DeviceSession::packed_reports() const noexcept { return impl_->packed_reports(); }
const SessionCounters& DeviceSession::counters() const noexcept { return impl_->counters(); }
TransportState DeviceSession::transport_state() const noexcept { return impl_->transport_state(); }
void DeviceSession::write_calibration(std::string_view text) { impl_->write_calibration(text); }
std::vector<TrafficRecord> DeviceSession::ring_log() const { return impl_->ring_log(); }
std::vector<TrafficRecord> DeviceSession::fault_log() const { return impl_->fault_log(); }
TimePoint DeviceSession::last_fault_time() const noexcept { return impl_->last_fault_time(); }
std::uint8_t DeviceSession::last_fault_code() const noexcept { return impl_->last_fault_code(); }
std::vector<LogEntry> DeviceSession::decode_log(const std::vector<TrafficRecord>& records) const {
  return impl_->decode_log(records);
}
std::string DeviceSession::format_log(const std::vector<TrafficRecord>& records) const {
  return impl_->format_log(records);
}
std::string DeviceSession::fault_report() const { return impl_->fault_report(); }

static_assert(sizeof(DeviceSession) == sizeof(void*),
              "DeviceSession is one pointer: its state lives in DeviceSession::Impl");

}  // namespace mrskin
