// Why a stream source dropped a sample or a message: one list for every source (udp://,
// replay://, igtl://, igtl-listen://), counted per reason in SourceStats and BridgeStats.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <string_view>

namespace mrskin::bridge {

enum class DropReason : unsigned char {
  format,        // not this format or version: bad magic, header version, a line that does not parse
  length,        // a size that does not match its type (short, body size, value count)
  crc,           // checksum mismatch
  oversized,     // larger than the format or the options allow
  type,          // a message type this source does not use (STATUS, STRING, ...)
  device,        // a message from a device or tool name that is not configured
  unit,          // a unit that is not a force (SENSOR: newton with any prefix)
  non_finite,    // NaN or Inf in a value
  out_of_range,  // a value outside SourceOptions' ranges
  stamp,         // a robot stamp outside 0..2^62 ns
  out_of_order,  // a robot stamp older than the last accepted one
  duplicate,     // a robot stamp equal to the last accepted one
  superseded,    // queued, then replaced by a newer sample before the tick took it
};
inline constexpr std::size_t kDropReasonCount = 13;

// Samples dropped per reason, indexed by DropReason.
using DropCounts = std::array<std::uint64_t, kDropReasonCount>;

// The reason's key in statistics and logs ("device", "out_of_order", ...).
[[nodiscard]] constexpr std::string_view drop_reason_name(DropReason r) noexcept {
  constexpr std::array<std::string_view, kDropReasonCount> kNames{
      "format",     "length",       "crc",   "oversized",    "type",      "device",    "unit",
      "non_finite", "out_of_range", "stamp", "out_of_order", "duplicate", "superseded"};
  return kNames.at(static_cast<std::size_t>(r));
}

}  // namespace mrskin::bridge
