// Entry logic of the protocol fuzzers, shared by the libFuzzer targets (fuzz_*.cpp) and
// by the corpus replay test (corpus_replay.cpp) and the property tests.
//
// Every entry takes raw bytes and returns nullptr when the decoder behaved, or a short
// description of the broken invariant. The libFuzzer targets abort on a description, so
// a broken invariant is a finding just like a sanitizer report.
//
// Input formats (documented in docs/protocol.md, section "Fuzzing"):
//   packet:      the bytes are the packet (as hid_read() returns them), and walked as a
//                packed report (protocol 1.2).
//   can_classic: byte 0 = decoder node (1 + byte % 15), then records of 12 bytes:
//                flags, id (2 bytes, little-endian, not masked to 11 bits), length,
//                8 data bytes. flags bit 0: recompute the CRC-8 in data[7];
//                bit 1: force the node bits of the id to the decoder's node.
//   can_fd:      byte 0 = decoder node (1 + byte % 15), then records: flags, id (2 bytes LE), length,
//                min(length, 64) data bytes. flags bit 0: FD frame; bit 1: force node;
//                bit 2: recompute the packet's CRC-16 over its declared length.
//   quantize:    the bytes are read as little-endian doubles and integers, see
//                quantize_entry().
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <limits>
#include <span>
#include <vector>

#include "mrskin/protocol/can.hpp"
#include "mrskin/protocol/crc.hpp"
#include "mrskin/protocol/errors.hpp"
#include "mrskin/protocol/messages.hpp"
#include "mrskin/protocol/packed_report.hpp"
#include "mrskin/protocol/packet.hpp"
#include "mrskin/protocol/units.hpp"

