#include "mrskin/protocol/units.hpp"

#include <cmath>

namespace mrskin::protocol {

Quantized<std::uint16_t> quantize_unsigned(double value, double lsb, std::uint16_t max_counts) noexcept {
  if (!std::isfinite(value) || !std::isfinite(lsb) || lsb <= 0.0) {
    return {Error::not_finite, 0};
  }
  const double c = std::nearbyint(value / lsb);
  // A count whose value overflows a double (c * lsb = Inf) could never be read back.
  if (c < 0.0 || c > static_cast<double>(max_counts) || !std::isfinite(c * lsb)) {
    return {Error::out_of_range, 0};
  }
  return {Error::ok, static_cast<std::uint16_t>(c)};
}

Quantized<std::int16_t> quantize_signed(double value, double lsb, std::int16_t min_counts,
                                        std::int16_t max_counts) noexcept {
  if (!std::isfinite(value) || !std::isfinite(lsb) || lsb <= 0.0) {
    return {Error::not_finite, 0};
  }
  const double c = std::nearbyint(value / lsb);
  if (c < static_cast<double>(min_counts) || c > static_cast<double>(max_counts) || !std::isfinite(c * lsb)) {
    return {Error::out_of_range, 0};
  }
  return {Error::ok, static_cast<std::int16_t>(c)};
}

Quantized<std::uint16_t> quantize_current(double current_A, const Identity& id) noexcept {
  return quantize_unsigned(current_A, static_cast<double>(id.current_lsb_nA) * 1e-9, id.current_max_counts);
}

double current_from_counts(std::uint16_t counts, const Identity& id) noexcept {
  return static_cast<double>(counts) * static_cast<double>(id.current_lsb_nA) * 1e-9;
}

double sensor_from_counts(std::int16_t counts, const Identity& id) noexcept {
  return static_cast<double>(counts) * static_cast<double>(id.sensor_lsb_nano) * 1e-9;
}

Quantized<std::int16_t> quantize_sensor(double value, const Identity& id) noexcept {
  return quantize_signed(value, static_cast<double>(id.sensor_lsb_nano) * 1e-9, kSensorCountMin,
                         kSensorCountMax);
}

Quantized<CellTarget> quantize_cell_target(const CellTargetSi& si) noexcept {
  const auto k = quantize_unsigned(si.stiffness_N_per_m, kStiffnessLsb_N_per_m, kStiffnessCountMax);
  const auto x = quantize_unsigned(si.offset_m, kOffsetLsb_m, kOffsetCountMax);
  const auto f = quantize_unsigned(si.ceiling_N, kCeilingLsb_N, kCeilingCountMax);
  const auto v = quantize_unsigned(si.validity_s, kValidityLsb_s, kValidityCountMax);
  for (const Error e : {k.error, x.error, f.error, v.error}) {
    if (e != Error::ok) {
      return {e, {}};
    }
  }
  return {Error::ok, CellTarget{k.counts, x.counts, f.counts, static_cast<std::uint8_t>(v.counts)}};
}

CellTargetSi cell_target_to_si(const CellTarget& t) noexcept {
  return {t.stiffness * kStiffnessLsb_N_per_m, t.offset * kOffsetLsb_m, t.ceiling * kCeilingLsb_N,
          t.validity * kValidityLsb_s};
}

}  // namespace mrskin::protocol
