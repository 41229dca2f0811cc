// The can:// transport: its URI, and the session's datagrams over a raw SocketCAN socket on an I/O
// thread, framed by CanPacketCodec (mrskin/driver/transports/can.hpp says how it behaves).
#include <fmt/format.h>
#include <linux/can.h>
#include <linux/can/error.h>
#include <net/if.h>
#include <pthread.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <charconv>
#include <cstring>
#include <thread>
#include <utility>

#include "can_socket.hpp"
#include "can_socket_api.hpp"
#include "event_fd.hpp"
#include "mrskin/driver/queued_transport.hpp"
#include "mrskin/driver/relaxed_counter.hpp"

namespace mrskin {
namespace proto = mrskin::protocol;
using socketcan::from_wire;
using socketcan::link_lost;
using socketcan::open_bound_socket;
using socketcan::OpenResult;
using socketcan::throw_open_error;
using socketcan::to_wire;

// ============================================================================ URI

namespace {

constexpr std::string_view kCanScheme = "can://";
constexpr std::string_view kCanUriForm = "can://IFACE?node=N[&fd=1], e.g. can://can0?node=3";

[[noreturn]] void bad_uri(std::string_view uri, std::string_view what) {
  throw InvalidArgument(fmt::format("'{}': {} (expected {})", uri, what, kCanUriForm));
}

}  // namespace

CanUri parse_can_uri(std::string_view uri) {
  if (!uri.starts_with(kCanScheme)) {
    bad_uri(uri, "not a can:// URI");
  }
  const std::string_view rest = uri.substr(kCanScheme.size());
  const std::size_t q = rest.find('?');
  const std::string_view iface = rest.substr(0, q);
  CanUri out;
  if (iface.empty()) {
    bad_uri(uri, "names no CAN interface");
  }
  if (iface.size() >= IFNAMSIZ) {
    bad_uri(uri, fmt::format("interface name '{}' is longer than {} characters", iface, IFNAMSIZ - 1));
  }
  if (iface == "." || iface == ".." || std::any_of(iface.begin(), iface.end(), [](char c) {
        return c == '/' || c == ':' || c <= ' ' || c == '&';
      })) {
    bad_uri(uri, fmt::format("'{}' is not an interface name", iface));
  }
  out.interface = std::string(iface);
  bool have_node = false;
  std::string_view query = q == std::string_view::npos ? std::string_view{} : rest.substr(q + 1);
  while (!query.empty()) {
    const std::size_t amp = query.find('&');
    const std::string_view pair = query.substr(0, amp);
    query = amp == std::string_view::npos ? std::string_view{} : query.substr(amp + 1);
    const std::size_t eq = pair.find('=');
    if (eq == std::string_view::npos) {
      bad_uri(uri, fmt::format("parameter '{}' needs a value (key=value)", pair));
    }
    const std::string_view key = pair.substr(0, eq);
    const std::string_view value = pair.substr(eq + 1);
    if (key == "node") {
      unsigned node = 0;
      const auto [end, ec] = std::from_chars(value.data(), value.data() + value.size(), node);
      if (ec != std::errc{} || end != value.data() + value.size() || node < proto::kCanNodeMin ||
          node > proto::kCanNodeMax) {
        bad_uri(uri, fmt::format("node '{}' is not a node id {}..{}", value, proto::kCanNodeMin,
                                 proto::kCanNodeMax));
      }
      out.node = static_cast<std::uint8_t>(node);
      have_node = true;
    } else if (key == "fd") {
      if (value != "0" && value != "1") {
        bad_uri(uri, fmt::format("fd '{}' is 0 or 1", value));
      }
      out.fd = value == "1";
    } else {
      bad_uri(uri, fmt::format("unknown parameter '{}' (known: node, fd)", key));
    }
  }
  if (!have_node) {
    bad_uri(uri, "needs node=N, the unit's node id 1..15");
  }
  return out;
}

std::string format_can_uri(const CanUri& uri) {
  return fmt::format("can://{}?node={}{}", uri.interface, uri.node, uri.fd ? "&fd=1" : "");
}

// ============================================================================ transport

namespace {

class CanTransport final : public QueuedTransport {
 public:
  CanTransport(const CanUri& parsed, const CanTransportOptions& options, std::shared_ptr<CanSocketApi> api)
      : QueuedTransport(format_can_uri(parsed), options.send_queue, options.receive_queue),
        uri_(parsed),
        role_(options.role),
        api_(std::move(api)),
        codec_(options.role, parsed.node, parsed.fd),
        filters_(can_receive_filters(options.role, parsed.node)),
        reopen_min_(scaled_duration(options.reopen_backoff_min, options.time_scale)),
        reopen_max_(scaled_duration(options.reopen_backoff_max, options.time_scale)),
        enobufs_min_(scaled_duration(options.enobufs_backoff_min, options.time_scale)),
        enobufs_max_(scaled_duration(options.enobufs_backoff_max, options.time_scale)) {
    const OpenResult r = open();
    if (r.fd < 0) {
      throw_open_error(uri(), uri_.interface, uri_.fd, r, *api_);
    }
    socket_ = r.fd;
    set_state(TransportState::open);
    thread_ = std::thread([this] {
      (void)::pthread_setname_np(::pthread_self(), "mrskin-can");
      run();
    });
  }
  CanTransport(const CanTransport&) = delete;
  CanTransport& operator=(const CanTransport&) = delete;
  CanTransport(CanTransport&&) = delete;
  CanTransport& operator=(CanTransport&&) = delete;
  ~CanTransport() override {
    stop_.store(true, std::memory_order_release);
    stop_event_.signal();
    thread_.join();
    if (socket_ >= 0) {
      api_->close_socket(socket_);
    }
  }

