#include "mrskin/protocol/usb.hpp"

#include <cmath>
#include <cstddef>

namespace mrskin::protocol {

std::string format_usb_serial(std::uint32_t serial) {
  static constexpr char kHex[] = "0123456789ABCDEF";
  std::string text(8, '0');
  for (std::size_t i = 0; i < 8; ++i) {
    text[7 - i] = kHex[(serial >> (4U * i)) & 0xFU];
  }
  return text;
}

UsbSlots usb_slots_message(const UsbInterruptSlots& slots) noexcept {
  UsbSlots m;
  m.report_bytes = static_cast<std::uint16_t>(slots.report_bytes);
  m.reports_per_interval = static_cast<std::uint8_t>(slots.reports_per_interval);
  m.interval_us = static_cast<std::uint16_t>(std::lround(slots.interval_s * 1e6));
  return m;
}

std::optional<std::uint32_t> parse_usb_serial(std::string_view text) noexcept {
  if (text.size() != 8) {
    return std::nullopt;
  }
  std::uint32_t value = 0;
  for (const char c : text) {
    std::uint32_t digit = 0;
    if (c >= '0' && c <= '9') {
      digit = static_cast<std::uint32_t>(c - '0');
    } else if (c >= 'a' && c <= 'f') {
      digit = static_cast<std::uint32_t>(c - 'a' + 10);
    } else if (c >= 'A' && c <= 'F') {
      digit = static_cast<std::uint32_t>(c - 'A' + 10);
    } else {
      return std::nullopt;
    }
    value = (value << 4U) | digit;
  }
  return value;
}

}  // namespace mrskin::protocol
