// The tick side of a transport whose OS calls block (hidraw, libusb, SocketCAN): two
// wait-free SPSC queues between the tick thread and the transport's own I/O thread(s), an
// eventfd that wakes the I/O thread when the tick queues a datagram, and one that wakes a
// setup-time receive_for(). Subclasses own their threads and call the protected I/O-side
// functions from them; the public Transport functions stay non-blocking and allocation-free.
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <string_view>

#include "mrskin/driver/export.hpp"
#include "mrskin/driver/relaxed_counter.hpp"
#include "mrskin/driver/spsc_queue.hpp"
#include "mrskin/driver/transport.hpp"

namespace mrskin {

class MRSKIN_DRIVER_API QueuedTransport : public Transport {
 public:
  // Queue capacities in datagrams. Throws Error when eventfd() fails.
  QueuedTransport(std::string uri, std::size_t send_capacity, std::size_t receive_capacity);
  QueuedTransport(const QueuedTransport&) = delete;
  QueuedTransport& operator=(const QueuedTransport&) = delete;
  QueuedTransport(QueuedTransport&&) = delete;
  QueuedTransport& operator=(QueuedTransport&&) = delete;
  ~QueuedTransport() override;

  ResultCode send(std::span<const std::uint8_t> bytes) noexcept override;
  ResultCode receive(Datagram& out) noexcept override;
  ResultCode receive_for(Datagram& out, Duration timeout) noexcept override;
  [[nodiscard]] TransportState state() const noexcept override {
    return state_.load(std::memory_order_acquire);
  }
  [[nodiscard]] std::string_view uri() const noexcept override { return uri_; }
  [[nodiscard]] TransportCounters counters() const noexcept override;

 protected:
  // --- I/O side, called from the subclass's thread(s) ---
  // Readable (POLLIN) when send() queued something; drain it with take_outgoing().
  [[nodiscard]] int send_event_fd() const noexcept { return send_event_fd_; }
  // Next datagram to write, or false; also clears the send event when the queue is empty.
  bool take_outgoing(Datagram& out) noexcept;
  // Hands a received datagram to the tick side; counts an overrun when its queue is full.
  void deliver(const Datagram& d) noexcept;
  // Drops everything queued for sending (the device went away: stale commands must not be
  // written to the next device that appears).
  void discard_outgoing() noexcept;
  // State changes count disconnects, reopens and bus-off events and wake receive_for().
  void set_state(TransportState s) noexcept;

  struct AtomicCounters {
    RelaxedCounter sent;
    RelaxedCounter received;
    RelaxedCounter send_would_block;
    RelaxedCounter receive_overruns;
    RelaxedCounter timeouts;
    RelaxedCounter io_errors;
    RelaxedCounter disconnects;
    RelaxedCounter reopens;
    RelaxedCounter malformed;
    RelaxedCounter error_frames;
    RelaxedCounter bus_off;
  };
  AtomicCounters counters_;

 private:
  std::string uri_;
  SpscQueue<Datagram> outgoing_;
  SpscQueue<Datagram> incoming_;
  std::atomic<TransportState> state_{TransportState::disconnected};
  int send_event_fd_ = -1;
  int receive_event_fd_ = -1;
};

}  // namespace mrskin
