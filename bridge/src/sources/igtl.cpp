// igtl://HOST:PORT (client) and igtl-listen://HOST:PORT (server): OpenIGTLink v1 headers; SENSOR,
// TRANSFORM, POSITION and NDARRAY bodies (docs/sources.md). The library checks the CRC and decodes
// units; the framing and the bodies are read here, bounds-checked, before anything is trusted.
#include <igtl_ndarray.h>
#include <igtl_unit.h>
#include <igtl_util.h>
#include <netdb.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <bit>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include "core.hpp"
#include "mrskin/driver/errors.hpp"

namespace mrskin::bridge::sources {
namespace {

constexpr std::size_t kHeaderBytes = 58;
constexpr std::size_t kMaxMapCells = 4096;  // 64 x 64

std::uint64_t get_be(const std::uint8_t* p, std::size_t n) noexcept {
  std::uint64_t v = 0;
  for (std::size_t i = 0; i < n; ++i) {
    v = (v << 8U) | p[i];
  }
  return v;
}
double get_f64(const std::uint8_t* p) noexcept { return std::bit_cast<double>(get_be(p, 8)); }
float get_f32(const std::uint8_t* p) noexcept {
  return std::bit_cast<float>(static_cast<std::uint32_t>(get_be(p, 4)));
}

// A fixed-width, NUL-padded header field.
std::string_view field(const std::uint8_t* p, std::size_t n) noexcept {
  const auto* c = reinterpret_cast<const char*>(p);  // NOLINT(cppcoreguidelines-pro-type-reinterpret-cast)
  return {c, strnlen(c, n)};
}

struct Header {
  std::uint16_t version = 0;
  std::string_view type;
  std::string_view device;
  std::uint64_t timestamp = 0;  // 32.32 fixed point seconds; 0: none
  std::uint64_t body_bytes = 0;
  std::uint64_t crc = 0;
};

Header parse_header(const std::uint8_t* p) noexcept {
  Header h;
  h.version = static_cast<std::uint16_t>(get_be(p, 2));
  h.type = field(p + 2, 12);
  h.device = field(p + 14, 20);
  h.timestamp = get_be(p + 34, 8);
  h.body_bytes = get_be(p + 42, 8);
  h.crc = get_be(p + 50, 8);
  return h;
}

std::int64_t timestamp_ns(std::uint64_t ts) noexcept {
  const std::uint64_t seconds = ts >> 32U;
  const std::uint64_t fraction = ts & 0xFFFFFFFFULL;
  return static_cast<std::int64_t>(seconds * 1'000'000'000ULL + ((fraction * 1'000'000'000ULL) >> 32U));
}

bool is_newton(std::uint64_t unit) noexcept {
  igtl_unit_data d{};
  if (igtl_unit_unpack(unit, &d) == 0) {
    return false;
  }
  if (d.prefix != IGTL_UNIT_PREFIX_NONE || d.unit[0] != IGTL_UNIT_SI_DERIVED_NEWTON || d.exp[0] != 1) {
    return false;
  }
  return std::all_of(d.unit + 1, d.unit + 6, [](igtl_uint8 u) { return u == 0; });
}

// Bytes per element of an NDARRAY scalar type we read, else 0.
std::size_t scalar_bytes(std::uint8_t type) noexcept {
  switch (type) {
    case IGTL_NDARRAY_STYPE_TYPE_INT8:
    case IGTL_NDARRAY_STYPE_TYPE_UINT8:
      return 1;
    case IGTL_NDARRAY_STYPE_TYPE_INT16:
    case IGTL_NDARRAY_STYPE_TYPE_UINT16:
      return 2;
    case IGTL_NDARRAY_STYPE_TYPE_INT32:
    case IGTL_NDARRAY_STYPE_TYPE_UINT32:
    case IGTL_NDARRAY_STYPE_TYPE_FLOAT32:
      return 4;
    case IGTL_NDARRAY_STYPE_TYPE_FLOAT64:
      return 8;
    default:
      return 0;
  }
}

