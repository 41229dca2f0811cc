// udp://HOST:PORT: one sample per datagram, format v1 (docs/sources.md).
#include <fmt/format.h>
#include <poll.h>
#include <pthread.h>
#include <sys/socket.h>

#include <bit>
#include <cerrno>
#include <cstring>
#include <thread>

#include "core.hpp"
#include "udp_source.hpp"

namespace mrskin::bridge {
namespace {

constexpr std::array<std::uint8_t, 4> kMagic{'M', 'R', 'S', 'S'};
constexpr std::size_t kCrcOffset = 64;

constexpr std::array<std::uint32_t, 256> make_crc32c_table() noexcept {
  std::array<std::uint32_t, 256> t{};
  for (std::uint32_t i = 0; i < 256; ++i) {
    std::uint32_t c = i;
    for (int k = 0; k < 8; ++k) {
      c = (c & 1U) != 0 ? (c >> 1U) ^ 0x82F63B78U : c >> 1U;
    }
    t[i] = c;
  }
  return t;
}
constexpr auto kCrc32cTable = make_crc32c_table();

template <class T>
void put_le(std::uint8_t* p, T v) noexcept {
  static_assert(std::endian::native == std::endian::little);
  std::memcpy(p, &v, sizeof v);
}
template <class T>
T get_le(const std::uint8_t* p) noexcept {
  T v;
  std::memcpy(&v, p, sizeof v);
  return v;
}

}  // namespace

std::uint32_t crc32c(std::span<const std::uint8_t> data) noexcept {
  std::uint32_t c = 0xFFFFFFFFU;
  for (const std::uint8_t b : data) {
    c = kCrc32cTable[(c ^ b) & 0xFFU] ^ (c >> 8U);
  }
  return c ^ 0xFFFFFFFFU;
}

std::array<std::uint8_t, kUdpDatagramBytes> encode_udp_sample(const UdpSample& s) noexcept {
  std::array<std::uint8_t, kUdpDatagramBytes> d{};
  std::memcpy(d.data(), kMagic.data(), kMagic.size());
  put_le<std::uint16_t>(d.data() + 4, kUdpVersion);
  put_le<std::uint16_t>(d.data() + 6, 0);  // flags
  put_le<std::uint32_t>(d.data() + 8, s.sequence);
  put_le<std::uint32_t>(d.data() + 12, 0);  // reserved
  put_le<std::int64_t>(d.data() + 16, s.stamp_ns);
  put_le<double>(d.data() + 24, s.force_N);
  put_le<double>(d.data() + 32, s.indentation_m);
  put_le<double>(d.data() + 40, s.contact_x_m);
  put_le<double>(d.data() + 48, s.contact_y_m);
  put_le<double>(d.data() + 56, s.tip_radius_m);
  put_le<std::uint32_t>(d.data() + kCrcOffset, crc32c(std::span(d.data(), kCrcOffset)));
  return d;
}

namespace sources {

UdpSource::UdpSource(const Endpoint& where, const SourceOptions& options, Clock* clock)
    : QueuedSource(options, clock),
      socket_(bind_socket(where, SOCK_DGRAM, "udp source")),
      port_(bound_port(socket_.get())),
      gate_(options.restart_after_out_of_order),
      mapper_(options.offset_drift_s_per_s) {
  thread_ = std::thread([this] {
    (void)::pthread_setname_np(::pthread_self(), "mrskin-udp");
    run();
  });
}

UdpSource::~UdpSource() {
  stop_.raise();
  thread_.join();
}

UdpParsed parse_udp_datagram(std::span<const std::uint8_t> d, std::size_t length) noexcept {
  UdpParsed p;
  if (length > kUdpDatagramBytes) {
    p.reason = DropReason::oversized;
    return p;
  }
  if (length < kUdpDatagramBytes || d.size() < kUdpDatagramBytes) {
    p.reason = DropReason::length;
    return p;
  }
  if (std::memcmp(d.data(), kMagic.data(), kMagic.size()) != 0 ||
      get_le<std::uint16_t>(d.data() + 4) != kUdpVersion) {
    p.reason = DropReason::format;
    return p;
  }
  if (get_le<std::uint32_t>(d.data() + kCrcOffset) != crc32c(d.first(kCrcOffset))) {
    p.reason = DropReason::crc;
    return p;
  }
  p.ok = true;
  p.sample.sequence = get_le<std::uint32_t>(d.data() + 8);
  p.sample.stamp_ns = get_le<std::int64_t>(d.data() + 16);
  p.sample.force_N = get_le<double>(d.data() + 24);
  p.sample.indentation_m = get_le<double>(d.data() + 32);
  p.sample.contact_x_m = get_le<double>(d.data() + 40);
  p.sample.contact_y_m = get_le<double>(d.data() + 48);
  p.sample.tip_radius_m = get_le<double>(d.data() + 56);
  return p;
}

void UdpSource::handle(std::span<const std::uint8_t> d, std::size_t length, TimePoint arrival) noexcept {
  const UdpParsed p = parse_udp_datagram(d, length);
  if (!p.ok) {
    switch (p.reason) {
      case DropReason::oversized:
      case DropReason::length:
        drop(stats_, events_, p.reason, [&] {
          return fmt::format("UDP datagram of {} bytes dropped: a sample is {} bytes (docs/sources.md)",
                             length, kUdpDatagramBytes);
        });
        return;
      case DropReason::format:
        drop(stats_, events_, p.reason, [] {
          return std::string(
              "UDP datagram dropped: not an mrskin sample v1 (magic MRSS, version 1; docs/sources.md)");
        });
        return;
      default:  // DropReason::crc
        drop(stats_, events_, p.reason, [] {
          return std::string(
              "UDP datagram dropped: bad CRC-32C (over bytes 0..63, at offset 64; docs/sources.md)");
        });
        return;
    }
  }
  SlaveSample s;
  const std::int64_t robot_ns = p.sample.stamp_ns;
  s.force_N = p.sample.force_N;
  s.indentation_m = p.sample.indentation_m;
  s.contact_x_m = p.sample.contact_x_m;
  s.contact_y_m = p.sample.contact_y_m;
  s.tip_radius_m = p.sample.tip_radius_m;
  if (!values_ok(s, options_, stats_, events_)) {
    return;
  }
  if (!stamp_ok(robot_ns)) {
    drop(stats_, events_, DropReason::stamp, [&] {
      return fmt::format("UDP sample dropped: robot stamp {} ns is outside 0..2^62 ns", robot_ns);
    });
    return;
  }
  switch (gate_.check(robot_ns)) {
    case OrderGate::Verdict::duplicate:
      drop(stats_, events_, DropReason::duplicate, [] {
        return std::string("UDP sample dropped: its robot stamp repeats the last one (a resend?)");
      });
      return;
    case OrderGate::Verdict::out_of_order:
      drop(stats_, events_, DropReason::out_of_order, [] {
        return std::string("UDP sample dropped: its robot stamp is older than the last one (reordered)");
      });
      return;
    case OrderGate::Verdict::restart:
      stats_.restarts.bump();
      mapper_.reset();
      break;
    case OrderGate::Verdict::accept:
      break;
  }
  s.stamp = mapper_.map(robot_ns, arrival);
  s.received = arrival;
  s.valid = true;
  publish(s);
}

void UdpSource::run() noexcept {
  // One byte beyond the format so that MSG_TRUNC tells oversized from exact.
  std::array<std::uint8_t, 2048> buffer{};
  for (;;) {
    std::array<pollfd, 2> fds{{{socket_.get(), POLLIN, 0}, {stop_.fd(), POLLIN, 0}}};
    // While a sample is held back by a full queue, come back soon to hand it over.
    const int timeout_ms = has_pending() ? 1 : 100;
    if (::poll(fds.data(), fds.size(), timeout_ms) < 0 && errno != EINTR) {
      return;
    }
    if ((fds[1].revents & POLLIN) != 0) {
      return;
    }
    (void)flush_pending();
    if ((fds[0].revents & POLLIN) == 0) {
      continue;
    }
    // A bounded batch, then back to poll: a flood cannot starve the stop signal.
    for (int k = 0; k < 256; ++k) {
      const ssize_t n = ::recv(socket_.get(), buffer.data(), buffer.size(), MSG_DONTWAIT | MSG_TRUNC);
      if (n < 0) {
        break;
      }
      const auto length = static_cast<std::size_t>(n);
      handle(std::span(buffer.data(), std::min(length, buffer.size())), length, now());
    }
  }
}

}  // namespace sources
}  // namespace mrskin::bridge
