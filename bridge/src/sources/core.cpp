#include "core.hpp"

#include <arpa/inet.h>
#include <fmt/format.h>
#include <netdb.h>
#include <netinet/in.h>
#include <sys/eventfd.h>
#include <sys/socket.h>
#include <unistd.h>

#include <array>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstring>
#include <limits>
#include <string>

#include "mrskin/driver/errors.hpp"

namespace mrskin::bridge::sources {

SourceStats AtomicStats::snapshot() const noexcept {
  SourceStats s;
  s.accepted = accepted.value();
  for (std::size_t i = 0; i < kDropReasonCount; ++i) {
    s.drops.at(i) = drops.at(i).value();
  }
  s.poses = poses.value();
  s.restarts = restarts.value();
  s.connections = connections.value();
  s.disconnects = disconnects.value();
  s.connect_failures = connect_failures.value();
  return s;
}

void SourceEvents::add(bool warning, std::string_view text) noexcept {
  try {
    const std::lock_guard<std::mutex> lock(mutex_);
    const std::uint64_t seq = count_.load(std::memory_order_relaxed) + 1;
    events_.push_back(SourceEvent{seq, warning, std::string(text)});
    if (events_.size() > kKept) {
      events_.pop_front();
    }
    if (warning) {
      last_warning_ = text;
    }
    count_.store(seq, std::memory_order_release);
  } catch (...) {  // NOLINT(bugprone-empty-catch): an event lost to a full heap
  }
}

std::vector<SourceEvent> SourceEvents::after(std::uint64_t seq) const {
  const std::lock_guard<std::mutex> lock(mutex_);
  std::vector<SourceEvent> out;
  for (const SourceEvent& e : events_) {
    if (e.seq > seq) {
      out.push_back(e);
    }
  }
  return out;
}

std::string SourceEvents::last_warning() const {
  const std::lock_guard<std::mutex> lock(mutex_);
  return last_warning_;
}

bool values_ok(const SlaveSample& s, const SourceOptions& o, AtomicStats& stats,
               SourceEvents& events) noexcept {
  if (!std::isfinite(s.force_N) || !std::isfinite(s.indentation_m) || !std::isfinite(s.contact_x_m) ||
      !std::isfinite(s.contact_y_m) || !std::isfinite(s.tip_radius_m)) {
    drop(stats, events, DropReason::non_finite,
         [] { return std::string("a sample with NaN or Inf dropped: the sender's values are not numbers"); });
    return false;
  }
  if (s.force_N < 0.0 || s.force_N > o.max_force_N || std::abs(s.indentation_m) > o.max_abs_indentation_m ||
      std::abs(s.contact_x_m) > o.max_abs_contact_m || std::abs(s.contact_y_m) > o.max_abs_contact_m ||
      s.tip_radius_m < 0.0 || s.tip_radius_m > o.max_tip_radius_m) {
    drop(stats, events, DropReason::out_of_range, [&] {
      return fmt::format(
          "a sample out of range dropped (force {} N, indentation {} m, contact ({}, {}) m, tip radius {} "
          "m): "
          "allowed force 0..{} N, |indentation| <= {} m, |contact| <= {} m, tip radius 0..{} m; check the "
          "sender's units and frame",
          s.force_N, s.indentation_m, s.contact_x_m, s.contact_y_m, s.tip_radius_m, o.max_force_N,
          o.max_abs_indentation_m, o.max_abs_contact_m, o.max_tip_radius_m);
    });
    return false;
  }
  return true;
}

OrderGate::Verdict OrderGate::check(std::int64_t stamp_ns) noexcept {
  if (have_ && stamp_ns == last_ns_) {
    return Verdict::duplicate;
  }
  if (have_ && stamp_ns < last_ns_) {
    if (++backwards_ < restart_after_) {
      return Verdict::out_of_order;
    }
    backwards_ = 0;
    last_ns_ = stamp_ns;
    return Verdict::restart;
  }
  backwards_ = 0;
  have_ = true;
  last_ns_ = stamp_ns;
  return Verdict::accept;
}

TimePoint ClockMapper::map(std::int64_t robot_ns, TimePoint arrival) noexcept {
  const std::int64_t d = arrival.count() - robot_ns;
  if (!have_) {
    have_ = true;
    offset_ns_ = d;
  } else {
    const auto since = static_cast<double>((arrival - last_arrival_).count());
    offset_ns_ += static_cast<std::int64_t>(drift_ * std::max(0.0, since));
    offset_ns_ = std::min(offset_ns_, d);
  }
  last_arrival_ = arrival;
  return TimePoint{robot_ns + offset_ns_};
}

QueuedSource::QueuedSource(const SourceOptions& options, Clock* clock)
    : options_(options),
      own_clock_(clock == nullptr ? std::make_unique<MonotonicClock>() : nullptr),
      clock_(clock == nullptr ? own_clock_.get() : clock),
      queue_(options.queue_capacity) {
  if (options.queue_capacity == 0 || options.queue_capacity > (1U << 20U)) {
    throw InvalidArgument("source: queue capacity must be 1..1048576 samples (got " +
                          std::to_string(options.queue_capacity) + ")");
  }
}

void QueuedSource::set_arrival_hook(ArrivalHook hook, void* context) noexcept {
  hook_context_.store(context, std::memory_order_relaxed);
  hook_.store(hook, std::memory_order_release);
}

void QueuedSource::notify() noexcept {
  if (ArrivalHook hook = hook_.load(std::memory_order_acquire)) {
    hook(hook_context_.load(std::memory_order_relaxed));
  }
}

void QueuedSource::publish(const SlaveSample& s) noexcept {
  stats_.accepted.bump();
  enqueue(s);
}

void QueuedSource::enqueue(const SlaveSample& s) noexcept {
  if (pending_valid_ && !queue_.try_push(pending_)) {
    stats_.count(DropReason::superseded);  // the held one: the tick did not take it in time
    pending_ = s;
    return;
  }
  pending_valid_ = false;
  if (!queue_.try_push(s)) {
    pending_ = s;
    pending_valid_ = true;
    return;
  }
  notify();
}

bool QueuedSource::flush_pending() noexcept {
  if (pending_valid_ && queue_.try_push(pending_)) {
    pending_valid_ = false;
    notify();
  }
  return !pending_valid_;
}

bool admit(OrderGate& gate, std::int64_t robot_ns, ClockMapper& mapper, AtomicStats& stats,
           SourceEvents& events, std::string_view what) noexcept {
  switch (gate.check(robot_ns)) {
    case OrderGate::Verdict::duplicate:
      drop(stats, events, DropReason::duplicate,
           [&] { return fmt::format("{} dropped: its timestamp repeats the last one of its kind", what); });
      return false;
    case OrderGate::Verdict::out_of_order:
      drop(stats, events, DropReason::out_of_order, [&] {
        return fmt::format("{} dropped: its timestamp is older than the last one of its kind", what);
      });
      return false;
    case OrderGate::Verdict::restart:
      stats.restarts.bump();
      mapper.reset();
      return true;
    case OrderGate::Verdict::accept:
      return true;
  }
  return false;
}

bool QueuedSource::latest(TimePoint /*now*/, SlaveSample& out) noexcept {
  SlaveSample s;
  while (queue_.try_pop(s)) {
    last_ = s;
  }
  if (!last_.valid) {
    return false;
  }
  out = last_;
  return true;
}

// ---- sockets --------------------------------------------------------------------------------

Endpoint parse_endpoint(std::string_view text, std::string_view uri, bool need_host, bool allow_port_0) {
  Endpoint e;
  std::string_view port_text;
  if (text.starts_with('[')) {
    const auto close = text.find(']');
    if (close == std::string_view::npos || close + 1 >= text.size() || text[close + 1] != ':') {
      throw InvalidArgument("source '" + std::string(uri) + "': bad address '" + std::string(text) +
                            "' (an IPv6 address is written [ADDR]:PORT)");
    }
    e.host = std::string(text.substr(1, close - 1));
    port_text = text.substr(close + 2);
  } else {
    const auto colon = text.rfind(':');
    if (colon == std::string_view::npos) {
      throw InvalidArgument("source '" + std::string(uri) + "': missing port in '" + std::string(text) +
                            "' (HOST:PORT)");
    }
    e.host = std::string(text.substr(0, colon));
    port_text = text.substr(colon + 1);
  }
  if (need_host && e.host.empty()) {
    throw InvalidArgument("source '" + std::string(uri) + "': missing host (HOST:PORT)");
  }
  unsigned port = 0;
  const auto [end, ec] = std::from_chars(port_text.data(), port_text.data() + port_text.size(), port);
  if (ec != std::errc{} || end != port_text.data() + port_text.size() || port > 65535 ||
      (port == 0 && !allow_port_0)) {
    throw InvalidArgument("source '" + std::string(uri) + "': bad port '" + std::string(port_text) + "' (" +
                          (allow_port_0 ? "0" : "1") + "..65535)");
  }
  e.port = static_cast<std::uint16_t>(port);
  return e;
}

Fd& Fd::operator=(Fd&& o) noexcept {
  if (this != &o) {
    reset();
    fd_ = o.release();
  }
  return *this;
}

void Fd::reset() noexcept {
  if (fd_ >= 0) {
    ::close(fd_);
    fd_ = -1;
  }
}

Fd bind_socket(const Endpoint& where, int type, std::string_view what) {
  const std::string host = where.host.empty() ? "127.0.0.1" : where.host;
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = type;
  hints.ai_flags = AI_PASSIVE | AI_NUMERICSERV;
  addrinfo* found = nullptr;
  const std::string port = std::to_string(where.port);
  if (const int rc = ::getaddrinfo(host.c_str(), port.c_str(), &hints, &found); rc != 0) {
    throw InvalidArgument(std::string(what) + ": cannot resolve '" + host + "': " + ::gai_strerror(rc));
  }
  std::unique_ptr<addrinfo, decltype(&::freeaddrinfo)> list(found, &::freeaddrinfo);
  int err = 0;
  for (const addrinfo* a = found; a != nullptr; a = a->ai_next) {
    Fd fd(::socket(a->ai_family, a->ai_socktype | SOCK_NONBLOCK | SOCK_CLOEXEC, a->ai_protocol));
    if (!fd.valid()) {
      err = errno;
      continue;
    }
    const int one = 1;
    if (type == SOCK_STREAM) {
      (void)::setsockopt(fd.get(), SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
    }
    if (::bind(fd.get(), a->ai_addr, a->ai_addrlen) != 0 ||
        (type == SOCK_STREAM && ::listen(fd.get(), 4) != 0)) {
      err = errno;
      continue;
    }
    return fd;
  }
  throw Error(std::string(what) + ": cannot bind " + host + ":" + port + ": " + std::strerror(err) +
              " (is the port in use? give another, or 0 for any free port)");
}

std::uint16_t bound_port(int fd) noexcept {
  sockaddr_storage addr{};
  socklen_t len = sizeof addr;
  // NOLINTNEXTLINE(cppcoreguidelines-pro-type-reinterpret-cast): the sockets API's own cast
  if (::getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len) != 0) {
    return 0;
  }
  if (addr.ss_family == AF_INET) {
    sockaddr_in v4{};
    std::memcpy(&v4, &addr, sizeof v4);
    return ntohs(v4.sin_port);
  }
  if (addr.ss_family == AF_INET6) {
    sockaddr_in6 v6{};
    std::memcpy(&v6, &addr, sizeof v6);
    return ntohs(v6.sin6_port);
  }
  return 0;
}

StopSignal::StopSignal() : fd_(::eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK)) {
  if (!fd_.valid()) {
    throw Error(std::string("source: eventfd failed: ") + std::strerror(errno));
  }
}

void StopSignal::raise() noexcept {
  const std::uint64_t one = 1;
  [[maybe_unused]] const ssize_t n = ::write(fd_.get(), &one, sizeof one);  // full only if raised before
}

}  // namespace mrskin::bridge::sources