double scalar(std::uint8_t type, const std::uint8_t* p) noexcept {
  switch (type) {
    case IGTL_NDARRAY_STYPE_TYPE_INT8:
      return static_cast<std::int8_t>(p[0]);
    case IGTL_NDARRAY_STYPE_TYPE_UINT8:
      return p[0];
    case IGTL_NDARRAY_STYPE_TYPE_INT16:
      return static_cast<std::int16_t>(get_be(p, 2));
    case IGTL_NDARRAY_STYPE_TYPE_UINT16:
      return static_cast<double>(get_be(p, 2));
    case IGTL_NDARRAY_STYPE_TYPE_INT32:
      return static_cast<std::int32_t>(get_be(p, 4));
    case IGTL_NDARRAY_STYPE_TYPE_UINT32:
      return static_cast<double>(get_be(p, 4));
    case IGTL_NDARRAY_STYPE_TYPE_FLOAT32:
      return get_f32(p);
    default:
      return get_f64(p);
  }
}

class IgtlSource final : public QueuedSource {
 public:
  IgtlSource(const Endpoint& where, bool listen, const SourceOptions& options, Clock* clock)
      : QueuedSource(options, clock),
        where_(where),
        force_gate_(options.restart_after_out_of_order),
        pose_gate_(options.restart_after_out_of_order),
        map_gate_(options.restart_after_out_of_order),
        mapper_(options.offset_drift_s_per_s),
        buffer_(kHeaderBytes + options.max_message_bytes) {
    if (listen) {
      listener_ = bind_socket(where, SOCK_STREAM, "igtl-listen source");
      port_ = bound_port(listener_.get());
    }
    if (!(options.tactile_pitch_m > 0.0 && options.reconnect_min_s > 0.0 &&
          options.reconnect_max_s >= options.reconnect_min_s)) {
      throw InvalidArgument(
          "igtl source: need tactile_pitch_m > 0 and 0 < reconnect_min_s <= reconnect_max_s");
    }
    thread_ = std::thread([this] { listener_.valid() ? serve() : connect_loop(); });
  }
  IgtlSource(const IgtlSource&) = delete;
  IgtlSource& operator=(const IgtlSource&) = delete;
  IgtlSource(IgtlSource&&) = delete;
  IgtlSource& operator=(IgtlSource&&) = delete;
  ~IgtlSource() override {
    stop_.raise();
    thread_.join();
  }
  [[nodiscard]] std::uint16_t local_port() const noexcept override { return port_; }

 private:
  // Waits for the stop signal up to timeout_ms; true when stopping.
  bool stopped(int timeout_ms) const noexcept {
    pollfd p{stop_.fd(), POLLIN, 0};
    return ::poll(&p, 1, timeout_ms) > 0;
  }

  // The client: connect, read until the peer goes, back off, again.
  void connect_loop() noexcept {
    double backoff_s = options_.reconnect_min_s;
    while (!stopped(0)) {
      Fd conn = try_connect();
      if (conn.valid()) {
        backoff_s = options_.reconnect_min_s;
        stats_.connections.fetch_add(1, std::memory_order_relaxed);
        if (session(conn.get(), false) == End::stop) {
          return;
        }
        stats_.disconnects.fetch_add(1, std::memory_order_relaxed);
      }
      if (stopped(static_cast<int>(backoff_s * 1000.0))) {
        return;
      }
      backoff_s = std::min(2.0 * backoff_s, options_.reconnect_max_s);
    }
  }