namespace mrskin::fuzz {

namespace p = mrskin::protocol;

// ---- packets -------------------------------------------------------------------------

inline bool known_error(p::Error e) noexcept { return p::to_string(e) != "unknown error"; }

// Decodes in; a decoded packet must re-encode to exactly the bytes it came from.
inline const char* check_packet(std::span<const std::uint8_t> in) noexcept {
  const p::PacketDecoded d = p::decode_packet(in);
  if (!known_error(d.error)) return "decode_packet returned an undefined error code";
  if (d.error == p::Error::wrong_version && d.peer_version == p::kVersionMajor) {
    return "wrong_version reported for our own version";
  }
  // The framing alone: decode_packet's verdict wherever the framing fails, else ok.
  const p::Error framing = p::check_packet_framing(in);
  const bool content_error = d.error == p::Error::unknown_type || d.error == p::Error::out_of_range ||
                             (d.error == p::Error::bad_length && in.size() >= p::kPacketHeaderBytes &&
                              in[3] <= p::kPacketMaxPayload);
  if (framing != (d.error == p::Error::ok || content_error ? p::Error::ok : d.error)) {
    return "check_packet_framing disagrees with decode_packet";
  }
  if (d.error != p::Error::ok) return nullptr;
  std::array<std::uint8_t, p::kPacketMaxBytes> out{};
  const p::EncodeResult e = p::encode_packet(d.message, d.sequence, out);
  if (e.error != p::Error::ok) return "decoded packet does not re-encode";
  if (e.bytes > in.size() ||
      !std::equal(out.begin(), out.begin() + static_cast<std::ptrdiff_t>(e.bytes), in.begin())) {
    return "decoded packet re-encodes to other bytes";
  }
  return nullptr;
}

// Walks in as a packed report (protocol 1.2): every packet handed out with intact framing must
// re-encode to exactly its bytes at its offset, the walk must stay inside the input and end
// after at most one packet with broken framing, and the first packet is decode_packet's.
inline const char* check_packed_report(std::span<const std::uint8_t> in) noexcept {
  p::PacketWalker walker(in);
  p::PacketWalker skipper(in);  // skip() must step exactly as next() does
  p::PacketDecoded d;
  std::size_t packets = 0;
  std::size_t offset = 0;
  while (walker.next(d)) {
    if (!skipper.skip() || skipper.offset() != walker.offset() || skipper.broken() != walker.broken()) {
      return "PacketWalker::skip() stepped otherwise than next()";
    }
    if (p::check_packet_framing(in.subspan(offset, std::min(p::kPacketMaxBytes, in.size() - offset))) !=
            p::Error::ok &&
        !walker.broken() && in.size() <= p::kUsbSlotsMaxReportBytes) {
      return "PacketWalker went past a packet whose framing check_packet_framing refuses";
    }
    if (!known_error(d.error)) return "PacketWalker returned an undefined error code";
    if (packets == 0 && in.size() <= p::kPacketMaxBytes && d.error != p::decode_packet(in).error) {
      return "PacketWalker's first packet disagrees with decode_packet";
    }
    if (++packets > p::kUsbSlotsMaxReportBytes / (p::kPacketHeaderBytes + p::kPacketCrcBytes) + 1) {
      return "PacketWalker handed out more packets than a report holds";
    }
    if (walker.broken()) {
      if (d.error == p::Error::ok) return "PacketWalker broke on a packet that decoded";
      if (walker.next(d)) return "PacketWalker went on after a broken packet";
      break;
    }
    if (walker.offset() <= offset || walker.offset() > in.size()) return "PacketWalker's offset went wrong";
    if (d.error == p::Error::ok) {
      std::array<std::uint8_t, p::kPacketMaxBytes> out{};
      const p::EncodeResult e = p::encode_packet(d.message, d.sequence, out);
      if (e.error != p::Error::ok || e.bytes != walker.offset() - offset ||
          !std::equal(out.begin(), out.begin() + static_cast<std::ptrdiff_t>(e.bytes),
                      in.begin() + static_cast<std::ptrdiff_t>(offset))) {
        return "walked packet re-encodes to other bytes";
      }
    }
    offset = walker.offset();
  }
  if (skipper.skip()) return "PacketWalker::skip() went on after next() ended";
  return nullptr;
}

inline const char* packet_entry(const std::uint8_t* data, std::size_t size) noexcept {
  // As received. data is exactly size bytes, so ASan sees any read past the end.
  if (const char* f = check_packet({data, size})) return f;
  if (const char* f = check_packed_report({data, size})) return f;
  // Again with the CRC of every packet along the walk recomputed over its declared length, so
  // the walk reaches the packets after the first without the fuzzer solving CRC-16.
  if (size <= p::kPacketMaxBytes) {
    std::vector<std::uint8_t> packed(data, data + size);
    std::size_t at = 0;
    while (at + p::kPacketHeaderBytes + p::kPacketCrcBytes <= size && packed[at] != 0) {
      const std::size_t body = p::kPacketHeaderBytes + packed[at + 3];
      if (at + body + p::kPacketCrcBytes > size) break;
      const std::uint16_t crc = p::crc16_ccitt({packed.data() + at, body});
      packed[at + body] = static_cast<std::uint8_t>(crc & 0xFFU);
      packed[at + body + 1] = static_cast<std::uint8_t>(crc >> 8U);
      at += body + p::kPacketCrcBytes;
    }
    if (const char* f = check_packed_report(packed)) return f;
  }
  // Again with a correct CRC over the declared length, so the payload parsers are reached
  // without the fuzzer having to solve CRC-16.
  if (size >= p::kPacketHeaderBytes + p::kPacketCrcBytes && size <= p::kPacketMaxBytes) {
    std::vector<std::uint8_t> buf(data, data + size);
    const std::size_t body = p::kPacketHeaderBytes + buf[3];
    if (body + p::kPacketCrcBytes <= size) {
      const std::uint16_t crc = p::crc16_ccitt({buf.data(), body});
      buf[body] = static_cast<std::uint8_t>(crc & 0xFFU);
      buf[body + 1] = static_cast<std::uint8_t>(crc >> 8U);
      if (const char* f = check_packet(buf)) return f;
    }
  }
  return nullptr;
}

// ---- CAN -----------------------------------------------------------------------------

// Bits of bytes 0..6 of a classic single frame that carry meaning; the rest are reserved
// (sent as zero, ignored on receipt). Byte 7 (CRC) is handled by the caller.
inline std::array<std::uint8_t, 7> classic_defined_bits(const p::CanFrame& f) noexcept {
  std::array<std::uint8_t, 7> mask{};
  mask[6] = 0xF0;  // rolling counter
  const unsigned fn = (f.id >> 8U) & 0x7U;
  const unsigned block = (f.id >> 4U) & 0xFU;
  const unsigned low = f.data[6] & 0xFU;
  auto bytes = [&mask](std::size_t n) {
    for (std::size_t i = 0; i < n; ++i) mask[i] = 0xFF;
  };
  switch (static_cast<p::CanFunction>(fn)) {
    case p::CanFunction::valve_block:
    case p::CanFunction::sensor_block:
      mask[6] = 0xFF;  // counter and value count
      for (unsigned bit = 0; bit < 12 * low && bit < 48; ++bit) {
        mask[bit / 8] = static_cast<std::uint8_t>(mask[bit / 8] | (1U << (bit % 8)));
      }
      break;
    case p::CanFunction::cell_target:
      bytes(6);
      break;
    case p::CanFunction::management:
      switch (static_cast<p::CanManagement>(block)) {
        case p::CanManagement::heartbeat:
          bytes(2);
          break;
        case p::CanManagement::status:
          bytes(5);
          break;
        case p::CanManagement::time_sync:
          bytes(4);
          break;
        case p::CanManagement::state_request:
          bytes(1);
          break;
        default:
          break;
      }
      break;
    default:
      break;
  }
  return mask;
}

inline bool is_segmented_id(std::uint32_t id) noexcept {
  const unsigned fn = (id >> 8U) & 0x7U;
  const unsigned block = (id >> 4U) & 0xFU;
  return fn == static_cast<unsigned>(p::CanFunction::management) &&
         (block == static_cast<unsigned>(p::CanManagement::segmented_host_to_device) ||
          block == static_cast<unsigned>(p::CanManagement::segmented_device_to_host));
}

// Checks one decode result against the frame that produced it.
inline const char* check_can(const p::CanFrame& frame, std::uint8_t node, const p::CanDecoded& d) noexcept {
  if (!known_error(d.error)) return "CanDecoder returned an undefined error code";
  if (d.complete && d.error != p::Error::ok) {
    return "CanDecoder reported a complete message with an error";
  }
  if (d.error == p::Error::wrong_version && d.peer_version == p::kVersionMajor) {
    return "wrong_version reported for our own version";
  }
  if (!d.complete) return nullptr;
  if (frame.fd) {
    // The packet in the frame must re-encode to the same bytes, in a frame with the same id.
    const auto fn = static_cast<p::CanFunction>((frame.id >> 8U) & 0x7U);
    const p::Direction dir =
        fn == p::CanFunction::fd_host_to_device ? p::Direction::host_to_device : p::Direction::device_to_host;
    p::CanFrame re;
    if (p::encode_canfd(d.message, node, dir, d.sequence, re).error != p::Error::ok) {
      return "decoded CAN FD message does not re-encode";
    }
    if (re.id != frame.id) return "CAN FD message re-encodes with another id";
    const std::size_t n = p::kPacketHeaderBytes + re.data[3] + p::kPacketCrcBytes;
    if (n > frame.length ||
        !std::equal(re.data.begin(), re.data.begin() + static_cast<std::ptrdiff_t>(n), frame.data.begin())) {
      return "CAN FD message re-encodes to other bytes";
    }
    return nullptr;
  }
  if (is_segmented_id(frame.id)) {
    // Reassembled packet: the message must survive a packet round trip unchanged.
    std::array<std::uint8_t, p::kPacketMaxBytes> buf{};
    const p::EncodeResult e = p::encode_packet(d.message, d.sequence, buf);
    if (e.error != p::Error::ok) return "segmented message does not re-encode";
    const p::PacketDecoded again = p::decode_packet({buf.data(), e.bytes});
    if (again.error != p::Error::ok || !(again.message == d.message)) {
      return "segmented message changes in a packet round trip";
    }
    return nullptr;
  }
  // Single frame: re-encoding gives one frame equal to the input in every defined bit.
  std::array<p::CanFrame, p::kCanMaxFramesPerMessage> re{};
  const p::CanEncodeResult e = p::encode_can(d.message, node, d.counter, 0, re);
  if (e.error != p::Error::ok) return "decoded CAN frame does not re-encode";
  if (e.frames != 1) return "decoded CAN frame re-encodes to several frames";
  if (re[0].id != frame.id || re[0].length != frame.length) return "CAN frame re-encodes with another id";
  const auto mask = classic_defined_bits(frame);
  bool reserved_zero = true;
  for (std::size_t i = 0; i < mask.size(); ++i) {
    if ((re[0].data[i] & mask[i]) != (frame.data[i] & mask[i])) return "CAN frame re-encodes to other bytes";
    if ((re[0].data[i] & ~mask[i]) != 0) return "encoder set a reserved bit";
    if ((frame.data[i] & ~mask[i]) != 0) reserved_zero = false;
  }
  if (reserved_zero && re[0].data[7] != frame.data[7]) return "CAN frame re-encodes with another CRC";
  return nullptr;
}

inline std::uint32_t force_node(std::uint32_t id, std::uint8_t node) noexcept {
  return (id & ~0xFU) | (node & 0xFU);
}

// A decoder serves one valid node id, 1..15.
inline std::uint8_t decoder_node(std::uint8_t byte) noexcept {
  return static_cast<std::uint8_t>(p::kCanNodeMin + byte % p::kCanNodeMax);
}

inline const char* can_classic_entry(const std::uint8_t* data, std::size_t size) noexcept {
  if (size < 1) return nullptr;
  const auto node = decoder_node(data[0]);
  p::CanDecoder decoder(node);
  constexpr std::size_t kRecord = 12;
  for (std::size_t pos = 1; pos + kRecord <= size; pos += kRecord) {
    const std::uint8_t* r = data + pos;
    p::CanFrame f;
    f.id = static_cast<std::uint32_t>(r[1] | (r[2] << 8U));
    if ((r[0] & 2U) != 0) f.id = force_node(f.id & 0x7FFU, node);
    f.length = r[3];
    f.fd = false;
    std::copy_n(r + 4, 8, f.data.begin());
    if ((r[0] & 1U) != 0) {
      const std::array<std::uint8_t, 9> crc_in{static_cast<std::uint8_t>((f.id >> 8U) & 0x7U),
                                               static_cast<std::uint8_t>(f.id & 0xFFU),
                                               f.data[0],
                                               f.data[1],
                                               f.data[2],
                                               f.data[3],
                                               f.data[4],
                                               f.data[5],
                                               f.data[6]};
      f.data[7] = p::crc8_j1850(crc_in);
    }
    if (const char* failure = check_can(f, node, decoder.decode(f))) return failure;
  }
  return nullptr;
}

inline const char* can_fd_entry(const std::uint8_t* data, std::size_t size) noexcept {
  if (size < 1) return nullptr;
  const auto node = decoder_node(data[0]);
  p::CanDecoder decoder(node);
  std::size_t pos = 1;
  while (pos + 4 <= size) {
    const std::uint8_t* r = data + pos;
    p::CanFrame f;
    f.fd = (r[0] & 1U) != 0;
    f.id = static_cast<std::uint32_t>(r[1] | (r[2] << 8U));
    if ((r[0] & 2U) != 0) f.id = force_node(f.id & 0x7FFU, node);
    f.length = r[3];
    const std::size_t n = std::min<std::size_t>({f.length, f.data.size(), size - pos - 4});
    std::copy_n(r + 4, n, f.data.begin());
    pos += 4 + n;
    if ((r[0] & 4U) != 0 && f.length <= f.data.size()) {
      const std::size_t body = p::kPacketHeaderBytes + f.data[3];
      if (body + p::kPacketCrcBytes <= f.length) {
        const std::uint16_t crc = p::crc16_ccitt({f.data.data(), body});
        f.data[body] = static_cast<std::uint8_t>(crc & 0xFFU);
        f.data[body + 1] = static_cast<std::uint8_t>(crc >> 8U);
      }
    }
    if (const char* failure = check_can(f, node, decoder.decode(f))) return failure;
  }
  return nullptr;
}

// ---- quantisation --------------------------------------------------------------------

class ByteReader {
 public:
  ByteReader(const std::uint8_t* data, std::size_t size) noexcept : data_(data), size_(size) {}
  template <class T>
  T next() noexcept {
    // Past the end of the input the bytes read as zero.
    std::array<std::uint8_t, sizeof(T)> raw{};
    const std::size_t n = pos_ < size_ ? std::min(sizeof(T), size_ - pos_) : 0;
    if (n > 0) std::memcpy(raw.data(), data_ + pos_, n);
    pos_ += n;
    T v;
    std::memcpy(&v, raw.data(), sizeof(T));
    return v;
  }

