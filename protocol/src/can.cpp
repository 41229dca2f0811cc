#include "mrskin/protocol/can.hpp"

#include <algorithm>
#include <utility>

#include "mrskin/protocol/crc.hpp"
#include "mrskin/protocol/packed_report.hpp"
#include "validate.hpp"

namespace mrskin::protocol {
namespace {

constexpr std::size_t kClassicBytes = 8;
constexpr std::size_t kSingleFirstDataBytes = 7;
constexpr std::size_t kFirstFrameDataBytes = 6;
constexpr std::size_t kConsecutiveDataBytes = 7;

// Little-endian bit packing inside bytes 0..5 of a single frame.
void put_bits(std::array<std::uint8_t, 64>& d, unsigned bit, unsigned width, std::uint32_t value) noexcept {
  for (unsigned i = 0; i < width; ++i) {
    const unsigned b = bit + i;
    const auto mask = static_cast<std::uint8_t>(1U << (b % 8U));
    if (((value >> i) & 1U) != 0) {
      d[b / 8U] = static_cast<std::uint8_t>(d[b / 8U] | mask);
    } else {
      d[b / 8U] = static_cast<std::uint8_t>(d[b / 8U] & ~mask);
    }
  }
}
std::uint32_t get_bits(const std::array<std::uint8_t, 64>& d, unsigned bit, unsigned width) noexcept {
  std::uint32_t v = 0;
  for (unsigned i = 0; i < width; ++i) {
    const unsigned b = bit + i;
    v |= static_cast<std::uint32_t>((d[b / 8U] >> (b % 8U)) & 1U) << i;
  }
  return v;
}

std::uint8_t frame_crc(const CanFrame& f) noexcept {
  std::array<std::uint8_t, 9> buf{};
  buf[0] = static_cast<std::uint8_t>((f.id >> 8U) & 0x7U);
  buf[1] = static_cast<std::uint8_t>(f.id & 0xFFU);
  std::copy_n(f.data.begin(), 7, buf.begin() + 2);
  return crc8_j1850(buf);
}

CanFrame single(CanFunction fn, std::uint8_t block, std::uint8_t node, std::uint8_t counter,
                std::uint8_t low_nibble) noexcept {
  CanFrame f;
  f.id = can_id(fn, block, node);
  f.length = kClassicBytes;
  f.data[6] = static_cast<std::uint8_t>(((counter & 0xFU) << 4U) | (low_nibble & 0xFU));
  return f;
}
void seal(CanFrame& f) noexcept { f.data[7] = frame_crc(f); }

bool is_segmented(const Message& m) noexcept {
  return std::holds_alternative<IdentifyRequest>(m) || std::holds_alternative<Identity>(m) ||
         std::holds_alternative<ConfigRead>(m) || std::holds_alternative<ConfigData>(m) ||
         std::holds_alternative<ConfigWrite>(m) || std::holds_alternative<ConfigAck>(m) ||
         std::holds_alternative<UsbSlots>(m) || std::holds_alternative<SensorDeadband>(m);
}
bool host_to_device(const Message& m) noexcept {
  return std::holds_alternative<IdentifyRequest>(m) || std::holds_alternative<ConfigRead>(m) ||
         std::holds_alternative<ConfigWrite>(m) || std::holds_alternative<ValveCurrents>(m) ||
         std::holds_alternative<CellTargets>(m) || std::holds_alternative<Heartbeat>(m) ||
         std::holds_alternative<StateRequest>(m);
}

CanEncodeResult encode_segmented(const Message& m, std::uint8_t node, std::uint8_t sequence,
                                 std::span<CanFrame> out) noexcept {
  std::array<std::uint8_t, kPacketMaxBytes> packet{};
  const EncodeResult enc = encode_packet(m, sequence, packet);
  if (enc.error != Error::ok) {
    return {enc.error, 0};
  }
  const auto block = static_cast<std::uint8_t>(host_to_device(m) ? CanManagement::segmented_host_to_device
                                                                 : CanManagement::segmented_device_to_host);
  const std::uint32_t id = can_id(CanFunction::management, block, node);
  const std::size_t total = enc.bytes;
  std::size_t frames = 1;
  if (total > kSingleFirstDataBytes) {
    frames += (total - kFirstFrameDataBytes + kConsecutiveDataBytes - 1) / kConsecutiveDataBytes;
  }
  if (out.size() < frames) {
    return {Error::short_buffer, 0};
  }
  if (total <= kSingleFirstDataBytes) {
    CanFrame& f = out[0];
    f = CanFrame{};
    f.id = id;
    f.length = kClassicBytes;
    f.data[0] = static_cast<std::uint8_t>(total);
    std::copy_n(packet.begin(), total, f.data.begin() + 1);
    return {Error::ok, 1};
  }
  CanFrame& first = out[0];
  first = CanFrame{};
  first.id = id;
  first.length = kClassicBytes;
  first.data[0] = static_cast<std::uint8_t>(0x10U | ((total >> 8U) & 0xFU));
  first.data[1] = static_cast<std::uint8_t>(total & 0xFFU);
  std::copy_n(packet.begin(), kFirstFrameDataBytes, first.data.begin() + 2);
  std::size_t pos = kFirstFrameDataBytes;
  for (std::size_t i = 1; i < frames; ++i) {
    CanFrame& f = out[i];
    f = CanFrame{};
    f.id = id;
    f.length = kClassicBytes;
    f.data[0] = static_cast<std::uint8_t>(0x20U | (i & 0xFU));
    const std::size_t n = std::min(kConsecutiveDataBytes, total - pos);
    std::copy_n(packet.begin() + static_cast<std::ptrdiff_t>(pos), n, f.data.begin() + 1);
    pos += n;
  }
  return {Error::ok, frames};
}

// The message a classic frame carries once its CRC checked: valve and sensor blocks, one cell's
// target, or a management frame (heartbeat, status, time sync, state request).
Error decode_cyclic(std::uint8_t fn, std::uint8_t block, std::uint8_t low,
                    const std::array<std::uint8_t, 64>& d, Message& out) noexcept {
  switch (static_cast<CanFunction>(fn)) {
    case CanFunction::valve_block: {
      if (low == 0 || low > kCanValuesPerBlock) {
        return Error::out_of_range;
      }
      ValveCurrents v;
      v.first = static_cast<std::uint16_t>(block * kCanValuesPerBlock);
      v.count = low;
      for (unsigned i = 0; i < low; ++i) {
        v.counts[i] = static_cast<std::uint16_t>(get_bits(d, 12 * i, 12));
      }
      out = Message(std::move(v));
      break;
    }
    case CanFunction::sensor_block: {
      if (low == 0 || low > kCanValuesPerBlock) {
        return Error::out_of_range;
      }
      Telemetry t;
      t.first = static_cast<std::uint16_t>(block * kCanValuesPerBlock);
      t.count = low;
      for (unsigned i = 0; i < low; ++i) {
        const std::uint32_t raw = get_bits(d, 12 * i, 12);
        t.counts[i] =
            static_cast<std::int16_t>(raw >= 0x800U ? static_cast<int>(raw) - 0x1000 : static_cast<int>(raw));
      }
      out = Message(std::move(t));
      break;
    }
    case CanFunction::cell_target: {
      CellTargets c;
      c.first = static_cast<std::uint16_t>(block | (get_bits(d, 44, 4) << 4U));
      c.count = 1;
      c.targets[0].stiffness = static_cast<std::uint16_t>(get_bits(d, 0, 14));
      c.targets[0].offset = static_cast<std::uint16_t>(get_bits(d, 14, 12));
      c.targets[0].ceiling = static_cast<std::uint16_t>(get_bits(d, 26, 12));
      c.targets[0].validity = static_cast<std::uint8_t>(get_bits(d, 38, 6));
      out = Message(std::move(c));
      break;
    }
    case CanFunction::management: {
      switch (static_cast<CanManagement>(block)) {
        case CanManagement::heartbeat:
          out = Message(Heartbeat{static_cast<std::uint16_t>(d[0] | (d[1] << 8U))});
          break;
        case CanManagement::status:
          out = Message(Status{d[0], d[1], static_cast<std::uint16_t>(d[2] | (d[3] << 8U)), d[4]});
          break;
        case CanManagement::time_sync:
          out = Message(TimeSync{static_cast<std::uint32_t>(d[0]) | (static_cast<std::uint32_t>(d[1]) << 8U) |
                                 (static_cast<std::uint32_t>(d[2]) << 16U) |
                                 (static_cast<std::uint32_t>(d[3]) << 24U)});
          break;
        case CanManagement::state_request:
          out = Message(StateRequest{d[0]});
          break;
        default:
          return Error::unknown_type;
      }
      break;
    }
    default:
      return Error::unknown_type;
  }
  return Error::ok;
}

}  // namespace

CanEncodeResult encode_can(const Message& message, std::uint8_t node, std::uint8_t counter,
                           std::uint8_t sequence, std::span<CanFrame> out) noexcept {
  if (node < kCanNodeMin || node > kCanNodeMax) {
    return {Error::out_of_range, 0};
  }
  if (const Error e = detail::validate(message); e != Error::ok) {
    return {e, 0};
  }
  if (is_segmented(message)) {
    return encode_segmented(message, node, sequence, out);
  }
  if (const auto* v = std::get_if<ValveCurrents>(&message)) {
    if (v->first % kCanValuesPerBlock != 0) {
      return {Error::out_of_range, 0};
    }
    const std::size_t frames = (v->count + kCanValuesPerBlock - 1) / kCanValuesPerBlock;
    const std::size_t first_block = v->first / kCanValuesPerBlock;
    if (first_block + frames > kCanMaxBlocks) {
      return {Error::out_of_range, 0};
    }
    if (out.size() < frames) {
      return {Error::short_buffer, 0};
    }
    for (std::size_t b = 0; b < frames; ++b) {
      const std::size_t n = std::min(kCanValuesPerBlock, v->count - b * kCanValuesPerBlock);
      CanFrame f = single(CanFunction::valve_block, static_cast<std::uint8_t>(first_block + b), node, counter,
                          static_cast<std::uint8_t>(n));
      for (std::size_t i = 0; i < n; ++i) {
        put_bits(f.data, static_cast<unsigned>(12 * i), 12, v->counts[b * kCanValuesPerBlock + i]);
      }
      seal(f);
      out[b] = f;
    }
    return {Error::ok, frames};
  }
  if (const auto* t = std::get_if<Telemetry>(&message)) {
    if (t->first % kCanValuesPerBlock != 0) {
      return {Error::out_of_range, 0};
    }
    const std::size_t frames = (t->count + kCanValuesPerBlock - 1) / kCanValuesPerBlock;
    const std::size_t first_block = t->first / kCanValuesPerBlock;
    if (first_block + frames > kCanMaxBlocks) {
      return {Error::out_of_range, 0};
    }
    if (out.size() < frames) {
      return {Error::short_buffer, 0};
    }
    for (std::size_t b = 0; b < frames; ++b) {
      const std::size_t n = std::min(kCanValuesPerBlock, t->count - b * kCanValuesPerBlock);
      CanFrame f = single(CanFunction::sensor_block, static_cast<std::uint8_t>(first_block + b), node,
                          counter, static_cast<std::uint8_t>(n));
      for (std::size_t i = 0; i < n; ++i) {
        const auto raw = static_cast<std::uint16_t>(t->counts[b * kCanValuesPerBlock + i]) & 0xFFFU;
        put_bits(f.data, static_cast<unsigned>(12 * i), 12, raw);
      }
      seal(f);
      out[b] = f;
    }
    return {Error::ok, frames};
  }
  if (const auto* c = std::get_if<CellTargets>(&message)) {
    if (c->first + c->count - 1 > kCellIndexMaxCan) {
      return {Error::out_of_range, 0};
    }
    if (out.size() < c->count) {
      return {Error::short_buffer, 0};
    }
    for (std::size_t i = 0; i < c->count; ++i) {
      const auto cell = static_cast<std::uint32_t>(c->first + i);
      const CellTarget& t = c->targets[i];
      CanFrame f = single(CanFunction::cell_target, static_cast<std::uint8_t>(cell & 0xFU), node, counter, 0);
      put_bits(f.data, 0, 14, t.stiffness);
      put_bits(f.data, 14, 12, t.offset);
      put_bits(f.data, 26, 12, t.ceiling);
      put_bits(f.data, 38, 6, t.validity);
      put_bits(f.data, 44, 4, cell >> 4U);
      seal(f);
      out[i] = f;
    }
    return {Error::ok, c->count};
  }
  if (out.empty()) {
    return {Error::short_buffer, 0};
  }
  CanFrame f;
  if (const auto* h = std::get_if<Heartbeat>(&message)) {
    f = single(CanFunction::management, static_cast<std::uint8_t>(CanManagement::heartbeat), node, counter,
               0);
    f.data[0] = static_cast<std::uint8_t>(h->counter & 0xFFU);
    f.data[1] = static_cast<std::uint8_t>(h->counter >> 8U);
  } else if (const auto* s = std::get_if<Status>(&message)) {
    f = single(CanFunction::management, static_cast<std::uint8_t>(CanManagement::status), node, counter, 0);
    f.data[0] = s->state;
    f.data[1] = s->fault;
    f.data[2] = static_cast<std::uint8_t>(s->fault_detail & 0xFFU);
    f.data[3] = static_cast<std::uint8_t>(s->fault_detail >> 8U);
    f.data[4] = s->flags;
  } else if (const auto* ts = std::get_if<TimeSync>(&message)) {
    f = single(CanFunction::management, static_cast<std::uint8_t>(CanManagement::time_sync), node, counter,
               0);
    for (unsigned i = 0; i < 4; ++i) {
      f.data[i] = static_cast<std::uint8_t>((ts->device_time_us >> (8U * i)) & 0xFFU);
    }
  } else if (const auto* r = std::get_if<StateRequest>(&message)) {
    f = single(CanFunction::management, static_cast<std::uint8_t>(CanManagement::state_request), node,
               counter, 0);
    f.data[0] = r->request;
  } else {
    return {Error::unknown_type, 0};
  }
  seal(f);
  out[0] = f;
  return {Error::ok, 1};
}

CanEncodeResult encode_canfd(const Message& message, std::uint8_t node, Direction direction,
                             std::uint8_t sequence, CanFrame& out) noexcept {
  if (node < kCanNodeMin || node > kCanNodeMax) {
    return {Error::out_of_range, 0};
  }
  CanFrame f;
  const EncodeResult enc = encode_packet(message, sequence, f.data);
  if (enc.error != Error::ok) {
    return {enc.error, 0};
  }
  f.fd = true;
  f.id = can_id(direction == Direction::host_to_device ? CanFunction::fd_host_to_device
                                                       : CanFunction::fd_device_to_host,
                0, node);
  f.length = static_cast<std::uint8_t>(canfd_padded_length(enc.bytes));
  out = f;
  return {Error::ok, 1};
}

CanEncodeResult encode_canfd_report(std::span<const std::uint8_t> report, std::uint8_t node,
                                    Direction direction, CanFrame& out) noexcept {
  if (node < kCanNodeMin || node > kCanNodeMax) {
    return {Error::out_of_range, 0};
  }
  if (report.size() > kPacketMaxBytes) {
    return {Error::too_long, 0};  // one FD frame holds 64 bytes (a USB report may hold 1024)
  }
  PacketWalker walker(report);
  PacketDecoded p;
  std::size_t packets = 0;
  while (walker.next(p)) {
    if (p.error != Error::ok) {
      return {p.error, 0};
    }
    ++packets;
  }
  if (packets == 0) {
    return {Error::short_buffer, 0};
  }
  CanFrame f;
  f.fd = true;
  f.id = can_id(direction == Direction::host_to_device ? CanFunction::fd_host_to_device
                                                       : CanFunction::fd_device_to_host,
                0, node);
  std::copy_n(report.begin(), walker.offset(), f.data.begin());
  f.length = static_cast<std::uint8_t>(canfd_padded_length(walker.offset()));
  out = f;
  return {Error::ok, 1};
}

CanDecoded CanDecoder::decode(const CanFrame& frame) noexcept {
  CanDecoded result;
  if (frame.id > 0x7FFU) {
    result.error = Error::unknown_type;
    return result;
  }
  if (frame.length > (frame.fd ? 64U : 8U)) {
    result.error = Error::too_long;
    return result;
  }
  const auto node = static_cast<std::uint8_t>(frame.id & 0xFU);
  const auto block = static_cast<std::uint8_t>((frame.id >> 4U) & 0xFU);
  const auto fn = static_cast<std::uint8_t>((frame.id >> 8U) & 0x7U);
  if (node != node_) {
    result.error = Error::wrong_node;
    return result;
  }
  if (frame.fd || fn == static_cast<std::uint8_t>(CanFunction::fd_host_to_device) ||
      fn == static_cast<std::uint8_t>(CanFunction::fd_device_to_host)) {
    if (!frame.fd || block != 0 ||
        (fn != static_cast<std::uint8_t>(CanFunction::fd_host_to_device) &&
         fn != static_cast<std::uint8_t>(CanFunction::fd_device_to_host))) {
      result.error = Error::unknown_type;
      return result;
    }
    const PacketDecoded p = decode_packet(std::span<const std::uint8_t>(frame.data.data(), frame.length));
    result.error = p.error;
    result.sequence = p.sequence;
    result.peer_version = p.peer_version;
    result.message = p.message;
    result.complete = p.error == Error::ok;
    return result;
  }
  if (frame.length != kClassicBytes) {
    result.error = frame.length < kClassicBytes ? Error::short_buffer : Error::too_long;
    return result;
  }
  if (fn == static_cast<std::uint8_t>(CanFunction::management) &&
      (block == static_cast<std::uint8_t>(CanManagement::segmented_host_to_device) ||
       block == static_cast<std::uint8_t>(CanManagement::segmented_device_to_host))) {
    return decode_segment(
        frame, reassembly_[block - static_cast<std::uint8_t>(CanManagement::segmented_host_to_device)]);
  }
  if (frame_crc(frame) != frame.data[7]) {
    result.error = Error::bad_crc;
    return result;
  }
  result.counter = static_cast<std::uint8_t>(frame.data[6] >> 4U);
  const auto low = static_cast<std::uint8_t>(frame.data[6] & 0xFU);
  result.error = decode_cyclic(fn, block, low, frame.data, result.message);
  if (result.error != Error::ok) {
    return result;
  }
  result.error = detail::validate(result.message);
  result.complete = result.error == Error::ok;
  return result;
}

CanDecoded CanDecoder::decode_segment(const CanFrame& frame, Reassembly& r) noexcept {
  CanDecoded result;
  const auto& d = frame.data;
  const unsigned pci = d[0] >> 4U;
  std::size_t chunk = 0;
  const std::uint8_t* src = nullptr;
  if (pci == 0) {
    const std::size_t len = d[0] & 0xFU;
    if (len == 0 || len > kSingleFirstDataBytes) {
      result.error = Error::bad_segment;
      return result;
    }
    r = Reassembly{};
    r.expected = len;
    r.active = true;
    chunk = len;
    src = &d[1];
  } else if (pci == 1) {
    const std::size_t len = ((d[0] & 0xFU) << 8U) | d[1];
    if (len <= kSingleFirstDataBytes || len > kPacketMaxBytes) {
      r.active = false;
      result.error = len > kPacketMaxBytes ? Error::too_long : Error::bad_segment;
      return result;
    }
    r = Reassembly{};
    r.expected = len;
    r.active = true;
    r.next_index = 1;
    chunk = kFirstFrameDataBytes;
    src = &d[2];
  } else if (pci == 2) {
    if (!r.active || (d[0] & 0xFU) != (r.next_index & 0xFU)) {
      r.active = false;
      result.error = Error::bad_segment;
      return result;
    }
    r.next_index = static_cast<std::uint8_t>(r.next_index + 1U);
    chunk = std::min(kConsecutiveDataBytes, r.expected - r.received);
    src = &d[1];
  } else {
    r.active = false;
    result.error = Error::bad_segment;
    return result;
  }
  std::copy_n(src, chunk, r.buffer.begin() + static_cast<std::ptrdiff_t>(r.received));
  r.received += chunk;
  if (r.received < r.expected) {
    return result;  // ok, not complete
  }
  r.active = false;
  const PacketDecoded p = decode_packet(std::span<const std::uint8_t>(r.buffer.data(), r.expected));
  result.error = p.error;
  result.sequence = p.sequence;
  result.peer_version = p.peer_version;
  result.message = p.message;
  result.complete = p.error == Error::ok;
  return result;
}

std::size_t can_frame_bits_worst_case(std::size_t data_bytes, bool fd) noexcept {
  if (!fd) {
    // SOF..CRC is 34 + 8n bits and may be stuffed; delimiters, ACK, EOF and IFS are 13.
    const std::size_t stuffable = 34 + 8 * data_bytes;
    return stuffable + (stuffable - 1) / 4 + 13;
  }
  // FD base format at one bit rate: SOF..data (1+11+1+1+1+1+1+1+4 = 22 + 8n) stuffed
  // dynamically; stuff count (4) and CRC (17 or 21) carry fixed stuff bits every 4 bits.
  const std::size_t n = canfd_padded_length(data_bytes);
  const std::size_t dynamic = 22 + 8 * n;
  const std::size_t crc = n <= 16 ? 17 : 21;
  const std::size_t fixed_field = 4 + crc;
  return dynamic + (dynamic - 1) / 4 + fixed_field + (fixed_field + 3) / 4 + 13;
}

CanFrameBits can_frame_bits_by_phase_worst_case(std::size_t data_bytes, bool fd) noexcept {
  const std::size_t total = can_frame_bits_worst_case(data_bytes, fd);
  if (!fd) {
    return {total, 0};
  }
  constexpr std::size_t kSofToBrs = 17;         // SOF, 11-bit id, RRS, IDE, FDF, res, BRS
  constexpr std::size_t kAckToIfs = 2 + 7 + 3;  // ACK slot and delimiter, EOF, intermission
  constexpr std::size_t kNominal = kSofToBrs + (kSofToBrs - 1) / 4 + kAckToIfs;
  return {kNominal, total - kNominal};
}

double can_frame_time_worst_case_s(std::size_t data_bytes, bool fd, double nominal_bitrate_bit_per_s,
                                   double data_bitrate_bit_per_s) noexcept {
  const CanFrameBits bits = can_frame_bits_by_phase_worst_case(data_bytes, fd);
  const double data_s =
      bits.data_bits == 0 ? 0.0 : static_cast<double>(bits.data_bits) / data_bitrate_bit_per_s;
  return static_cast<double>(bits.nominal_bits) / nominal_bitrate_bit_per_s + data_s;
}

std::uint16_t CanDeltaBlocks::select(std::span<const std::uint16_t, kValues> values, std::size_t first_block,
                                     std::size_t end_block) noexcept {
  if (end_block > kCanMaxBlocks || first_block >= end_block) {
    return 0;
  }
  const auto block_values = [](auto& array, std::size_t b) {
    return std::span(array).subspan(b * kCanValuesPerBlock, kCanValuesPerBlock);
  };
  std::uint16_t changed = 0;
  for (std::size_t b = first_block; b < end_block; ++b) {
    const auto now = block_values(values, b);
    const auto sent = block_values(sent_, b);
    if (!std::equal(now.begin(), now.end(), sent.begin())) {
      changed = static_cast<std::uint16_t>(changed | (1U << b));
    }
  }
  const bool refresh = repeat_refreshes_ && changed == 0;  // the host's same values again
  std::uint16_t send = 0;
  for (std::size_t b = first_block; b < end_block; ++b) {
    const bool due = unsent_updates_[b] == kNeverSent || unsent_updates_[b] + 1U >= kCanDeltaRefreshUpdates;
    if (refresh || due || (changed & (1U << b)) != 0) {
      send = static_cast<std::uint16_t>(send | (1U << b));
      const auto now = block_values(values, b);
      std::copy(now.begin(), now.end(), block_values(sent_, b).begin());
      unsent_updates_[b] = 0;
    } else {
      ++unsent_updates_[b];
    }
  }
  return send;
}

}  // namespace mrskin::protocol