  Fd try_connect() noexcept {
    addrinfo hints{};
    hints.ai_family = AF_UNSPEC;
    hints.ai_socktype = SOCK_STREAM;
    hints.ai_flags = AI_NUMERICSERV;
    addrinfo* found = nullptr;
    const std::string port = std::to_string(where_.port);
    if (::getaddrinfo(where_.host.c_str(), port.c_str(), &hints, &found) != 0) {
      return {};
    }
    std::unique_ptr<addrinfo, decltype(&::freeaddrinfo)> list(found, &::freeaddrinfo);
    for (const addrinfo* a = found; a != nullptr; a = a->ai_next) {
      Fd fd(::socket(a->ai_family, a->ai_socktype | SOCK_NONBLOCK | SOCK_CLOEXEC, a->ai_protocol));
      if (!fd.valid()) {
        continue;
      }
      if (::connect(fd.get(), a->ai_addr, a->ai_addrlen) == 0) {
        return fd;
      }
      if (errno != EINPROGRESS) {
        continue;
      }
      std::array<pollfd, 2> p{{{fd.get(), POLLOUT, 0}, {stop_.fd(), POLLIN, 0}}};
      if (::poll(p.data(), p.size(), 1000) <= 0 || (p[1].revents & POLLIN) != 0) {
        continue;
      }
      int err = 0;
      socklen_t len = sizeof err;
      if (::getsockopt(fd.get(), SOL_SOCKET, SO_ERROR, &err, &len) == 0 && err == 0) {
        return fd;
      }
    }
    return {};
  }

  // The server: one robot at a time; a new connection replaces the current one (a robot that
  // rebooted without closing its socket must not lock itself out).
  void serve() noexcept {
    Fd conn;
    for (;;) {
      if (!conn.valid()) {
        std::array<pollfd, 2> p{{{listener_.get(), POLLIN, 0}, {stop_.fd(), POLLIN, 0}}};
        if (::poll(p.data(), p.size(), -1) < 0 && errno != EINTR) {
          return;
        }
        if ((p[1].revents & POLLIN) != 0) {
          return;
        }
        conn = Fd(::accept4(listener_.get(), nullptr, nullptr, SOCK_NONBLOCK | SOCK_CLOEXEC));
        if (!conn.valid()) {
          continue;
        }
        stats_.connections.fetch_add(1, std::memory_order_relaxed);
      }
      const End end = session(conn.get(), true);
      if (end == End::stop) {
        return;
      }
      stats_.disconnects.fetch_add(1, std::memory_order_relaxed);
      conn.reset();
      if (end == End::replaced) {
        conn = std::move(next_);
        stats_.connections.fetch_add(1, std::memory_order_relaxed);
      }
    }
  }

  enum class End : unsigned char { stop, closed, replaced };

  End session(int conn, bool listening) noexcept {
    // A new connection may be a new robot, with its own clock and stamps.
    force_gate_.reset();
    pose_gate_.reset();
    map_gate_.reset();
    mapper_.reset();
    pose_ = {};
    std::size_t have = 0;
    for (;;) {
      std::array<pollfd, 3> p{{{conn, POLLIN, 0}, {stop_.fd(), POLLIN, 0}, {-1, POLLIN, 0}}};
      if (listening) {
        p[2].fd = listener_.get();
      }
      const int timeout_ms = has_pending() ? 1 : 100;
      if (::poll(p.data(), p.size(), timeout_ms) < 0 && errno != EINTR) {
        return End::closed;
      }
      if ((p[1].revents & POLLIN) != 0) {
        return End::stop;
      }
      (void)flush_pending();
      if ((p[2].revents & POLLIN) != 0) {
        Fd next(::accept4(listener_.get(), nullptr, nullptr, SOCK_NONBLOCK | SOCK_CLOEXEC));
        if (next.valid()) {
          next_ = std::move(next);
          return End::replaced;
        }
      }
      if ((p[0].revents & (POLLIN | POLLHUP | POLLERR)) == 0) {
        continue;
      }
      const ssize_t n = ::recv(conn, buffer_.data() + have, buffer_.size() - have, 0);
      if (n == 0 || (n < 0 && errno != EAGAIN && errno != EINTR)) {
        return End::closed;
      }
      if (n < 0) {
        continue;
      }
      have += static_cast<std::size_t>(n);
      // Every complete message in the buffer.
      std::size_t used = 0;
      while (have - used >= kHeaderBytes) {
        const Header h = parse_header(buffer_.data() + used);
        if (h.body_bytes > options_.max_message_bytes) {
          // The framing cannot be trusted past this header: drop the connection.
          stats_.count(Drop::oversized);
          return End::closed;
        }
        const std::size_t total = kHeaderBytes + h.body_bytes;
        if (have - used < total) {
          break;
        }
        handle(h, std::span(buffer_.data() + used + kHeaderBytes, h.body_bytes));
        used += total;
      }
      std::memmove(buffer_.data(), buffer_.data() + used, have - used);
      have -= used;
    }
  }