 private:
  const std::uint8_t* data_;
  std::size_t size_;
  std::size_t pos_ = 0;
};

// |counts * lsb - value| within half an LSB (plus rounding of the products).
inline bool within_half_lsb(double dequantized, double value, double lsb) noexcept {
  const double tol =
      0.5 * lsb * (1.0 + 1e-12) + 1e-12 * std::fabs(value) + 4.0 * std::numeric_limits<double>::denorm_min();
  return std::fabs(dequantized - value) <= tol;
}

// Checks one quantisation result given the quotient the function rounds.
template <class Q>
const char* check_quantized(const Q& q, double value, double lsb, double min_counts, double max_counts,
                            double dequantized) noexcept {
  if (!known_error(q.error)) return "quantize returned an undefined error code";
  if (!std::isfinite(value) || !std::isfinite(lsb) || !(lsb > 0.0)) {
    return q.error == p::Error::not_finite ? nullptr : "NaN/Inf not refused with not_finite";
  }
  const double quotient = value / lsb;
  const bool in_range = quotient >= min_counts - 0.5 && quotient <= max_counts + 0.5;
  if (q.error == p::Error::out_of_range) {
    // Exactly at a half the rounding mode decides; both answers are right there.
    const bool edge = quotient == min_counts - 0.5 || quotient == max_counts + 0.5;
    // A count whose value overflows a double is refused too (units.hpp).
    const double nearest = std::nearbyint(quotient);
    const bool overflows = !std::isfinite(nearest * lsb);
    return (!in_range || edge || overflows) ? nullptr : "in-range value refused";
  }
  if (q.error != p::Error::ok) return "unexpected error from quantize";
  if (!in_range) return "out-of-range value accepted";
  const auto c = static_cast<double>(q.counts);
  if (c < min_counts || c > max_counts) return "counts outside their range";
  if (!within_half_lsb(dequantized, value, lsb)) return "quantisation error above half an LSB";
  return nullptr;
}

inline const char* quantize_entry(const std::uint8_t* data, std::size_t size) noexcept {
  ByteReader in(data, size);
  const auto value = in.next<double>();
  const auto lsb = in.next<double>();
  const auto max_u = in.next<std::uint16_t>();
  const auto a = in.next<std::int16_t>();
  const auto b = in.next<std::int16_t>();
  const auto current_lsb_nA = in.next<std::uint32_t>();
  const auto current_max = in.next<std::uint16_t>();
  const auto sensor_lsb_nano = in.next<std::uint32_t>();
  const auto extra1 = in.next<double>();
  const auto extra2 = in.next<double>();

  {
    const auto q = p::quantize_unsigned(value, lsb, max_u);
    if (const char* f = check_quantized(q, value, lsb, 0.0, max_u, q.counts * lsb)) return f;
  }
  {
    const auto lo = std::min(a, b);
    const auto hi = std::max(a, b);
    const auto q = p::quantize_signed(value, lsb, lo, hi);
    if (const char* f = check_quantized(q, value, lsb, lo, hi, q.counts * lsb)) return f;
  }
  p::Identity id;
  id.current_lsb_nA = current_lsb_nA;
  id.current_max_counts =
      static_cast<std::uint16_t>(std::min<std::uint16_t>(current_max, p::kCurrentCountMax));
  id.sensor_lsb_nano = sensor_lsb_nano;
  {
    const auto q = p::quantize_current(value, id);
    const double lsb_A = static_cast<double>(current_lsb_nA) * 1e-9;
    if (const char* f = check_quantized(q, value, lsb_A, 0.0, id.current_max_counts,
                                        p::current_from_counts(q.counts, id))) {
      return f;
    }
  }
  {
    const auto q = p::quantize_sensor(value, id);
    const double lsb_s = static_cast<double>(sensor_lsb_nano) * 1e-9;
    if (const char* f = check_quantized(q, value, lsb_s, p::kSensorCountMin, p::kSensorCountMax,
                                        p::sensor_from_counts(q.counts, id))) {
      return f;
    }
  }
  {
    const p::CellTargetSi si{value, lsb, extra1, extra2};
    const auto q = p::quantize_cell_target(si);
    if (!known_error(q.error)) return "quantize_cell_target returned an undefined error code";
    const bool all_finite =
        std::isfinite(value) && std::isfinite(lsb) && std::isfinite(extra1) && std::isfinite(extra2);
    // NaN/Inf is always refused; when another field is also out of range, the first bad
    // field in stiffness, offset, ceiling, validity order names the error.
    if (!all_finite && q.error != p::Error::not_finite && q.error != p::Error::out_of_range) {
      return "cell target: NaN/Inf not refused";
    }
    if (all_finite && q.error == p::Error::not_finite) return "cell target: finite values called not_finite";
    if (q.error == p::Error::ok) {
      const p::CellTargetSi back = p::cell_target_to_si(q.counts);
      if (!within_half_lsb(back.stiffness_N_per_m, si.stiffness_N_per_m, p::kStiffnessLsb_N_per_m) ||
          !within_half_lsb(back.offset_m, si.offset_m, p::kOffsetLsb_m) ||
          !within_half_lsb(back.ceiling_N, si.ceiling_N, p::kCeilingLsb_N) ||
          !within_half_lsb(back.validity_s, si.validity_s, p::kValidityLsb_s)) {
        return "cell target: quantisation error above half an LSB";
      }
      if (q.counts.stiffness > p::kStiffnessCountMax || q.counts.offset > p::kOffsetCountMax ||
          q.counts.ceiling > p::kCeilingCountMax || q.counts.validity > p::kValidityCountMax) {
        return "cell target: counts outside their range";
      }
    }
  }
  return nullptr;
}

}  // namespace mrskin::fuzz
