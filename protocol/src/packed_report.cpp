#include "mrskin/protocol/packed_report.hpp"

#include <algorithm>
#include <array>

namespace mrskin::protocol {

EncodeResult append_packet(const Message& message, std::uint8_t sequence, std::span<std::uint8_t> report,
                           std::size_t used) noexcept {
  if (used > report.size()) {
    return {Error::short_buffer, 0};
  }
  std::array<std::uint8_t, kPacketMaxBytes> packet{};
  const EncodeResult r = encode_packet(message, sequence, packet);
  if (r.error != Error::ok) {
    return r;
  }
  if (r.bytes > report.size() - used) {
    return {Error::short_buffer, 0};
  }
  std::copy_n(packet.begin(), r.bytes, report.begin() + static_cast<std::ptrdiff_t>(used));
  if (used + r.bytes < report.size()) {
    report[used + r.bytes] = 0x00;  // ends the report
  }
  return r;
}

PacketWalker::Start PacketWalker::start(std::span<const std::uint8_t>& rest) noexcept {
  if (ended_) {
    return Start::ended;
  }
  if (report_.size() > kUsbSlotsMaxReportBytes) {
    broken_ = ended_ = true;
    return Start::oversized;
  }
  if (offset_ >= report_.size() || report_[offset_] == 0x00) {
    ended_ = true;
    return Start::ended;
  }
  // A packet is at most kPacketMaxBytes, whatever the report's size (UsbSlots: up to 1024).
  rest = report_.subspan(offset_, std::min(kPacketMaxBytes, report_.size() - offset_));
  return Start::packet;
}

void PacketWalker::finish(std::span<const std::uint8_t> rest, bool framing_holds) noexcept {
  if (!framing_holds) {
    broken_ = ended_ = true;
    return;
  }
  offset_ += kPacketHeaderBytes + rest[3] + kPacketCrcBytes;
}

bool PacketWalker::next(PacketDecoded& out) noexcept {
  std::span<const std::uint8_t> rest;
  switch (start(rest)) {
    case Start::ended:
      return false;
    case Start::oversized:
      out = PacketDecoded{};
      out.error = Error::too_long;
      return true;
    case Start::packet:
      break;
  }
  out = decode_packet(rest);
  // decode_packet checks the framing (length, version, CRC) before the content: these errors
  // come after the CRC matched, so the packet's length is the one its sender wrote.
  finish(rest, out.error == Error::ok || out.error == Error::unknown_type ||
                   out.error == Error::out_of_range ||
                   (out.error == Error::bad_length && rest[3] <= kPacketMaxPayload));
  return true;
}

bool PacketWalker::skip() noexcept {
  std::span<const std::uint8_t> rest;
  switch (start(rest)) {
    case Start::ended:
      return false;
    case Start::oversized:
      return true;
    case Start::packet:
      break;
  }
  finish(rest, check_packet_framing(rest) == Error::ok);
  return true;
}

}  // namespace mrskin::protocol
