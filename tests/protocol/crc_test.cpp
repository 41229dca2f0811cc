// CRC check values of the catalogue (reveng): CRC-16/CCITT-FALSE and CRC-8/SAE-J1850.
#include "mrskin/protocol/crc.hpp"

#include <gtest/gtest.h>

#include <array>
#include <cstdint>
#include <random>
#include <span>
#include <string_view>
#include <vector>

namespace {

using namespace mrskin::protocol;

std::span<const std::uint8_t> bytes(std::string_view s) {
  return {reinterpret_cast<const std::uint8_t*>(s.data()), s.size()};
}

TEST(ProtocolCrc, Crc16CcittFalseCheckValue) { EXPECT_EQ(crc16_ccitt(bytes("123456789")), 0x29B1); }

TEST(ProtocolCrc, Crc16EmptyIsInit) { EXPECT_EQ(crc16_ccitt({}), 0xFFFF); }

TEST(ProtocolCrc, Crc16CanBeChained) {
  // The optional second argument continues a running CRC.
  EXPECT_EQ(crc16_ccitt(bytes("56789"), crc16_ccitt(bytes("1234"))), 0x29B1);
}

TEST(ProtocolCrc, Crc16KnownVectors) {
  // Independent values: a single zero byte and "A" under CRC-16/CCITT-FALSE.
  const std::array<std::uint8_t, 1> zero{0x00};
  EXPECT_EQ(crc16_ccitt(zero), 0xE1F0);
  EXPECT_EQ(crc16_ccitt(bytes("A")), 0xB915);
}

// The table walk (four bytes at a time, then one) against the bitwise definition, on every
// length up to 70 (each remainder of four), from random starting registers.
TEST(ProtocolCrc, Crc16MatchesTheBitwiseDefinitionAtEveryLength) {
  const auto bitwise = [](std::span<const std::uint8_t> data, std::uint16_t crc) {
    for (const std::uint8_t byte : data) {
      crc = static_cast<std::uint16_t>(crc ^ (byte << 8U));
      for (int bit = 0; bit < 8; ++bit) {
        crc = (crc & 0x8000U) != 0 ? static_cast<std::uint16_t>((crc << 1U) ^ 0x1021U)
                                   : static_cast<std::uint16_t>(crc << 1U);
      }
    }
    return crc;
  };
  std::mt19937 rng(16);
  std::vector<std::uint8_t> data(70);
  for (int round = 0; round < 20; ++round) {
    for (std::uint8_t& b : data) {
      b = static_cast<std::uint8_t>(rng());
    }
    const auto init = static_cast<std::uint16_t>(rng());
    for (std::size_t n = 0; n <= data.size(); ++n) {
      const std::span<const std::uint8_t> d(data.data(), n);
      ASSERT_EQ(crc16_ccitt(d, init), bitwise(d, init)) << n << " bytes, init " << init;
    }
  }
}

TEST(ProtocolCrc, Crc8SaeJ1850CheckValue) { EXPECT_EQ(crc8_j1850(bytes("123456789")), 0x4B); }

TEST(ProtocolCrc, Crc8EmptyIsInitXorOut) { EXPECT_EQ(crc8_j1850({}), 0x00); }

TEST(ProtocolCrc, Crc8DetectsEverySingleBitFlip) {
  std::array<std::uint8_t, 9> frame{0x01, 0x15, 0x11, 0x22, 0x33, 0x44, 0x55, 0x66, 0x94};
  const std::uint8_t good = crc8_j1850(frame);
  for (std::size_t byte = 0; byte < frame.size(); ++byte) {
    for (unsigned bit = 0; bit < 8; ++bit) {
      frame[byte] = static_cast<std::uint8_t>(frame[byte] ^ (1U << bit));
      EXPECT_NE(crc8_j1850(frame), good) << byte << ':' << bit;
      frame[byte] = static_cast<std::uint8_t>(frame[byte] ^ (1U << bit));
    }
  }
}

}  // namespace
