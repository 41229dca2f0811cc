#include "mrskin/protocol/usb.hpp"

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
