#include "mrskin/protocol/packet.hpp"

#include <algorithm>
#include <array>
#include <type_traits>
#include <utility>

#include "bytes.hpp"
#include "mrskin/protocol/crc.hpp"
#include "validate.hpp"
#include "visit.hpp"

namespace mrskin::protocol {
namespace {

using detail::Reader;
using detail::Writer;

void put(Writer& w, const IdentifyRequest& m) noexcept {
  w.u8(m.host_major);
  w.u8(m.host_minor);
}
void put(Writer& w, const Identity& m) noexcept {
  w.u8(m.proto_major);
  w.u8(m.proto_minor);
  w.u8(m.fw_major);
  w.u8(m.fw_minor);
  w.u8(m.fw_patch);
  w.u8(m.rows);
  w.u8(m.cols);
  w.u16(m.fluid_cells);
  w.u16(m.valves);
  w.u16(m.sensors);
  w.u32(m.serial);
  w.u32(m.current_lsb_nA);
  w.u16(m.current_max_counts);
  w.u8(m.sensor_quantity);
  w.u32(m.sensor_lsb_nano);
  w.u16(m.heartbeat_timeout_ms);
  w.u16(m.telemetry_rate_hz);
}
void put(Writer& w, const ValveCurrents& m) noexcept {
  w.u16(m.first);
  w.u8(m.count);
  w.u16s(std::span<const std::uint16_t>(m.counts.data(), std::min<std::size_t>(m.count, m.counts.size())));
}
void put(Writer& w, const CellTargets& m) noexcept {
  w.u16(m.first);
  w.u8(m.count);
  for (std::size_t i = 0; i < m.count; ++i) {
    w.u16(m.targets[i].stiffness);
    w.u16(m.targets[i].offset);
    w.u16(m.targets[i].ceiling);
    w.u8(m.targets[i].validity);
  }
}
void put(Writer& w, const Telemetry& m) noexcept {
  w.u32(m.device_time_us);
  w.u16(m.first);
  w.u8(m.count);
  for (std::size_t i = 0; i < m.count; ++i) {
    w.i16(m.counts[i]);
  }
}
void put(Writer& w, const TimeSync& m) noexcept { w.u32(m.device_time_us); }
void put(Writer& w, const Status& m) noexcept {
  w.u8(m.state);
  w.u8(m.fault);
  w.u16(m.fault_detail);
  w.u8(m.flags);
}
void put(Writer& w, const Heartbeat& m) noexcept { w.u16(m.counter); }
void put(Writer& w, const StateRequest& m) noexcept { w.u8(m.request); }
void put(Writer& w, const ConfigRead& m) noexcept {
  w.u16(m.key);
  w.u16(m.offset);
  w.u8(m.length);
}
void put(Writer& w, const ConfigChunk& m) noexcept {
  w.u16(m.key);
  w.u16(m.offset);
  w.u16(m.total);
  w.u8(m.length);
  for (std::size_t i = 0; i < m.length; ++i) {
    w.u8(m.bytes[i]);
  }
}
void put(Writer& w, const ConfigAck& m) noexcept {
  w.u16(m.key);
  w.u16(m.offset);
  w.u8(m.status);
}
void put(Writer& w, const UsbSlots& m) noexcept {
  w.u16(m.report_bytes);
  w.u8(m.reports_per_interval);
  w.u16(m.interval_us);
}
void put(Writer& w, const SensorDeadband& m) noexcept { w.u8(m.counts); }

// Each get() reads the payload and returns the length the payload must have.
std::size_t get(Reader& r, IdentifyRequest& m) noexcept {
  m.host_major = r.u8();
  m.host_minor = r.u8();
  return 2;
}
std::size_t get(Reader& r, Identity& m) noexcept {
  m.proto_major = r.u8();
  m.proto_minor = r.u8();
  m.fw_major = r.u8();
  m.fw_minor = r.u8();
  m.fw_patch = r.u8();
  m.rows = r.u8();
  m.cols = r.u8();
  m.fluid_cells = r.u16();
  m.valves = r.u16();
  m.sensors = r.u16();
  m.serial = r.u32();
  m.current_lsb_nA = r.u32();
  m.current_max_counts = r.u16();
  m.sensor_quantity = r.u8();
  m.sensor_lsb_nano = r.u32();
  m.heartbeat_timeout_ms = r.u16();
  m.telemetry_rate_hz = r.u16();
  return 32;
}
std::size_t get(Reader& r, ValveCurrents& m) noexcept {
  m.first = r.u16();
  m.count = r.u8();
  const std::size_t n = std::min<std::size_t>(m.count, kMaxValveCurrents);
  r.u16s(m.counts.data(), n);
  return 3 + 2 * static_cast<std::size_t>(m.count);
}
std::size_t get(Reader& r, CellTargets& m) noexcept {
  m.first = r.u16();
  m.count = r.u8();
  const std::size_t n = std::min<std::size_t>(m.count, kMaxCellTargets);
  for (std::size_t i = 0; i < n; ++i) {
    m.targets[i].stiffness = r.u16();
    m.targets[i].offset = r.u16();
    m.targets[i].ceiling = r.u16();
    m.targets[i].validity = r.u8();
  }
  return 3 + 7 * static_cast<std::size_t>(m.count);
}
std::size_t get(Reader& r, Telemetry& m) noexcept {
  m.device_time_us = r.u32();
  m.first = r.u16();
  m.count = r.u8();
  const std::size_t n = std::min<std::size_t>(m.count, kMaxTelemetryValues);
  r.u16s(m.counts.data(), n);
  return 7 + 2 * static_cast<std::size_t>(m.count);
}
std::size_t get(Reader& r, TimeSync& m) noexcept {
  m.device_time_us = r.u32();
  return 4;
}
std::size_t get(Reader& r, Status& m) noexcept {
  m.state = r.u8();
  m.fault = r.u8();
  m.fault_detail = r.u16();
  m.flags = r.u8();
  return 5;
}
std::size_t get(Reader& r, Heartbeat& m) noexcept {
  m.counter = r.u16();
  return 2;
}
std::size_t get(Reader& r, StateRequest& m) noexcept {
  m.request = r.u8();
  return 1;
}
std::size_t get(Reader& r, ConfigRead& m) noexcept {
  m.key = r.u16();
  m.offset = r.u16();
  m.length = r.u8();
  return 5;
}
std::size_t get(Reader& r, ConfigChunk& m) noexcept {
  m.key = r.u16();
  m.offset = r.u16();
  m.total = r.u16();
  m.length = r.u8();
  const std::size_t n = std::min<std::size_t>(m.length, kMaxConfigBytes);
  for (std::size_t i = 0; i < n; ++i) {
    m.bytes[i] = r.u8();
  }
  return 7 + static_cast<std::size_t>(m.length);
}
std::size_t get(Reader& r, ConfigAck& m) noexcept {
  m.key = r.u16();
  m.offset = r.u16();
  m.status = r.u8();
  return 5;
}
std::size_t get(Reader& r, UsbSlots& m) noexcept {
  m.report_bytes = r.u16();
  m.reports_per_interval = r.u8();
  m.interval_us = r.u16();
  return 5;
}
std::size_t get(Reader& r, SensorDeadband& m) noexcept {
  m.counts = r.u8();
  return 1;
}

// Default-constructed alternatives, built at compile time: copying one is a trivial copy
// (every alternative is trivially copyable), so it cannot throw.
template <std::size_t... I>
constexpr std::array<Message, sizeof...(I)> make_prototypes(std::index_sequence<I...> /*indices*/) noexcept {
  return {Message{std::in_place_index<I>}...};
}
constexpr auto kPrototypes = make_prototypes(std::make_index_sequence<std::variant_size_v<Message>>{});
static_assert(std::is_trivially_copy_assignable_v<Message>);

bool message_for_type(std::uint8_t type, Message& out) noexcept {
  for (const Message& prototype : kPrototypes) {
    if (static_cast<std::uint8_t>(type_of(prototype)) == type) {
      out = prototype;
      return true;
    }
  }
  return false;
}

}  // namespace

std::size_t packet_payload_length(const Message& message) noexcept {
  if (detail::validate(message) != Error::ok) {
    return 0;
  }
  std::array<std::uint8_t, kPacketMaxBytes> scratch{};
  Writer w(scratch);
  detail::visit_nothrow<int>(
      [&w](const auto& m) noexcept {
        put(w, m);
        return 0;
      },
      message);
  return w.overflow() ? 0 : w.position();
}

EncodeResult encode_packet(const Message& message, std::uint8_t sequence,
                           std::span<std::uint8_t> out) noexcept {
  if (const Error e = detail::validate(message); e != Error::ok) {
    return {e, 0};
  }
  // Straight into `out` when any packet fits there (a packed report's packet buffer), else into
  // a buffer of the largest packet's size first (a short `out` learns its length below).
  std::array<std::uint8_t, kPacketMaxBytes> local{};
  const std::span<std::uint8_t> buffer =
      out.size() >= kPacketMaxBytes ? out.first(kPacketMaxBytes) : std::span<std::uint8_t>(local);
  Writer w(buffer.subspan(kPacketHeaderBytes, kPacketMaxPayload));
  detail::visit_nothrow<int>(
      [&w](const auto& m) noexcept {
        put(w, m);
        return 0;
      },
      message);
  if (w.overflow()) {
    return {Error::too_long, 0};
  }
  const std::size_t payload = w.position();
  buffer[0] = kVersionMajor;
  buffer[1] = static_cast<std::uint8_t>(type_of(message));
  buffer[2] = sequence;
  buffer[3] = static_cast<std::uint8_t>(payload);
  const std::size_t body = kPacketHeaderBytes + payload;
  const std::uint16_t crc = crc16_ccitt(std::span<const std::uint8_t>(buffer.data(), body));
  buffer[body] = static_cast<std::uint8_t>(crc & 0xFFU);
  buffer[body + 1] = static_cast<std::uint8_t>(crc >> 8U);
  const std::size_t total = body + kPacketCrcBytes;
  if (out.size() < total) {
    return {Error::short_buffer, 0};
  }
  if (buffer.data() != out.data()) {
    std::copy_n(buffer.begin(), total, out.begin());
  }
  return {Error::ok, total};
}

EncodeResult encode_hid_report(const Message& message, std::uint8_t sequence,
                               std::span<std::uint8_t, kHidReportBytes> report) noexcept {
  std::fill(report.begin(), report.end(), std::uint8_t{0});
  return encode_packet(message, sequence, report);
}

namespace {

// The framing's checks, inlined into decode_packet (check_packet_framing, exported, is a call
// through the PLT from inside the library).
inline Error framing_error(std::span<const std::uint8_t> in) noexcept {
  if (in.size() > kPacketMaxBytes) {
    return Error::too_long;
  }
  if (in.size() < kPacketHeaderBytes + kPacketCrcBytes) {
    return Error::short_buffer;
  }
  // Byte 0 is the major version in every protocol version, so it is checked first.
  if (in[0] != kVersionMajor) {
    return Error::wrong_version;
  }
  const std::size_t payload = in[3];
  if (payload > kPacketMaxPayload) {
    return Error::bad_length;
  }
  const std::size_t body = kPacketHeaderBytes + payload;
  if (in.size() < body + kPacketCrcBytes) {
    return Error::short_buffer;
  }
  const std::uint16_t expected = crc16_ccitt(in.first(body));
  const auto received = static_cast<std::uint16_t>(in[body] | (in[body + 1] << 8U));
  return expected == received ? Error::ok : Error::bad_crc;
}

}  // namespace

Error check_packet_framing(std::span<const std::uint8_t> in) noexcept { return framing_error(in); }

PacketDecoded decode_packet(std::span<const std::uint8_t> in) noexcept {
  PacketDecoded result;
  result.error = framing_error(in);
  if (in.size() >= kPacketHeaderBytes + kPacketCrcBytes && in.size() <= kPacketMaxBytes) {
    result.peer_version = in[0];  // whenever the size lets the version be read, as it is checked
  }
  if (result.error != Error::ok) {
    return result;
  }
  const std::size_t payload = in[3];
  result.sequence = in[2];
  if (!message_for_type(in[1], result.message)) {
    result.error = Error::unknown_type;
    return result;
  }
  Reader r(in.subspan(kPacketHeaderBytes, payload));
  const auto wanted =
      detail::visit_nothrow<std::size_t>([&r](auto& m) noexcept { return get(r, m); }, result.message);
  if (wanted != payload || r.underflow()) {
    result.error = Error::bad_length;
    return result;
  }
  result.error = detail::validate(result.message);
  return result;
}

std::size_t canfd_padded_length(std::size_t n) noexcept {
  static constexpr std::size_t kLengths[] = {0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64};
  for (const std::size_t len : kLengths) {
    if (n <= len) {
      return len;
    }
  }
  return 0;
}

Error CounterTracker::accept(std::uint8_t value) noexcept {
  const unsigned modulus = modulus_ == 0 ? 256U : modulus_;
  value = static_cast<std::uint8_t>(value % modulus);
  if (!have_last_) {
    have_last_ = true;
    last_ = value;
    missed_ = 0;
    return Error::ok;
  }
  const unsigned expected = (last_ + 1U) % modulus;
  last_ = value;
  if (value == expected) {
    missed_ = 0;
    return Error::ok;
  }
  missed_ = (value + modulus - expected) % modulus;
  return Error::counter_gap;
}

}  // namespace mrskin::protocol
