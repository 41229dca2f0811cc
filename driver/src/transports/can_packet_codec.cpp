// CanPacketCodec: protocol-v1 packets to classic CAN or CAN FD frames and back, and the receive
// filters of each role (docs/protocol.md, "Classic CAN" and "CAN FD").
#include <linux/can.h>

#include <algorithm>
#include <variant>

#include "mrskin/driver/transports/can.hpp"
#include "mrskin/protocol/packed_report.hpp"

namespace mrskin {
namespace proto = mrskin::protocol;

// ============================================================================ codec

namespace {

bool sent_by_host(const proto::Message& m) noexcept {
  return std::holds_alternative<proto::IdentifyRequest>(m) ||
         std::holds_alternative<proto::ValveCurrents>(m) || std::holds_alternative<proto::CellTargets>(m) ||
         std::holds_alternative<proto::Heartbeat>(m) || std::holds_alternative<proto::StateRequest>(m) ||
         std::holds_alternative<proto::ConfigRead>(m) || std::holds_alternative<proto::ConfigWrite>(m);
}
bool sent_by_device(const proto::Message& m) noexcept {
  return std::holds_alternative<proto::Identity>(m) || std::holds_alternative<proto::Telemetry>(m) ||
         std::holds_alternative<proto::TimeSync>(m) || std::holds_alternative<proto::Status>(m) ||
         std::holds_alternative<proto::Heartbeat>(m) || std::holds_alternative<proto::ConfigData>(m) ||
         std::holds_alternative<proto::ConfigAck>(m) || std::holds_alternative<proto::UsbSlots>(m) ||
         std::holds_alternative<proto::SensorDeadband>(m);
}
bool sent_by(CanRole role, const proto::Message& m) noexcept {
  return role == CanRole::host ? sent_by_host(m) : sent_by_device(m);
}

constexpr auto fn_of(std::uint32_t id) noexcept { return static_cast<std::uint8_t>((id >> 8U) & 0x7U); }
constexpr auto block_of(std::uint32_t id) noexcept { return static_cast<std::uint8_t>((id >> 4U) & 0xFU); }
constexpr std::uint8_t u8(proto::CanFunction f) noexcept { return static_cast<std::uint8_t>(f); }
constexpr std::uint8_t u8(proto::CanManagement m) noexcept { return static_cast<std::uint8_t>(m); }

// Whether a frame identifier is one the other side of role sends.
bool from_peer(CanRole role, std::uint32_t id) noexcept {
  const std::uint8_t fn = fn_of(id);
  const std::uint8_t block = block_of(id);
  using F = proto::CanFunction;
  using M = proto::CanManagement;
  if (role == CanRole::host) {
    return (fn == u8(F::management) && (block == u8(M::status) || block == u8(M::time_sync) ||
                                        block == u8(M::segmented_device_to_host))) ||
           fn == u8(F::sensor_block) || fn == u8(F::fd_device_to_host);
  }
  return (fn == u8(F::management) && (block == u8(M::heartbeat) || block == u8(M::state_request) ||
                                      block == u8(M::segmented_host_to_device))) ||
         fn == u8(F::valve_block) || fn == u8(F::cell_target) || fn == u8(F::fd_host_to_device);
}

bool is_segmented_id(std::uint32_t id) noexcept {
  return fn_of(id) == u8(proto::CanFunction::management) &&
         (block_of(id) == u8(proto::CanManagement::segmented_host_to_device) ||
          block_of(id) == u8(proto::CanManagement::segmented_device_to_host));
}

}  // namespace

CanPacketCodec::CanPacketCodec(CanRole role, std::uint8_t node, bool fd) noexcept
    : role_(role), node_(node), fd_(fd), decoder_(node), delta_(role == CanRole::host) {}

proto::Error CanPacketCodec::check(CanRole role, bool fd, std::span<const std::uint8_t> packet) noexcept {
  CanPacketCodec scratch(role, proto::kCanNodeMin, fd);
  std::array<proto::CanFrame, kMaxFrames> frames{};
  return scratch.encode(packet, frames).error;
}

CanPacketCodec::Encoded CanPacketCodec::encode(std::span<const std::uint8_t> packet,
                                               std::span<proto::CanFrame, kMaxFrames> out) noexcept {
  // The packets of the datagram: one in protocol 1.1, several in a packed report (1.2), at most 64
  // bytes on CAN (only a USB report is longer).
  if (packet.size() > proto::kPacketMaxBytes) {
    return {proto::Error::too_long, 0};
  }
  proto::PacketWalker walker(packet);
  proto::PacketDecoded p;
  std::size_t packets = 0;
  while (walker.next(p)) {
    if (p.error != proto::Error::ok) {
      return {p.error, 0};
    }
    if (!sent_by(role_, p.message)) {
      return {proto::Error::unknown_type, 0};
    }
    ++packets;
  }
  if (packets == 0) {
    return {proto::decode_packet(packet).error, 0};  // the error a lone packet would give
  }
  note_handshake(packet, role_);
  if (fd_ && packets > 1) {
    const auto dir =
        role_ == CanRole::host ? proto::Direction::host_to_device : proto::Direction::device_to_host;
    const proto::CanEncodeResult r = proto::encode_canfd_report(packet, node_, dir, out[0]);
    return {r.error, r.frames};
  }
  // Classic CAN keeps its frames: each packet as if it came alone.
  Encoded all;
  proto::PacketWalker again(packet);
  while (again.next(p)) {
    const Encoded e = encode_one(p, std::span<proto::CanFrame>(out).subspan(all.frames));
    if (e.error != proto::Error::ok) {
      return {e.error, 0};
    }
    all.frames += e.frames;
    all.unsent += e.unsent;
  }
  return all;
}

CanPacketCodec::Encoded CanPacketCodec::encode_one(const proto::PacketDecoded& p,
                                                   std::span<proto::CanFrame> out) noexcept {
  const proto::Message& m = p.message;
  if (fd_) {
    if (out.empty()) {
      return {proto::Error::too_long, 0};
    }
    const auto dir =
        role_ == CanRole::host ? proto::Direction::host_to_device : proto::Direction::device_to_host;
    const proto::CanEncodeResult r = proto::encode_canfd(m, node_, dir, p.sequence, out[0]);
    return {r.error, r.frames};
  }
  if (std::holds_alternative<proto::ValveCurrents>(m) || std::holds_alternative<proto::Telemetry>(m)) {
    return encode_blocks(m, out);
  }
  std::uint8_t counter = 0;
  if (std::holds_alternative<proto::Heartbeat>(m)) {
    if (role_ == CanRole::device) {
      return {proto::Error::ok, 0, 1};  // classic CAN has no heartbeat echo
    }
    counter = tx_heartbeat_++;
  } else if (std::holds_alternative<proto::CellTargets>(m)) {
    counter = tx_cells_++;
  } else if (std::holds_alternative<proto::StateRequest>(m) || std::holds_alternative<proto::Status>(m)) {
    counter = tx_state_++;
  } else if (std::holds_alternative<proto::TimeSync>(m)) {
    counter = tx_blocks_++;
  }
  const proto::CanEncodeResult r =
      proto::encode_can(m, node_, static_cast<std::uint8_t>(counter & 0xFU), p.sequence, out);
  return {r.error == proto::Error::short_buffer ? proto::Error::too_long : r.error, r.frames};
}

CanPacketCodec::Encoded CanPacketCodec::encode_blocks(const proto::Message& m,
                                                      std::span<proto::CanFrame> out) noexcept {
  const auto* v = std::get_if<proto::ValveCurrents>(&m);
  const auto* t = std::get_if<proto::Telemetry>(&m);
  const std::size_t first = v != nullptr ? v->first : t->first;
  const std::size_t count = v != nullptr ? v->count : t->count;
  if (first + count > kBlockValues) {
    return {proto::Error::out_of_range, 0};
  }
  const std::size_t end = first + count;
  const std::size_t blocks = (end + proto::kCanValuesPerBlock - 1) / proto::kCanValuesPerBlock -
                             first / proto::kCanValuesPerBlock + (t != nullptr ? 1U : 0U);
  if (blocks > out.size()) {
    return {proto::Error::too_long, 0};
  }
  for (std::size_t i = 0; i < count; ++i) {
    shadow_[first + i] = v != nullptr ? v->counts[i] : static_cast<std::uint16_t>(t->counts[i]);
  }
  const std::size_t first_block = first / proto::kCanValuesPerBlock;
  const std::size_t end_block = (end + proto::kCanValuesPerBlock - 1) / proto::kCanValuesPerBlock;
  // 1.2 deltas: the blocks that go (every one in 1.1; see CanDeltaBlocks).
  const std::uint16_t send = delta_blocks() ? delta_.select(shadow_, first_block, end_block) : 0xFFFFU;
  const auto counter = static_cast<std::uint8_t>(tx_blocks_ & 0xFU);
  ++tx_blocks_;
  std::size_t n = 0;
  if (t != nullptr) {
    const proto::CanEncodeResult r =
        proto::encode_can(proto::TimeSync{t->device_time_us}, node_, counter, 0, out.subspan(0, 1));
    if (r.error != proto::Error::ok) {
      return {r.error, 0};
    }
    n = 1;
  }
  for (std::size_t b = first_block; b < end_block; ++b) {
    if ((send & (1U << b)) == 0) {
      continue;
    }
    const std::size_t start = b * proto::kCanValuesPerBlock;
    const auto values = static_cast<std::uint8_t>(std::min(proto::kCanValuesPerBlock, end - start));
    const proto::Message block = v != nullptr ? proto::Message(valve_block(start, values))
                                              : proto::Message(sensor_block(start, values));
    const proto::CanEncodeResult r = proto::encode_can(block, node_, counter, 0, out.subspan(n, 1));
    if (r.error != proto::Error::ok) {
      return {r.error, 0};
    }
    ++n;
  }
  return {proto::Error::ok, n};
}

proto::ValveCurrents CanPacketCodec::valve_block(std::size_t start, std::uint8_t values) const noexcept {
  proto::ValveCurrents c;
  c.first = static_cast<std::uint16_t>(start);
  c.count = values;
  std::copy_n(shadow_.begin() + static_cast<std::ptrdiff_t>(start), values, c.counts.begin());
  return c;
}

proto::Telemetry CanPacketCodec::sensor_block(std::size_t start, std::uint8_t values) const noexcept {
  proto::Telemetry s;
  s.first = static_cast<std::uint16_t>(start);
  s.count = values;
  for (std::size_t i = 0; i < values; ++i) {
    s.counts[i] = static_cast<std::int16_t>(shadow_[start + i]);
  }
  return s;
}

void CanPacketCodec::finish(Decoded& d, const proto::Message& message, std::uint8_t sequence) noexcept {
  const proto::EncodeResult r = proto::encode_packet(message, sequence, d.packet.bytes);
  d.error = r.error;
  d.complete = r.error == proto::Error::ok;
  d.packet.length = static_cast<std::uint8_t>(r.bytes);
}

CanPacketCodec::Decoded CanPacketCodec::decode(const proto::CanFrame& frame) noexcept {
  Decoded out;
  if (frame.id > 0x7FFU) {
    out.error = proto::Error::unknown_type;
    return out;
  }
  if ((frame.id & 0xFU) != node_) {
    out.error = proto::Error::wrong_node;
    return out;
  }
  if (!from_peer(role_, frame.id)) {
    out.error = proto::Error::unknown_type;  // our own direction: another host, or an echo
    return out;
  }
  const proto::CanDecoded d = decoder_.decode(frame);
  if (d.error != proto::Error::ok) {
    out.error = d.error;
    // A frame of our node that did not arrive whole: the session should see a gap.
    if (d.error != proto::Error::unknown_type) {
      ++lost_;
    }
    return out;
  }
  if (!d.complete) {
    return out;  // a segmented transfer goes on
  }
  const proto::Message& m = d.message;
  if (!sent_by(role_ == CanRole::host ? CanRole::device : CanRole::host, m)) {
    out.error = proto::Error::unknown_type;
    return out;
  }
  note_handshake(m, false);
  if (frame.fd) {
    // The peer's own packet and sequence, end to end.
    finish(out, m, d.sequence);
    rx_sequence_ = static_cast<std::uint8_t>(d.sequence + 1U);
    lost_ = 0;
    const std::size_t first = out.packet.length;
    if (first < frame.length && frame.data[first] != 0x00) {
      // A packed report (protocol 1.2): the frame's packets as they came; the session walks them.
      std::copy_n(frame.data.begin(), frame.length, out.packet.bytes.begin());
      out.packet.length = frame.length;
    }
    return out;
  }
  proto::Message handed = m;
  if (role_ == CanRole::host && !is_segmented_id(frame.id)) {
    if (const auto* ts = std::get_if<proto::TimeSync>(&m)) {
      if (sample_counter_.accept(d.counter) == proto::Error::counter_gap) {
        lost_ = std::max(lost_, sample_counter_.missed());  // a refused frame may be the one missed
      }
      have_time_ = true;
      time_counter_ = d.counter;
      time_us_ = ts->device_time_us;
      return out;  // stamps the sensor blocks that follow
    }
    if (auto* t = std::get_if<proto::Telemetry>(&handed)) {
      if (!have_time_ || d.counter != time_counter_) {
        ++lost_;  // its TimeSync was lost: the sample's time is unknown
        out.error = proto::Error::counter_gap;
        return out;
      }
      t->device_time_us = time_us_;
    } else if (std::holds_alternative<proto::Status>(m)) {
      if (status_counter_.accept(d.counter) == proto::Error::counter_gap) {
        lost_ = std::max(lost_, status_counter_.missed());
      }
    }
  }
  // Never a skip of 255 (mod 256 the session would read it as a duplicate).
  constexpr std::uint32_t kMaxSkip = 128;
  const auto sequence = static_cast<std::uint8_t>(rx_sequence_ + std::min(lost_, kMaxSkip));
  finish(out, handed, sequence);
  rx_sequence_ = static_cast<std::uint8_t>(sequence + 1U);
  lost_ = 0;
  return out;
}

void CanPacketCodec::reset() noexcept {
  decoder_ = proto::CanDecoder(node_);
  sample_counter_.reset();
  status_counter_.reset();
  have_time_ = false;
  lost_ = 0;
  peer_major_ = peer_minor_ = 0;
  delta_.reset();
}

bool CanPacketCodec::delta_blocks() const noexcept {
  return !fd_ && proto::reads_delta_blocks(own_major_, own_minor_) &&
         proto::reads_delta_blocks(peer_major_, peer_minor_);
}

void CanPacketCodec::note_handshake(std::span<const std::uint8_t> packet, CanRole sender) noexcept {
  // The handshake's packets go first in their report (and alone on CAN): only the first is read,
  // and only when its type byte says IdentifyRequest or Identity.
  constexpr std::size_t kTypeByte = 1;
  if (packet.size() <= kTypeByte ||
      (packet[kTypeByte] != static_cast<std::uint8_t>(proto::MessageType::identify_request) &&
       packet[kTypeByte] != static_cast<std::uint8_t>(proto::MessageType::identity))) {
    return;
  }
  const proto::PacketDecoded p = proto::decode_first_packet(packet);
  if (p.error == proto::Error::ok) {
    note_handshake(p.message, sender == role_);
  }
}

void CanPacketCodec::note_handshake(const proto::Message& m, bool own) noexcept {
  std::uint8_t major = 0;
  std::uint8_t minor = 0;
  if (const auto* request = std::get_if<proto::IdentifyRequest>(&m)) {
    major = request->host_major;
    minor = request->host_minor;
    // A new handshake: the unit's answer decides again, and every block goes at its next update.
    if (own) {
      peer_major_ = peer_minor_ = 0;
    }
    delta_.reset();
  } else if (const auto* id = std::get_if<proto::Identity>(&m)) {
    major = id->proto_major;
    minor = id->proto_minor;
  } else {
    return;
  }
  (own ? own_major_ : peer_major_) = major;
  (own ? own_minor_ : peer_minor_) = minor;
}

CanIdFilters can_receive_filters(CanRole role, std::uint8_t node) noexcept {
  // Standard data frames only: the EFF and RTR flags are part of every mask.
  constexpr std::uint32_t kExact = CAN_SFF_MASK | CAN_EFF_FLAG | CAN_RTR_FLAG;
  constexpr std::uint32_t kAnyBlock = (CAN_SFF_MASK & ~0xF0U) | CAN_EFF_FLAG | CAN_RTR_FLAG;
  using F = proto::CanFunction;
  using M = proto::CanManagement;
  CanIdFilters f;
  const auto add = [&f, node](F fn, std::uint8_t block, std::uint32_t mask) {
    f.filters[f.count++] = CanIdFilter{proto::can_id(fn, block, node), mask};
  };
  if (role == CanRole::host) {
    add(F::management, u8(M::status), kExact);
    add(F::management, u8(M::time_sync), kExact);
    add(F::management, u8(M::segmented_device_to_host), kExact);
    add(F::sensor_block, 0, kAnyBlock);
    add(F::fd_device_to_host, 0, kExact);
  } else {
    add(F::management, u8(M::heartbeat), kExact);
    add(F::management, u8(M::state_request), kExact);
    add(F::management, u8(M::segmented_host_to_device), kExact);
    add(F::valve_block, 0, kAnyBlock);
    add(F::cell_target, 0, kAnyBlock);
    add(F::fd_host_to_device, 0, kExact);
  }
  return f;
}

}  // namespace mrskin
