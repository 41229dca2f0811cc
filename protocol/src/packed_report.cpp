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

bool PacketWalker::next(PacketDecoded& out) noexcept {
  if (ended_) {
    return false;
  }
  if (report_.size() > kUsbSlotsMaxReportBytes) {
    out = PacketDecoded{};
    out.error = Error::too_long;
    broken_ = ended_ = true;
    return true;
  }
  if (offset_ >= report_.size() || report_[offset_] == 0x00) {
    ended_ = true;
    return false;
  }
  // A packet is at most kPacketMaxBytes, whatever the report's size (UsbSlots: up to 1024).
  const std::span<const std::uint8_t> rest =
      report_.subspan(offset_, std::min(kPacketMaxBytes, report_.size() - offset_));
  out = decode_packet(rest);
  // decode_packet checks the framing (length, version, CRC) before the content: these errors
  // come after the CRC matched, so the packet's length is the one its sender wrote.
  const bool framing_holds = out.error == Error::ok || out.error == Error::unknown_type ||
                             out.error == Error::out_of_range ||
                             (out.error == Error::bad_length && rest[3] <= kPacketMaxPayload);
  if (!framing_holds) {
    broken_ = ended_ = true;
    return true;
  }
  offset_ += kPacketHeaderBytes + rest[3] + kPacketCrcBytes;
  return true;
}

}  // namespace mrskin::protocol
