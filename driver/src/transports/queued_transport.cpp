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
  d.length = static_cast<std::uint8_t>(bytes.size());
  if (!outgoing_.try_push(d)) {
    bump(counters_.send_would_block);
    return ResultCode::would_block;
  }
  signal_event(send_event_fd_);
  return ResultCode::ok;
}

ResultCode QueuedTransport::receive(Datagram& out) noexcept {
  if (incoming_.try_pop(out)) {
    bump(counters_.received);
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
  const auto r = [](const std::atomic<std::uint64_t>& c) { return c.load(std::memory_order_relaxed); };
  TransportCounters c;
  c.sent = r(counters_.sent);
  c.received = r(counters_.received);
  c.send_would_block = r(counters_.send_would_block);
  c.receive_overruns = r(counters_.receive_overruns);
  c.timeouts = r(counters_.timeouts);
  c.io_errors = r(counters_.io_errors);
  c.disconnects = r(counters_.disconnects);
  c.reopens = r(counters_.reopens);
  c.malformed = r(counters_.malformed);
  c.error_frames = r(counters_.error_frames);
  c.bus_off = r(counters_.bus_off);
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
    bump(counters_.receive_overruns);
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
    if (counters_.disconnects.load(std::memory_order_relaxed) +
            counters_.bus_off.load(std::memory_order_relaxed) >
        0) {
      bump(counters_.reopens);  // the first open is not a reopen
    }
  } else if (old == TransportState::open) {
    if (s == TransportState::bus_off) {
      bump(counters_.bus_off);
    } else {
      bump(counters_.disconnects);
    }
  }
  signal_event(receive_event_fd_);
}

}  // namespace mrskin
