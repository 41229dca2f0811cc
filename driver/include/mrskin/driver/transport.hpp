// One transport interface for every bus: datagrams of at most 64 bytes (one HID report,
// one packet). Calls are non-blocking and allocation-free, so the session may call them
// from the tick thread; transports whose OS calls block run their I/O on their own thread.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <span>
#include <string_view>

#include "mrskin/driver/errors.hpp"

namespace mrskin {

inline constexpr std::size_t kMaxDatagramBytes = 64;

struct Datagram {
  std::array<std::uint8_t, kMaxDatagramBytes> bytes{};
  std::uint8_t length = 0;
};

enum class TransportState : unsigned char { open, disconnected };

class Transport {
 public:
  Transport() = default;
  Transport(const Transport&) = delete;
  Transport& operator=(const Transport&) = delete;
  Transport(Transport&&) = delete;
  Transport& operator=(Transport&&) = delete;
  virtual ~Transport() = default;

  // Queues one datagram; would_block when the outgoing queue is full.
  virtual ResultCode send(std::span<const std::uint8_t> bytes) noexcept = 0;
  // Takes one received datagram; would_block when none is waiting.
  virtual ResultCode receive(Datagram& out) noexcept = 0;
  [[nodiscard]] virtual TransportState state() const noexcept = 0;
  [[nodiscard]] virtual std::string_view uri() const noexcept = 0;
};

}  // namespace mrskin
