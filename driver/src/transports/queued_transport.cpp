#include "mrskin/driver/queued_transport.hpp"

#include <poll.h>
#include <sys/eventfd.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstring>
#include <string>
#include <thread>

namespace mrskin {
namespace {

int make_eventfd(std::string_view uri) {
  const int fd = ::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (fd < 0) {
    throw Error("cannot create an eventfd for " + std::string(uri) + ": " + std::strerror(errno) +
                " (raise the open-file limit, ulimit -n)");
  }
  return fd;
}

// The receive eventfd, closing the send one if it cannot be made (the constructor's cleanup).
int make_second_eventfd(std::string_view uri, int first_fd) {
  try {
    return make_eventfd(uri);
  } catch (...) {
    ::close(first_fd);
    throw;
  }
}

void signal_event(int fd) noexcept {
  const std::uint64_t one = 1;
  // EAGAIN only when the counter would overflow: the waiter is already woken.
  [[maybe_unused]] const ssize_t n = ::write(fd, &one, sizeof one);
}

void clear_event(int fd) noexcept {
  std::uint64_t value = 0;
  [[maybe_unused]] const ssize_t n = ::read(fd, &value, sizeof value);
}

}  // namespace

ResultCode Transport::receive_for(Datagram& out, Duration timeout) noexcept {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  for (;;) {
    const ResultCode rc = receive(out);
    if (rc != ResultCode::would_block) {
      return rc;
    }
    if (state() != TransportState::open) {
      return ResultCode::disconnected;
    }
    if (std::chrono::steady_clock::now() >= deadline) {
      return ResultCode::would_block;
    }
    std::this_thread::sleep_for(std::chrono::microseconds(100));
  }
}

QueuedTransport::QueuedTransport(std::string uri, std::size_t send_capacity, std::size_t receive_capacity)
    : uri_(std::move(uri)),
      outgoing_(send_capacity),
      incoming_(receive_capacity),
      send_event_fd_(make_eventfd(uri_)),
      receive_event_fd_(make_second_eventfd(uri_, send_event_fd_)) {}

QueuedTransport::~QueuedTransport() {
  ::close(send_event_fd_);
  ::close(receive_event_fd_);
}

ResultCode QueuedTransport::send(std::span<const std::uint8_t> bytes) noexcept {
  if (bytes.empty() || bytes.size() > kMaxDatagramBytes) {
    return ResultCode::invalid_value;
  }
  if (state() != TransportState::open) {
    return ResultCode::disconnected;
  }
  Datagram d;
  std::memcpy(d.bytes.data(), bytes.data(), bytes.size());
  d.length = static_cast<std::uint16_t>(bytes.size());
  if (!outgoing_.try_push(d)) {
    counters_.send_would_block.bump();
    return ResultCode::would_block;
  }
  signal_event(send_event_fd_);
  return ResultCode::ok;
}

ResultCode QueuedTransport::receive(Datagram& out) noexcept {
  if (incoming_.try_pop(out)) {
    counters_.received.bump();
    return ResultCode::ok;
  }
  return state() == TransportState::open ? ResultCode::would_block : ResultCode::disconnected;
}

ResultCode QueuedTransport::receive_for(Datagram& out, Duration timeout) noexcept {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  for (;;) {
    const ResultCode rc = receive(out);
    if (rc != ResultCode::would_block) {
      return rc;
    }
    const auto left =
        std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
    if (left.count() < 0) {
      return ResultCode::would_block;
    }
    pollfd p{receive_event_fd_, POLLIN, 0};
    // Rounded up to whole milliseconds, at least one poll per call.
    (void)::poll(&p, 1, static_cast<int>(left.count()) + 1);
    clear_event(receive_event_fd_);
  }
}

TransportCounters QueuedTransport::counters() const noexcept {
  TransportCounters c;
  c.sent = counters_.sent.value();
  c.received = counters_.received.value();
  c.send_would_block = counters_.send_would_block.value();
  c.receive_overruns = counters_.receive_overruns.value();
  c.timeouts = counters_.timeouts.value();
  c.io_errors = counters_.io_errors.value();
  c.disconnects = counters_.disconnects.value();
  c.reopens = counters_.reopens.value();
  c.malformed = counters_.malformed.value();
  c.error_frames = counters_.error_frames.value();
  c.bus_off = counters_.bus_off.value();
  return c;
}

bool QueuedTransport::take_outgoing(Datagram& out) noexcept {
  if (outgoing_.try_pop(out)) {
    return true;
  }
  clear_event(send_event_fd_);
  // A send() between the failed pop and the clear would be missed: look once more.
  return outgoing_.try_pop(out);
}

void QueuedTransport::deliver(const Datagram& d) noexcept {
  if (!incoming_.try_push(d)) {
    counters_.receive_overruns.bump();
    return;
  }
  signal_event(receive_event_fd_);
}

void QueuedTransport::discard_outgoing() noexcept {
  Datagram d;
  while (outgoing_.try_pop(d)) {
  }
  clear_event(send_event_fd_);
}

void QueuedTransport::set_state(TransportState s) noexcept {
  const TransportState old = state_.exchange(s, std::memory_order_acq_rel);
  if (old == s) {
    return;
  }
  if (s == TransportState::open) {
    if (counters_.disconnects.value() + counters_.bus_off.value() > 0) {
      counters_.reopens.bump();  // the first open is not a reopen
    }
  } else if (old == TransportState::open) {
    if (s == TransportState::bus_off) {
      counters_.bus_off.bump();
    } else {
      counters_.disconnects.bump();
    }
  }
  signal_event(receive_event_fd_);
}

}  // namespace mrskin