  void handle(const Header& h, std::span<std::uint8_t> body) noexcept {
    if (h.version != 1 || crc64(body.data(), body.size(), 0) != h.crc) {
      stats_.count(Drop::malformed);
      return;
    }
    const TimePoint arrival = now();
    const std::int64_t robot_ns = h.timestamp != 0 ? timestamp_ns(h.timestamp) : arrival.count();
    if (h.type == "SENSOR" && h.device == options_.igtl_force_device) {
      sensor(body, robot_ns, arrival);
    } else if ((h.type == "TRANSFORM" || h.type == "POSITION") && h.device == options_.igtl_pose_device) {
      pose(h.type == "TRANSFORM", body, robot_ns);
    } else if (h.type == "NDARRAY" && h.device == options_.igtl_map_device) {
      pressure_map(body, robot_ns, arrival);
    } else {
      stats_.count(Drop::unsupported);
    }
  }

  // SENSOR: larray u8, status u8, unit u64, larray x float64; value 0 is the normal force.
  void sensor(std::span<const std::uint8_t> body, std::int64_t robot_ns, TimePoint arrival) noexcept {
    if (body.size() < 10 || body[0] == 0 || body.size() != 10 + 8 * std::size_t{body[0]}) {
      stats_.count(Drop::malformed);
      return;
    }
    if (!is_newton(get_be(body.data() + 2, 8))) {
      stats_.count(Drop::unsupported);
      return;
    }
    emit(get_f64(body.data() + 10), 0.0, 0.0, robot_ns, arrival, force_gate_);
  }

  // TRANSFORM: 12 float32, the translation last; POSITION: 3 float32 then an optional quaternion.
  // Millimetres in the tissue frame, z along the outward normal with the surface at 0.
  void pose(bool transform, std::span<const std::uint8_t> body, std::int64_t robot_ns) noexcept {
    const std::size_t at = transform ? 36 : 0;
    if (transform ? body.size() != 48 : (body.size() != 12 && body.size() != 24 && body.size() != 28)) {
      stats_.count(Drop::malformed);
      return;
    }
    Pose next;
    next.x_m = 1e-3 * get_f32(body.data() + at);
    next.y_m = 1e-3 * get_f32(body.data() + at + 4);
    next.indentation_m = -1e-3 * get_f32(body.data() + at + 8);
    SlaveSample check;
    check.contact_x_m = next.x_m;
    check.contact_y_m = next.y_m;
    check.indentation_m = next.indentation_m;
    if (!values_ok(check, options_, stats_) || !ordered(pose_gate_, robot_ns)) {
      return;
    }
    pose_ = next;
  }

