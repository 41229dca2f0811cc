// SI <-> wire count conversion. Every encode path from SI goes through these, so NaN, Inf
// and out-of-range values are refused here with a code, before a byte is written.
#pragma once

#include <cstdint>

#include "mrskin/protocol/errors.hpp"
#include "mrskin/protocol/export.hpp"
#include "mrskin/protocol/messages.hpp"

namespace mrskin::protocol {

inline constexpr double kStiffnessLsb_N_per_m = 2.0;
inline constexpr double kOffsetLsb_m = 2e-6;
inline constexpr double kCeilingLsb_N = 1e-3;
inline constexpr double kValidityLsb_s = 10e-3;

template <class T>
struct Quantized {
  Error error = Error::ok;
  T counts{};
};

// Rounds value/lsb to the nearest count in [0, max_counts]; out_of_range also when that count
// times lsb overflows a double (1.7e308 with an LSB of 1e308 rounds to 2 counts, 2e308 = Inf).
MRSKIN_PROTOCOL_API Quantized<std::uint16_t> quantize_unsigned(double value, double lsb,
                                                               std::uint16_t max_counts) noexcept;
// Rounds value/lsb to the nearest count in [min_counts, max_counts].
MRSKIN_PROTOCOL_API Quantized<std::int16_t> quantize_signed(double value, double lsb, std::int16_t min_counts,
                                                            std::int16_t max_counts) noexcept;

// Coil current in amperes, with the LSB and maximum the device declared in its Identity.
MRSKIN_PROTOCOL_API Quantized<std::uint16_t> quantize_current(double current_A, const Identity& id) noexcept;
MRSKIN_PROTOCOL_API double current_from_counts(std::uint16_t counts, const Identity& id) noexcept;

// Sensor reading in its SI unit.
MRSKIN_PROTOCOL_API double sensor_from_counts(std::int16_t counts, const Identity& id) noexcept;
MRSKIN_PROTOCOL_API Quantized<std::int16_t> quantize_sensor(double value, const Identity& id) noexcept;

struct CellTargetSi {
  double stiffness_N_per_m = 0.0;
  double offset_m = 0.0;
  double ceiling_N = 0.0;
  double validity_s = 0.0;
};
MRSKIN_PROTOCOL_API Quantized<CellTarget> quantize_cell_target(const CellTargetSi& si) noexcept;
MRSKIN_PROTOCOL_API CellTargetSi cell_target_to_si(const CellTarget& t) noexcept;

}  // namespace mrskin::protocol
