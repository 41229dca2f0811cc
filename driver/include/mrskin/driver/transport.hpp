// One transport interface for every bus: datagrams of at most 1024 bytes (one USB-HID report: 64
// bytes at full speed, up to 1024 once a unit declares them in 1.2's UsbSlots; one packet on CAN). send() and
// receive() are non-blocking and allocation-free, so the session may call them from the tick thread;
// transports whose OS calls block run their I/O on their own thread (QueuedTransport). receive_for() waits,
// for setup code only.
#pragma once

#include <array>
#include <atomic>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string_view>

#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/export.hpp"
#include "mrskin/protocol/bus_budget.hpp"
#include "mrskin/protocol/messages.hpp"

namespace mrskin {

inline constexpr std::size_t kMaxDatagramBytes = protocol::kUsbSlotsMaxReportBytes;

struct Datagram {
  std::array<std::uint8_t, kMaxDatagramBytes> bytes{};
  std::uint16_t length = 0;
};

// open: datagrams flow. disconnected: the device is gone (unplugged, interface down); the
// transport reopens it by itself and returns to open. bus_off: a CAN controller left the
// bus after too many errors; it counts as disconnected until the controller recovers.
enum class TransportState : unsigned char { open, disconnected, bus_off };
constexpr const char* to_string(TransportState s) noexcept {
  switch (s) {
    case TransportState::open:
      return "open";
    case TransportState::disconnected:
      return "disconnected";
    case TransportState::bus_off:
      return "bus-off";
  }
  return "unknown";
}

// What a transport counted since it was opened. Read from any thread.
struct TransportCounters {
  std::uint64_t sent = 0;              // datagrams handed to the OS
  std::uint64_t received = 0;          // datagrams delivered to receive()
  std::uint64_t send_would_block = 0;  // send() refused: outgoing queue full (back-pressure)
  std::uint64_t receive_overruns = 0;  // datagrams dropped: the host did not read in time
  std::uint64_t timeouts = 0;          // OS writes that did not complete in time
  std::uint64_t io_errors = 0;         // OS calls that failed without losing the device
  std::uint64_t disconnects = 0;       // the device went away
  std::uint64_t reopens = 0;           // ... and came back
  std::uint64_t malformed = 0;         // bus data that is not ours or not decodable: dropped
  std::uint64_t error_frames = 0;      // CAN error frames
  std::uint64_t bus_off = 0;           // CAN bus-off events
};

class MRSKIN_DRIVER_API Transport {
 public:
  Transport() = default;
  Transport(const Transport&) = delete;
  Transport& operator=(const Transport&) = delete;
  Transport(Transport&&) = delete;
  Transport& operator=(Transport&&) = delete;
  virtual ~Transport() = default;

  // Queues one datagram; would_block when the outgoing queue is full, disconnected when the
  // device is gone, invalid_value when bytes is empty or longer than kMaxDatagramBytes.
  virtual ResultCode send(std::span<const std::uint8_t> bytes) noexcept = 0;
  // Takes one received datagram; would_block when none is waiting.
  virtual ResultCode receive(Datagram& out) noexcept = 0;
  // Waits up to timeout for a datagram: ok, would_block on timeout, disconnected. Setup only.
  // The default polls receive() every 100 us on the system clock.
  virtual ResultCode receive_for(Datagram& out, Duration timeout) noexcept;
  [[nodiscard]] virtual TransportState state() const noexcept = 0;
  [[nodiscard]] virtual std::string_view uri() const noexcept = 0;
  [[nodiscard]] virtual TransportCounters counters() const noexcept { return {}; }
  // The bus the datagrams travel on, for the bus budget (DeviceSession::check_bus_budget);
  // nullopt when nothing limits it (mock://?bus=none, an in-process link).
  [[nodiscard]] virtual std::optional<protocol::BusSpec> bus() const noexcept { return std::nullopt; }
};

}  // namespace mrskin