  ResultCode send(std::span<const std::uint8_t> bytes) noexcept override {
    // Refused here, where the caller sees it, rather than dropped on the I/O thread.
    if (CanPacketCodec::check(role_, uri_.fd, bytes) != proto::Error::ok) {
      return ResultCode::invalid_value;
    }
    return QueuedTransport::send(bytes);
  }

  [[nodiscard]] CanTransportStats stats() const noexcept {
    CanTransportStats s;
    s.frames_written = stats_.frames_written.value();
    s.frames_read = stats_.frames_read.value();
    s.enobufs = stats_.enobufs.value();
    s.send_buffer_full = stats_.send_buffer_full.value();
    s.foreign_frames = stats_.foreign_frames.value();
    s.dropped_packets = stats_.dropped_packets.value();
    return s;
  }

  // 1 Mbit/s (5 Mbit/s data phase) assumed: SocketCAN's bit timing is the interface's, not ours.
  [[nodiscard]] std::optional<protocol::BusSpec> bus() const noexcept override {
    return protocol::default_bus_spec(uri_.fd ? protocol::BusKind::can_fd : protocol::BusKind::can_classic);
  }

 private:
  // What the writer waits for before writing again.
  enum class Wait : std::uint8_t { nothing, writable, backoff };
  static constexpr int kReadBurst = 64;  // frames read per round before the writer gets a turn

  OpenResult open() noexcept {
    return open_bound_socket(*api_, uri_.interface, uri_.fd,
                             std::span<const CanIdFilter>(filters_.filters.data(), filters_.count));
  }

  void run() noexcept {
    Duration reopen_backoff = reopen_min_;
    while (!stop_.load(std::memory_order_acquire)) {
      if (socket_ < 0) {
        const OpenResult r = open();
        if (r.fd < 0) {
          wait_for_stop(reopen_backoff);
          reopen_backoff = std::min(reopen_backoff * 2, reopen_max_);
          continue;
        }
        socket_ = r.fd;
        reopen_backoff = reopen_min_;
        discard_outgoing();  // a send() that raced the loss: meant for the link that went away
        set_state(TransportState::open);
      }
      const bool pending = next_frame_ < frame_count_;
      std::array<pollfd, 3> fds{{
          {socket_, static_cast<short>(POLLIN | (wait_ == Wait::writable ? POLLOUT : 0)), 0},
          {stop_event_.fd(), POLLIN, 0},
          {send_event_fd(), static_cast<short>(pending ? 0 : POLLIN), 0},
      }};
      const int ready = api_->poll(fds, wait_ == Wait::backoff ? enobufs_backoff_ : Duration{-1});
      if (ready < 0 && ready != -EINTR) {
        counters_.io_errors.bump();
        wait_for_stop(reopen_min_);  // poll itself failed (ENOMEM): do not spin
      }
      if (stop_.load(std::memory_order_acquire)) {
        break;
      }
      if ((static_cast<unsigned>(fds[0].revents) & POLLNVAL) != 0) {
        lose_link();
        continue;
      }
      if (!read_frames()) {
        continue;
      }
      if (wait_ == Wait::writable && (static_cast<unsigned>(fds[0].revents) & POLLOUT) == 0) {
        continue;
      }
      write_frames();
    }
  }

