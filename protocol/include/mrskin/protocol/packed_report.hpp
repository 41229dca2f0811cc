// Protocol 1.2: several packets back to back in one USB-HID report or CAN FD frame
// (docs/protocol.md, "Packed reports"). Each packet keeps its own header and CRC; the first
// byte after the last packet is 0x00 (padding), which ends the report, since a version byte is
// never 0. A 1.1 receiver reads the first packet and takes the rest for padding, so a sender
// packs only after its peer declared 1.2 (reads_packed_reports). Pure byte functions: no I/O,
// no allocation, no exceptions.
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <span>

#include "mrskin/protocol/errors.hpp"
#include "mrskin/protocol/export.hpp"
#include "mrskin/protocol/messages.hpp"
#include "mrskin/protocol/packet.hpp"

namespace mrskin::protocol {

// The first minor version of major 1 that reads packed reports.
inline constexpr std::uint8_t kPackedReportsMinor = 2;

// Whether a peer that declared major.minor (IdentifyRequest or Identity) reads packed reports.
constexpr bool reads_packed_reports(std::uint8_t major, std::uint8_t minor) noexcept {
  return major == kVersionMajor && minor >= kPackedReportsMinor;
}

// Appends message as one packet at report[used ..]. ok with bytes = the packet's length, and a
// 0x00 written after it when room is left (so a reused buffer stays terminated); short_buffer
// when it does not fit (or used > report.size()), with report unchanged; the encoder's field
// errors otherwise.
MRSKIN_PROTOCOL_API EncodeResult append_packet(const Message& message, std::uint8_t sequence,
                                               std::span<std::uint8_t> report, std::size_t used) noexcept;

// A report's first packet, as a 1.0 or 1.1 receiver reads a report: decode_packet over its first
// kPacketMaxBytes bytes (the rest is padding to it, whatever the report's size).
inline PacketDecoded decode_first_packet(std::span<const std::uint8_t> report) noexcept {
  return decode_packet(report.first(std::min(report.size(), kPacketMaxBytes)));
}

// Walks the packets of one report (a hid_read() report, a CAN FD frame's data), in order; each
// packet gets decode_packet's checks. The walk ends at the end of the bytes or at a 0x00 where a
// packet would start. A packet whose framing holds (version, length within the report, CRC) but
// whose content is refused (unknown_type: a later minor version's message; bad_length for its
// type; out_of_range) is handed out with its error and the walk goes on past it. A packet whose
// framing is broken (short_buffer, wrong_version, bad_length over 58, bad_crc) is handed out
// with its error and ends the walk: its length cannot be trusted, so nothing after it is read.
// The packets before it were handed out already. A report longer than kUsbSlotsMaxReportBytes
// (the largest a unit may declare) gives one too_long.
class MRSKIN_PROTOCOL_API PacketWalker {
 public:
  explicit PacketWalker(std::span<const std::uint8_t> report) noexcept : report_(report) {}
  // The next packet (out.error says whether it decoded), or false when the walk has ended.
  bool next(PacketDecoded& out) noexcept;
  // Steps over the next packet exactly as next() would (offset(), broken() and the end the
  // same), checking only its framing (check_packet_framing): a count of a report's packets
  // without decoding their content. False when the walk has ended.
  bool skip() noexcept;
  // Bytes of the report the walk has consumed: the packets with intact framing so far.
  [[nodiscard]] std::size_t offset() const noexcept { return offset_; }
  // The walk ended on a packet with broken framing (or a report over kUsbSlotsMaxReportBytes).
  [[nodiscard]] bool broken() const noexcept { return broken_; }

 private:
  enum class Start : unsigned char { packet, ended, oversized };
  // Not part of the ABI (hidden: the library inlines them into next() and skip()).
  // Where the walk stands before a packet: its bytes in rest, the end, or a report too long.
  __attribute__((visibility("hidden"))) Start start(std::span<const std::uint8_t>& rest) noexcept;
  // Past the packet when its framing held; else the walk ends on it, broken.
  __attribute__((visibility("hidden"))) void finish(std::span<const std::uint8_t> rest,
                                                    bool framing_holds) noexcept;

  std::span<const std::uint8_t> report_;
  std::size_t offset_ = 0;
  bool broken_ = false;
  bool ended_ = false;
};

}  // namespace mrskin::protocol
