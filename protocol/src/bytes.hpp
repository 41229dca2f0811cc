// Bounds-checked little-endian cursor over a span. Internal to the codec.
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <span>
#include <type_traits>

namespace mrskin::protocol::detail {

class Writer {
 public:
  explicit Writer(std::span<std::uint8_t> out) noexcept : out_(out) {}
  void u8(std::uint8_t v) noexcept {
    if (pos_ < out_.size()) {
      out_[pos_] = v;
    } else {
      overflow_ = true;
    }
    ++pos_;
  }
  void u16(std::uint16_t v) noexcept {
    u8(static_cast<std::uint8_t>(v & 0xFFU));
    u8(static_cast<std::uint8_t>(v >> 8U));
  }
  // Values little-endian, one bounds check for all (a valve command's counts, every tick).
  void u16s(std::span<const std::uint16_t> values) noexcept {
    if (values.size() * 2 > out_.size() - std::min(pos_, out_.size())) {
      for (const std::uint16_t v : values) {
        u16(v);  // past the end: counted and flagged byte by byte, as ever
      }
      return;
    }
    std::uint8_t* p = out_.data() + pos_;
    for (const std::uint16_t v : values) {
      *p++ = static_cast<std::uint8_t>(v & 0xFFU);
      *p++ = static_cast<std::uint8_t>(v >> 8U);
    }
    pos_ += values.size() * 2;
  }
  void i16(std::int16_t v) noexcept { u16(static_cast<std::uint16_t>(v)); }
  void u32(std::uint32_t v) noexcept {
    u16(static_cast<std::uint16_t>(v & 0xFFFFU));
    u16(static_cast<std::uint16_t>(v >> 16U));
  }
  [[nodiscard]] std::size_t position() const noexcept { return pos_; }
  [[nodiscard]] bool overflow() const noexcept { return overflow_; }

 private:
  std::span<std::uint8_t> out_;
  std::size_t pos_ = 0;
  bool overflow_ = false;
};

class Reader {
 public:
  explicit Reader(std::span<const std::uint8_t> in) noexcept : in_(in) {}
  std::uint8_t u8() noexcept {
    if (pos_ < in_.size()) {
      return in_[pos_++];
    }
    underflow_ = true;
    return 0;
  }
  std::uint16_t u16() noexcept {
    const std::uint16_t lo = u8();
    const std::uint16_t hi = u8();
    return static_cast<std::uint16_t>(lo | (hi << 8U));
  }
  std::int16_t i16() noexcept { return static_cast<std::int16_t>(u16()); }
  // n little-endian 16-bit values into out[0, n): the same as n calls of u16() (or i16()), with
  // one bounds check when they are all there.
  template <typename T>
  void u16s(T* out, std::size_t n) noexcept {
    static_assert(std::is_same_v<T, std::uint16_t> || std::is_same_v<T, std::int16_t>);
    if (n > remaining() / 2) {
      for (std::size_t i = 0; i < n; ++i) {
        out[i] = static_cast<T>(u16());  // past the end: flagged byte by byte, as ever
      }
      return;
    }
    const std::uint8_t* p = in_.data() + pos_;
    for (std::size_t i = 0; i < n; ++i, p += 2) {
      out[i] = static_cast<T>(static_cast<std::uint16_t>(p[0] | (p[1] << 8U)));
    }
    pos_ += 2 * n;
  }
  std::uint32_t u32() noexcept {
    const std::uint32_t lo = u16();
    const std::uint32_t hi = u16();
    return lo | (hi << 16U);
  }
  [[nodiscard]] std::size_t remaining() const noexcept { return in_.size() - pos_; }
  [[nodiscard]] bool underflow() const noexcept { return underflow_; }

 private:
  std::span<const std::uint8_t> in_;
  std::size_t pos_ = 0;
  bool underflow_ = false;
};

}  // namespace mrskin::protocol::detail