  void wait_for_stop(Duration d) noexcept {
    std::array<pollfd, 1> fds{{{stop_event_.fd(), POLLIN, 0}}};
    (void)api_->poll(fds, d);
  }

  // False when the link was lost.
  bool read_frames() noexcept {
    for (int i = 0; i < kReadBurst; ++i) {
      const long n = api_->read_frame(socket_, rx_raw_);
      if (n == -EAGAIN || n == -EWOULDBLOCK) {
        return true;
      }
      if (n == -EINTR) {
        continue;
      }
      if (link_lost(n)) {
        lose_link();
        return false;
      }
      if (n < 0) {
        counters_.io_errors.bump();
        return true;
      }
      handle_frame(static_cast<std::size_t>(n));
      stats_.frames_read.bump();  // after the frame is handled: tests wait on it
    }
    return true;
  }

  void handle_frame(std::size_t size) noexcept {
    if (size != CAN_MTU && size != CANFD_MTU) {
      counters_.malformed.bump();
      return;
    }
    canfd_frame raw{};
    std::memcpy(&raw, rx_raw_.data(), size);
    if ((raw.can_id & CAN_ERR_FLAG) != 0) {
      handle_error_frame(raw);
      return;
    }
    if ((raw.can_id & (CAN_EFF_FLAG | CAN_RTR_FLAG)) != 0 ||
        raw.len > (size == CANFD_MTU ? CANFD_MAX_DLEN : CAN_MAX_DLEN)) {
      counters_.malformed.bump();
      stats_.foreign_frames.bump();
      return;
    }
    const CanPacketCodec::Decoded d = codec_.decode(from_wire(raw, size == CANFD_MTU));
    if (d.error == proto::Error::wrong_node || d.error == proto::Error::unknown_type) {
      counters_.malformed.bump();
      stats_.foreign_frames.bump();
      return;
    }
    if (d.error != proto::Error::ok) {
      counters_.malformed.bump();
      return;
    }
    if (state() == TransportState::bus_off) {
      set_state(TransportState::open);  // error-free traffic again: the controller is back
    }
    if (d.complete) {
      deliver(d.packet);
    }
  }

  void handle_error_frame(const canfd_frame& raw) noexcept {
    counters_.error_frames.bump();
    if ((raw.can_id & CAN_ERR_BUSOFF) != 0) {
      if (state() == TransportState::open) {
        set_state(TransportState::bus_off);
      }
      drop_outgoing();  // the session identifies the unit again once the bus is back
      codec_.reset();
      return;
    }
    const bool restarted = (raw.can_id & CAN_ERR_RESTARTED) != 0 ||
                           ((raw.can_id & CAN_ERR_CRTL) != 0 && raw.data[1] == CAN_ERR_CRTL_ACTIVE);
    if (restarted && state() == TransportState::bus_off) {
      set_state(TransportState::open);
    }
  }

