#include "mrskin/protocol/crc.hpp"

#include <array>

namespace mrskin::protocol {
namespace {

// CRC-16/CCITT (poly 0x1021, MSB first), one table step per byte: the bitwise loop cost ~3k
// instructions of the 5x5 bridge tick (two frames a tick).
constexpr std::array<std::uint16_t, 256> make_crc16_table() noexcept {
  std::array<std::uint16_t, 256> table{};
  for (std::size_t i = 0; i < table.size(); ++i) {
    auto crc = static_cast<std::uint16_t>(i << 8U);
    for (int bit = 0; bit < 8; ++bit) {
      crc = (crc & 0x8000U) != 0 ? static_cast<std::uint16_t>((crc << 1U) ^ 0x1021U)
                                 : static_cast<std::uint16_t>(crc << 1U);
    }
    table[i] = crc;
  }
  return table;
}

constexpr std::array<std::uint16_t, 256> kCrc16Table = make_crc16_table();

}  // namespace

std::uint16_t crc16_ccitt(std::span<const std::uint8_t> data, std::uint16_t crc) noexcept {
  for (const std::uint8_t byte : data) {
    crc = static_cast<std::uint16_t>((crc << 8U) ^ kCrc16Table[((crc >> 8U) ^ byte) & 0xFFU]);
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
