#include "mrskin/protocol/usb.hpp"

#include <cstdio>

namespace mrskin::protocol {

std::string format_usb_serial(std::uint32_t serial) {
  std::array<char, 9> text{};
  (void)std::snprintf(text.data(), text.size(), "%08X", static_cast<unsigned>(serial));
  return {text.data(), 8};
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
