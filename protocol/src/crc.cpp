#include "mrskin/protocol/crc.hpp"

namespace mrskin::protocol {

std::uint16_t crc16_ccitt(std::span<const std::uint8_t> data, std::uint16_t crc) noexcept {
  for (const std::uint8_t byte : data) {
    crc = static_cast<std::uint16_t>(crc ^ (static_cast<std::uint16_t>(byte) << 8U));
    for (int bit = 0; bit < 8; ++bit) {
      crc = (crc & 0x8000U) != 0 ? static_cast<std::uint16_t>((crc << 1U) ^ 0x1021U)
                                 : static_cast<std::uint16_t>(crc << 1U);
    }
  }
  return crc;
}

std::uint8_t crc8_j1850(std::span<const std::uint8_t> data) noexcept {
  std::uint8_t crc = 0xFF;
  for (const std::uint8_t byte : data) {
    crc ^= byte;
    for (int bit = 0; bit < 8; ++bit) {
      crc = (crc & 0x80U) != 0 ? static_cast<std::uint8_t>((crc << 1U) ^ 0x1DU)
                               : static_cast<std::uint8_t>(crc << 1U);
    }
  }
  return static_cast<std::uint8_t>(crc ^ 0xFFU);
}

}  // namespace mrskin::protocol