  // NDARRAY: type u8, dim u8, dim x u16 sizes, then the elements, row-major. A rows x cols map of
  // pressures in Pa; force = sum(max(p, 0)) x pitch^2, contact = the pressure-weighted centroid
  // from the array's centre (column index along +x, row index along +y).
  void pressure_map(std::span<const std::uint8_t> body, std::int64_t robot_ns, TimePoint arrival) noexcept {
    if (body.size() < 2) {
      stats_.count(Drop::malformed);
      return;
    }
    const std::uint8_t type = body[0];
    const std::size_t dim = body[1];
    const std::size_t element = scalar_bytes(type);
    if (element == 0 || dim != 2) {
      stats_.count(Drop::unsupported);
      return;
    }
    if (body.size() < 2 + 2 * dim) {
      stats_.count(Drop::malformed);
      return;
    }
    const std::size_t rows = get_be(body.data() + 2, 2);
    const std::size_t cols = get_be(body.data() + 4, 2);
    if (rows * cols > kMaxMapCells) {
      stats_.count(Drop::oversized);
      return;
    }
    if (rows == 0 || cols == 0 || body.size() != 6 + rows * cols * element) {
      stats_.count(Drop::malformed);
      return;
    }
    double sum_Pa = 0.0;
    double mx = 0.0;
    double my = 0.0;
    const double pitch_m = options_.tactile_pitch_m;
    for (std::size_t r = 0; r < rows; ++r) {
      for (std::size_t c = 0; c < cols; ++c) {
        const double p_Pa = scalar(type, body.data() + 6 + (r * cols + c) * element);
        if (!std::isfinite(p_Pa)) {
          stats_.count(Drop::non_finite);
          return;
        }
        const double w = std::max(p_Pa, 0.0);  // sensor offset noise below zero presses nothing
        sum_Pa += w;
        mx += w * (static_cast<double>(c) - 0.5 * static_cast<double>(cols - 1)) * pitch_m;
        my += w * (static_cast<double>(r) - 0.5 * static_cast<double>(rows - 1)) * pitch_m;
      }
    }
    const double force_N = sum_Pa * pitch_m * pitch_m;
    const double dx_m = sum_Pa > 0.0 ? mx / sum_Pa : 0.0;
    const double dy_m = sum_Pa > 0.0 ? my / sum_Pa : 0.0;
    emit(force_N, dx_m, dy_m, robot_ns, arrival, map_gate_);
  }

  // A force sample with the latest pose (contact shifted by dx, dy).
  void emit(double force_N, double dx_m, double dy_m, std::int64_t robot_ns, TimePoint arrival,
            OrderGate& gate) noexcept {
    SlaveSample s;
    s.force_N = force_N;
    s.indentation_m = pose_.indentation_m;
    s.contact_x_m = pose_.x_m + dx_m;
    s.contact_y_m = pose_.y_m + dy_m;
    s.tip_radius_m = options_.tip_radius_m;
    if (!values_ok(s, options_, stats_) || !ordered(gate, robot_ns)) {
      return;
    }
    s.stamp = mapper_.map(robot_ns, arrival);
    s.received = arrival;
    s.valid = true;
    publish(s);
  }

  bool ordered(OrderGate& gate, std::int64_t robot_ns) noexcept {
    switch (gate.check(robot_ns)) {
      case OrderGate::Verdict::duplicate:
        stats_.count(Drop::duplicate);
        return false;
      case OrderGate::Verdict::out_of_order:
        stats_.count(Drop::out_of_order);
        return false;
      case OrderGate::Verdict::restart:
        stats_.restarts.fetch_add(1, std::memory_order_relaxed);
        mapper_.reset();
        return true;
      case OrderGate::Verdict::accept:
        return true;
    }
    return false;
  }

  struct Pose {
    double x_m = 0.0;
    double y_m = 0.0;
    double indentation_m = 0.0;
  };

  Endpoint where_;
  Fd listener_;
  Fd next_;
  std::uint16_t port_ = 0;
  StopSignal stop_;
  OrderGate force_gate_;
  OrderGate pose_gate_;
  OrderGate map_gate_;
  ClockMapper mapper_;
  Pose pose_;
  std::vector<std::uint8_t> buffer_;
  std::thread thread_;
};

}  // namespace

std::unique_ptr<StreamSource> open_igtl(const Endpoint& where, bool listen, const SourceOptions& options,
                                        Clock* clock) {
  return std::make_unique<IgtlSource>(where, listen, options, clock);
}

}  // namespace mrskin::bridge::sources
