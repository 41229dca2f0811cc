// Error codes of protocol v1 decode and encode. Never exceptions: the codec runs on the
// real-time path.
#pragma once

#include <cstdint>
#include <string_view>

namespace mrskin::protocol {

enum class Error : std::uint8_t {
  ok = 0,
  short_buffer,   // input ends before the frame does, or output buffer too small
  too_long,       // input longer than the framing allows
  bad_crc,        // checksum mismatch
  unknown_type,   // message type or CAN identifier not defined in v1
  wrong_version,  // peer speaks another protocol major version
  out_of_range,   // a field holds a value outside its documented range
  counter_gap,    // rolling counter or sequence number skipped
  not_finite,     // NaN or Inf handed to quantisation
  bad_length,     // length field disagrees with the message type
  wrong_node,     // CAN frame addressed to another node
  bad_segment,    // segmented transfer out of order or malformed
};

constexpr std::string_view to_string(Error e) noexcept {
  switch (e) {
    case Error::ok:
      return "ok";
    case Error::short_buffer:
      return "short buffer";
    case Error::too_long:
      return "too long";
    case Error::bad_crc:
      return "bad CRC";
    case Error::unknown_type:
      return "unknown message type";
    case Error::wrong_version:
      return "wrong protocol version";
    case Error::out_of_range:
      return "field out of range";
    case Error::counter_gap:
      return "counter gap";
    case Error::not_finite:
      return "NaN or Inf";
    case Error::bad_length:
      return "bad length";
    case Error::wrong_node:
      return "frame for another node";
    case Error::bad_segment:
      return "bad segment";
  }
  return "unknown error";
}

}  // namespace mrskin::protocol
