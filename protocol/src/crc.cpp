#include "mrskin/protocol/crc.hpp"

#include <array>

namespace mrskin::protocol {
namespace {

// CRC-16/CCITT (poly 0x1021, MSB first) by table: the bitwise loop cost ~3k instructions of the
// 5x5 bridge tick (two frames a tick). kCrc16Tables[0] is the one-byte step; kCrc16Tables[k] the
// effect of a byte followed by k zero bytes, so four bytes take four independent lookups (the
// register meets the first two bytes, the last two meet nothing): "slicing by 4", 35 -> about 15
// instructions per 4 bytes here.
using Crc16Table = std::array<std::uint16_t, 256>;

constexpr std::array<Crc16Table, 4> make_crc16_tables() noexcept {
  std::array<Crc16Table, 4> t{};
  for (std::size_t i = 0; i < 256; ++i) {
    auto crc = static_cast<std::uint16_t>(i << 8U);
    for (int bit = 0; bit < 8; ++bit) {
      crc = (crc & 0x8000U) != 0 ? static_cast<std::uint16_t>((crc << 1U) ^ 0x1021U)
                                 : static_cast<std::uint16_t>(crc << 1U);
    }
    t[0][i] = crc;
  }
  for (std::size_t k = 1; k < t.size(); ++k) {
    for (std::size_t i = 0; i < 256; ++i) {
      const std::uint16_t prev = t[k - 1][i];  // one more zero byte through the register
      t[k][i] = static_cast<std::uint16_t>((prev << 8U) ^ t[0][prev >> 8U]);
    }
  }
  return t;
}

constexpr std::array<Crc16Table, 4> kCrc16Tables = make_crc16_tables();

}  // namespace

std::uint16_t crc16_ccitt(std::span<const std::uint8_t> data, std::uint16_t crc) noexcept {
  const Crc16Table& t0 = kCrc16Tables[0];
  const std::uint8_t* p = data.data();
  std::size_t n = data.size();
  for (; n >= 4; n -= 4, p += 4) {
    const unsigned hi = ((crc >> 8U) ^ p[0]) & 0xFFU;
    const unsigned lo = (crc ^ p[1]) & 0xFFU;
    crc = static_cast<std::uint16_t>(kCrc16Tables[3][hi] ^ kCrc16Tables[2][lo] ^ kCrc16Tables[1][p[2]] ^
                                     t0[p[3]]);
  }
  for (; n > 0; --n, ++p) {
    crc = static_cast<std::uint16_t>((crc << 8U) ^ t0[((crc >> 8U) ^ *p) & 0xFFU]);
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
