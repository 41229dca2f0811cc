// Packet framing: one message per USB-HID report or CAN FD frame.
//   [0] protocol major version  [1] type  [2] sequence  [3] payload length N (<= 58)
//   [4 .. 4+N)  payload, little-endian
//   [4+N .. 6+N) CRC-16/CCITT-FALSE over bytes [0, 4+N), little-endian
// Bytes after the CRC are zero padding and are ignored on decode.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>

#include "mrskin/protocol/errors.hpp"
#include "mrskin/protocol/export.hpp"
#include "mrskin/protocol/messages.hpp"

namespace mrskin::protocol {

inline constexpr std::size_t kPacketHeaderBytes = 4;
inline constexpr std::size_t kPacketCrcBytes = 2;
inline constexpr std::size_t kPacketMaxBytes = 64;
inline constexpr std::size_t kPacketMaxPayload = kPacketMaxBytes - kPacketHeaderBytes - kPacketCrcBytes;

// USB-HID: the device uses no report IDs, so every report is 64 data bytes on the wire.
// hidapi's hid_write() wants the report-ID byte 0x00 in front (65 bytes), and hid_read()
// returns the 64 data bytes without it. libusb interrupt transfers carry the 64 bytes.
inline constexpr std::size_t kHidReportBytes = 64;
inline constexpr std::uint8_t kHidReportId = 0x00;

struct EncodeResult {
  Error error = Error::ok;
  std::size_t bytes = 0;  // bytes written (the packet, without padding)
};

struct PacketDecoded {
  Error error = Error::ok;
  std::uint8_t sequence = 0;
  std::uint8_t peer_version = 0;  // the version byte seen, named when error == wrong_version
  Message message{};
};

// Writes the packet into out (at least its length). Fields are range-checked.
MRSKIN_PROTOCOL_API EncodeResult encode_packet(const Message& message, std::uint8_t sequence,
                                               std::span<std::uint8_t> out) noexcept;

// Encodes into a full 64-byte HID report, zero padded.
MRSKIN_PROTOCOL_API EncodeResult encode_hid_report(const Message& message, std::uint8_t sequence,
                                                   std::span<std::uint8_t, kHidReportBytes> report) noexcept;

// Decodes a packet at the start of in; in may carry trailing padding up to 64 bytes.
MRSKIN_PROTOCOL_API PacketDecoded decode_packet(std::span<const std::uint8_t> in) noexcept;

// decode_packet's framing checks alone, in its order (too_long, short_buffer, wrong_version,
// bad_length over kPacketMaxPayload, short_buffer, bad_crc): ok when the packet's length and
// CRC can be trusted, whatever its content. No payload is decoded.
MRSKIN_PROTOCOL_API Error check_packet_framing(std::span<const std::uint8_t> in) noexcept;

// Smallest CAN FD data length (0-8, 12, 16, 20, 24, 32, 48, 64) holding n bytes.
MRSKIN_PROTOCOL_API std::size_t canfd_padded_length(std::size_t n) noexcept;

// Payload length of a message in packet framing, or 0 when it is malformed.
MRSKIN_PROTOCOL_API std::size_t packet_payload_length(const Message& message) noexcept;

// Detects gaps in a modular counter (8-bit sequences, 4-bit CAN counters).
class MRSKIN_PROTOCOL_API CounterTracker {
 public:
  explicit CounterTracker(std::uint8_t modulus = 0) noexcept : modulus_(modulus) {}
  // Returns ok for the first value and for last+1; counter_gap otherwise (value is taken).
  Error accept(std::uint8_t value) noexcept;
  // Counts missed values in the last gap (0 when in sequence).
  [[nodiscard]] std::uint32_t missed() const noexcept { return missed_; }
  void reset() noexcept { have_last_ = false; }

 private:
  std::uint8_t modulus_;  // 0 means 256
  std::uint8_t last_ = 0;
  bool have_last_ = false;
  std::uint32_t missed_ = 0;
};

}  // namespace mrskin::protocol