  void write_frames() noexcept {
    for (;;) {
      if (next_frame_ == frame_count_) {
        if (state() != TransportState::open) {
          discard_outgoing();  // a send() that raced the bus-off: stale, and would keep us awake
          return;
        }
        Datagram d;
        if (!take_outgoing(d)) {
          return;
        }
        const CanPacketCodec::Encoded e =
            codec_.encode(std::span<const std::uint8_t>(d.bytes.data(), d.length), frames_);
        if (e.error != proto::Error::ok) {
          stats_.dropped_packets.bump();
          continue;
        }
        next_frame_ = 0;
        frame_count_ = e.frames;
        if (e.frames == 0) {
          if (e.unsent > 0) {
            stats_.dropped_packets.bump();  // nothing on this framing (a classic heartbeat echo)
          } else {
            counters_.sent.bump();  // nothing the peer lacks
          }
          continue;
        }
      }
      const proto::CanFrame& f = frames_[next_frame_];
      const canfd_frame raw = to_wire(f);
      const std::size_t size = f.fd ? CANFD_MTU : CAN_MTU;
      std::memcpy(tx_raw_.data(), &raw, size);
      const long n = api_->write_frame(socket_, std::span<const std::byte>(tx_raw_.data(), size));
      if (n >= 0) {
        stats_.frames_written.bump();
        wait_ = Wait::nothing;
        enobufs_backoff_ = Duration{0};
        if (++next_frame_ == frame_count_) {
          counters_.sent.bump();
        }
        continue;
      }
      if (n == -EAGAIN || n == -EWOULDBLOCK) {
        stats_.send_buffer_full.bump();
        wait_ = Wait::writable;
        return;
      }
      if (n == -ENOBUFS) {
        // The interface's queue is full: keep the frame and try again shortly.
        stats_.enobufs.bump();
        wait_ = Wait::backoff;
        enobufs_backoff_ = std::clamp(enobufs_backoff_ * 2, enobufs_min_, enobufs_max_);
        return;
      }
      if (n == -EINTR) {
        continue;
      }
      if (link_lost(n)) {
        lose_link();
        return;
      }
      counters_.io_errors.bump();  // this frame cannot go out (EINVAL, EMSGSIZE): drop its packet
      stats_.dropped_packets.bump();
      next_frame_ = frame_count_ = 0;
    }
  }

  void drop_outgoing() noexcept {
    discard_outgoing();
    next_frame_ = frame_count_ = 0;
    wait_ = Wait::nothing;
    enobufs_backoff_ = Duration{0};
  }

  void lose_link() noexcept {
    api_->close_socket(socket_);
    socket_ = -1;
    set_state(TransportState::disconnected);
    drop_outgoing();
    codec_.reset();
  }

  struct Stats {
    RelaxedCounter frames_written;
    RelaxedCounter frames_read;
    RelaxedCounter enobufs;
    RelaxedCounter send_buffer_full;
    RelaxedCounter foreign_frames;
    RelaxedCounter dropped_packets;
  };

  CanUri uri_;
  CanRole role_;
  std::shared_ptr<CanSocketApi> api_;
  // I/O thread only.
  CanPacketCodec codec_;
  CanIdFilters filters_;
  Duration reopen_min_;
  Duration reopen_max_;
  Duration enobufs_min_;
  Duration enobufs_max_;
  Duration enobufs_backoff_{0};
  int socket_ = -1;
  Wait wait_ = Wait::nothing;
  std::array<proto::CanFrame, CanPacketCodec::kMaxFrames> frames_{};  // the packet being written
  std::size_t next_frame_ = 0;
  std::size_t frame_count_ = 0;
  std::array<std::byte, CANFD_MTU> rx_raw_{};
  std::array<std::byte, CANFD_MTU> tx_raw_{};
  Stats stats_;
  transports::EventFd stop_event_{"a can:// transport"};
  std::atomic<bool> stop_{false};
  std::thread thread_;
};

}  // namespace

std::unique_ptr<Transport> open_can_transport(std::string_view uri, const CanTransportOptions& options,
                                              std::shared_ptr<CanSocketApi> api) {
  const CanUri parsed = parse_can_uri(uri);
  if (!api) {
    throw InvalidArgument("open_can_transport needs a socket API");
  }
  return std::make_unique<CanTransport>(parsed, options, std::move(api));
}

std::unique_ptr<Transport> open_can_transport(std::string_view uri, const CanTransportOptions& options) {
  return open_can_transport(uri, options, make_system_can_api());
}

std::optional<CanTransportStats> can_transport_stats(const Transport& transport) noexcept {
  if (const auto* t = dynamic_cast<const CanTransport*>(&transport)) {
    return t->stats();
  }
  return std::nullopt;
}

}  // namespace mrskin
