// Checksums of protocol v1.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>

#include "mrskin/protocol/export.hpp"

namespace mrskin::protocol {

// CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final xor.
// Check value over "123456789" is 0x29B1.
MRSKIN_PROTOCOL_API std::uint16_t crc16_ccitt(std::span<const std::uint8_t> data,
                                              std::uint16_t crc = 0xFFFF) noexcept;

// CRC-8/SAE-J1850: poly 0x1D, init 0xFF, no reflection, final xor 0xFF.
// Check value over "123456789" is 0x4B.
MRSKIN_PROTOCOL_API std::uint8_t crc8_j1850(std::span<const std::uint8_t> data) noexcept;

}  // namespace mrskin::protocol
