// igtl://HOST:PORT (client) and igtl-listen://HOST:PORT (server): OpenIGTLink v1 headers; SENSOR,
// TRANSFORM, POSITION and NDARRAY bodies (docs/sources.md). The library checks the CRC and decodes
// units; the framing and the bodies are read here, bounds-checked, before anything is trusted.
#include <fmt/format.h>
#include <igtl_ndarray.h>
#include <igtl_unit.h>
#include <igtl_util.h>
#include <netdb.h>
#include <poll.h>
#include <pthread.h>
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
#include "igtl_parse.hpp"
#include "mrskin/driver/errors.hpp"

namespace mrskin::bridge::sources {
namespace {

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

// The factor to newtons of a SENSOR unit: newton with any SI prefix (mN, kN, ...); 0 otherwise.
double newton_scale(std::uint64_t unit) noexcept {
  igtl_unit_data d{};
  if (igtl_unit_unpack(unit, &d) == 0 || d.unit[0] != IGTL_UNIT_SI_DERIVED_NEWTON || d.exp[0] != 1 ||
      !std::all_of(d.unit + 1, d.unit + 6, [](igtl_uint8 u) { return u == 0; })) {
    return 0.0;
  }
  switch (d.prefix) {
    case IGTL_UNIT_PREFIX_NONE:
      return 1.0;
    case IGTL_UNIT_PREFIX_DEKA:
      return 1e1;
    case IGTL_UNIT_PREFIX_HECTO:
      return 1e2;
    case IGTL_UNIT_PREFIX_KILO:
      return 1e3;
    case IGTL_UNIT_PREFIX_MEGA:
      return 1e6;
    case IGTL_UNIT_PREFIX_DECI:
      return 1e-1;
    case IGTL_UNIT_PREFIX_CENTI:
      return 1e-2;
    case IGTL_UNIT_PREFIX_MILLI:
      return 1e-3;
    case IGTL_UNIT_PREFIX_MICRO:
      return 1e-6;
    case IGTL_UNIT_PREFIX_NANO:
      return 1e-9;
    default:
      return 0.0;  // giga and beyond, pico and below: no contact force is written that way
  }
}

bool matches(std::string_view wanted, std::string_view name) noexcept {
  return wanted == "*" || wanted == name;
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

// Protocol 3 (header version 2): an extended header, the content, then metadata; the content is
// what a version 1 body holds. False when the extended header does not fit the body.
bool version2_content(std::span<const std::uint8_t>& content) noexcept {
  constexpr std::size_t kExtendedHeaderBytes = 12;
  if (content.size() < kExtendedHeaderBytes) {
    return false;
  }
  const std::size_t ext = get_be(content.data(), 2);
  const std::size_t meta_header = get_be(content.data() + 2, 2);
  const std::size_t meta = get_be(content.data() + 4, 4);
  if (ext < kExtendedHeaderBytes || ext + meta_header + meta > content.size()) {
    return false;
  }
  content = content.subspan(ext, content.size() - ext - meta_header - meta);
  return true;
}

}  // namespace

// ---- parsing, without I/O (igtl_parse.hpp) ------------------------------------------------------

std::string_view igtl_field(const std::uint8_t* p, std::size_t n) noexcept {
  const auto* c = reinterpret_cast<const char*>(p);  // NOLINT(cppcoreguidelines-pro-type-reinterpret-cast)
  return {c, strnlen(c, n)};
}

IgtlHeader parse_igtl_header(const std::uint8_t* p) noexcept {
  IgtlHeader h;
  h.version = static_cast<std::uint16_t>(get_be(p, 2));
  h.type = igtl_field(p + 2, 12);
  h.device = igtl_field(p + 14, 20);
  h.timestamp = get_be(p + 34, 8);
  h.body_bytes = get_be(p + 42, 8);
  h.crc = get_be(p + 50, 8);
  return h;
}

std::int64_t igtl_timestamp_ns(std::uint64_t timestamp) noexcept {
  const std::uint64_t seconds = timestamp >> 32U;
  const std::uint64_t fraction = timestamp & 0xFFFFFFFFULL;
  return static_cast<std::int64_t>(seconds * 1'000'000'000ULL + ((fraction * 1'000'000'000ULL) >> 32U));
}

IgtlFrame next_igtl_frame(std::span<const std::uint8_t> stream, std::size_t max_body_bytes) noexcept {
  IgtlFrame f;
  if (stream.size() < kIgtlHeaderBytes) {
    return f;
  }
  f.header = parse_igtl_header(stream.data());
  if (f.header.body_bytes > max_body_bytes) {
    f.status = IgtlFrame::Status::oversized;
    return f;
  }
  const std::size_t total = kIgtlHeaderBytes + f.header.body_bytes;
  if (stream.size() >= total) {
    f.status = IgtlFrame::Status::complete;
    f.bytes = total;
  }
  return f;
}

IgtlMessage open_igtl_message(const IgtlHeader& h, std::span<const std::uint8_t> body) noexcept {
  IgtlMessage m;
  m.content = body;
  if (h.version != 1 && h.version != 2) {
    m.fault = IgtlFault::version;
    return m;
  }
  // The C API takes a non-const pointer; crc64 only reads.
  // NOLINTNEXTLINE(cppcoreguidelines-pro-type-const-cast)
  if (crc64(const_cast<std::uint8_t*>(body.data()), body.size(), 0) != h.crc) {
    m.fault = IgtlFault::crc;
    return m;
  }
  if (h.version == 2 && !version2_content(m.content)) {
    m.fault = IgtlFault::extended_header;
    return m;
  }
  if (h.type == "SENSOR") {
    m.kind = IgtlKind::force;
  } else if (h.type == "TRANSFORM" || h.type == "POSITION" || h.type == "QTDATA" || h.type == "TDATA") {
    m.kind = IgtlKind::pose;
  } else if (h.type == "NDARRAY") {
    m.kind = IgtlKind::map;
  } else {
    m.fault = IgtlFault::type;
  }
  return m;
}

IgtlForce parse_igtl_sensor(std::span<const std::uint8_t> content,
                            const std::array<double, 9>& robot_to_tissue) noexcept {
  IgtlForce f;
  if (content.size() < 10 || content[0] == 0 || content.size() != 10 + 8 * std::size_t{content[0]}) {
    f.fault = IgtlFault::sensor_length;
    return f;
  }
  const std::size_t n = content[0];
  f.values = n;
  if (n != 1 && n != 3 && n != 6) {
    f.fault = IgtlFault::sensor_count;
    return f;
  }
  const double scale = newton_scale(get_be(content.data() + 2, 8));
  if (scale == 0.0) {
    f.fault = IgtlFault::sensor_unit;
    return f;
  }
  std::array<double, 6> v{};
  for (std::size_t i = 0; i < n; ++i) {
    v.at(i) = get_f64(content.data() + 10 + 8 * i) * scale;
    if (!std::isfinite(v.at(i))) {
      f.fault = IgtlFault::non_finite;
      return f;
    }
  }
  // The contact force is the force's component along the tissue's outward normal.
  f.normal_N = n == 1 ? v[0] : rotate(robot_to_tissue, v[0], v[1], v[2])[2];
  return f;
}

IgtlPosition parse_igtl_pose(std::string_view type, std::span<const std::uint8_t> content,
                             std::string_view tool) noexcept {
  IgtlPosition p;
  std::size_t at = 0;
  bool ok = true;
  if (type == "TRANSFORM") {
    at = 36;
    ok = content.size() == 48;
  } else if (type == "POSITION") {
    ok = content.size() == 12 || content.size() == 24 || content.size() == 28;
  } else {
    const bool tdata = type == "TDATA";
    const std::size_t element = tdata ? kIgtlTdataElementBytes : kIgtlQtdataElementBytes;
    ok = !content.empty() && content.size() % element == 0;
    if (ok) {
      bool found = false;
      for (std::size_t e = 0; e < content.size() && !found; e += element) {
        if (matches(tool, igtl_field(content.data() + e, kIgtlTrackNameBytes))) {
          at = e + kIgtlTrackNameBytes + 2 + (tdata ? 36 : 0);
          found = true;
        }
      }
      if (!found) {
        p.fault = IgtlFault::no_tool;
        return p;
      }
    }
  }
  if (!ok) {
    p.fault = IgtlFault::pose_length;
    return p;
  }
  p.x_mm = get_f32(content.data() + at);
  p.y_mm = get_f32(content.data() + at + 4);
  p.z_mm = get_f32(content.data() + at + 8);
  return p;
}

IgtlPressureMap parse_igtl_pressure_map(std::span<const std::uint8_t> content, double pitch_m) noexcept {
  IgtlPressureMap m;
  if (content.size() < 2) {
    m.fault = IgtlFault::map_length;
    return m;
  }
  m.scalar_type = content[0];
  m.dims = content[1];
  const std::size_t element = scalar_bytes(m.scalar_type);
  if (element == 0 || m.dims != 2) {
    m.fault = IgtlFault::map_type;
    return m;
  }
  if (content.size() < 2 + 2 * m.dims) {
    m.fault = IgtlFault::map_length;
    return m;
  }
  const std::size_t rows = get_be(content.data() + 2, 2);
  const std::size_t cols = get_be(content.data() + 4, 2);
  m.rows = rows;
  m.cols = cols;
  if (rows * cols > kIgtlMaxMapCells) {
    m.fault = IgtlFault::map_oversized;
    return m;
  }
  if (rows == 0 || cols == 0 || content.size() != 6 + rows * cols * element) {
    m.fault = IgtlFault::map_length;
    return m;
  }
  double sum_Pa = 0.0;
  double mx = 0.0;
  double my = 0.0;
  for (std::size_t r = 0; r < rows; ++r) {
    for (std::size_t c = 0; c < cols; ++c) {
      const double p_Pa = scalar(m.scalar_type, content.data() + 6 + (r * cols + c) * element);
      if (!std::isfinite(p_Pa)) {
        m.fault = IgtlFault::non_finite;
        return m;
      }
      const double w = std::max(p_Pa, 0.0);  // sensor offset noise below zero presses nothing
      sum_Pa += w;
      mx += w * (static_cast<double>(c) - 0.5 * static_cast<double>(cols - 1)) * pitch_m;
      my += w * (static_cast<double>(r) - 0.5 * static_cast<double>(rows - 1)) * pitch_m;
    }
  }
  m.force_N = sum_Pa * pitch_m * pitch_m;
  // A weighted mean of the cells' offsets lies inside the array, but products with subnormal
  // weights round coarsely: 8e-317 Pa on one corner cell put it 2.3e-9 m outside (the fuzzer's
  // find, now in the corpus). Held to the array's extent.
  const double half_x_m = 0.5 * static_cast<double>(cols - 1) * pitch_m;
  const double half_y_m = 0.5 * static_cast<double>(rows - 1) * pitch_m;
  m.dx_m = sum_Pa > 0.0 ? std::clamp(mx / sum_Pa, -half_x_m, half_x_m) : 0.0;
  m.dy_m = sum_Pa > 0.0 ? std::clamp(my / sum_Pa, -half_y_m, half_y_m) : 0.0;
  return m;
}

namespace {

class IgtlSource final : public QueuedSource {
 public:
  IgtlSource(const Endpoint& where, bool listen, const SourceOptions& options, Clock* clock)
      : QueuedSource(options, clock),
        where_(where),
        force_gate_(options.restart_after_out_of_order),
        pose_gate_(options.restart_after_out_of_order),
        map_gate_(options.restart_after_out_of_order),
        mapper_(options.offset_drift_s_per_s),
        buffer_(kIgtlHeaderBytes + options.max_message_bytes) {
    if (listen) {
      listener_ = bind_socket(where, SOCK_STREAM, "igtl-listen source");
      port_ = bound_port(listener_.get());
    }
    if (!(options.tactile_pitch_m > 0.0 && options.reconnect_min_s > 0.0 &&
          options.reconnect_max_s >= options.reconnect_min_s)) {
      throw InvalidArgument(
          "igtl source: need tactile_pitch_m > 0 and 0 < reconnect_min_s <= reconnect_max_s");
    }
    thread_ = std::thread([this] {
      (void)::pthread_setname_np(::pthread_self(), "mrskin-igtl");
      listener_.valid() ? serve() : connect_loop();
    });
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

  // The client: connect, read until the peer goes, back off, again. A failure is reported at
  // once, and again only when its reason changes.
  void connect_loop() noexcept {
    double backoff_s = options_.reconnect_min_s;
    std::string reported;
    std::uint64_t failed = 0;
    while (!stopped(0)) {
      std::string why;
      Fd conn;
      try {
        conn = try_connect(why);
      } catch (...) {  // out of memory for the reason's text: a failed attempt all the same
        conn.reset();
      }
      if (conn.valid()) {
        backoff_s = options_.reconnect_min_s;
        stats_.connections.bump();
        note(false, [&] {
          return failed == 0
                     ? fmt::format("{}: connected to the robot", name())
                     : fmt::format("{}: connected to the robot after {} failed attempts", name(), failed);
        });
        reported.clear();
        failed = 0;
        if (session(conn.get(), false) == End::stop) {
          return;
        }
        stats_.disconnects.bump();
        note(true, [&] { return fmt::format("{}: the robot closed the connection; reconnecting", name()); });
      } else {
        stats_.connect_failures.bump();
        ++failed;
        if (why != reported) {
          note(true, [&] {
            return fmt::format("{}: cannot connect: {}; retrying after {} s, backing off to every {} s",
                               name(), why, options_.reconnect_min_s, options_.reconnect_max_s);
          });
          try {
            reported = why;
          } catch (...) {  // NOLINT(bugprone-empty-catch): reported again next time
          }
        }
      }
      if (stopped(static_cast<int>(backoff_s * 1000.0))) {
        return;
      }
      backoff_s = std::min(2.0 * backoff_s, options_.reconnect_max_s);
    }
  }

  // Adds make_text()'s event; out of memory it is lost, never the I/O thread.
  template <class MakeText>
  void note(bool warning, MakeText&& make_text) noexcept {
    try {
      events_.add(warning, make_text());
    } catch (...) {  // NOLINT(bugprone-empty-catch): an event lost to a full heap
    }
  }

  [[nodiscard]] std::string name() const {
    const bool v6 = where_.host.find(':') != std::string::npos;
    return fmt::format("{}://{}{}{}:{}", listener_.valid() ? "igtl-listen" : "igtl", v6 ? "[" : "",
                       where_.host, v6 ? "]" : "", listener_.valid() ? port_ : where_.port);
  }

  Fd try_connect(std::string& why) {
    addrinfo hints{};
    hints.ai_family = AF_UNSPEC;
    hints.ai_socktype = SOCK_STREAM;
    hints.ai_flags = AI_NUMERICSERV;
    addrinfo* found = nullptr;
    const std::string port = std::to_string(where_.port);
    if (const int rc = ::getaddrinfo(where_.host.c_str(), port.c_str(), &hints, &found); rc != 0) {
      why = fmt::format("cannot resolve '{}': {}", where_.host, ::gai_strerror(rc));
      return {};
    }
    std::unique_ptr<addrinfo, decltype(&::freeaddrinfo)> list(found, &::freeaddrinfo);
    why = "no address to try";
    for (const addrinfo* a = found; a != nullptr; a = a->ai_next) {
      Fd fd(::socket(a->ai_family, a->ai_socktype | SOCK_NONBLOCK | SOCK_CLOEXEC, a->ai_protocol));
      if (!fd.valid()) {
        why = std::strerror(errno);
        continue;
      }
      if (::connect(fd.get(), a->ai_addr, a->ai_addrlen) == 0) {
        return fd;
      }
      if (errno != EINPROGRESS) {
        why = std::strerror(errno);
        continue;
      }
      std::array<pollfd, 2> p{{{fd.get(), POLLOUT, 0}, {stop_.fd(), POLLIN, 0}}};
      if (::poll(p.data(), p.size(), 1000) <= 0 || (p[1].revents & POLLIN) != 0) {
        why = "no answer within 1 s";
        continue;
      }
      int err = 0;
      socklen_t len = sizeof err;
      if (::getsockopt(fd.get(), SOL_SOCKET, SO_ERROR, &err, &len) == 0 && err == 0) {
        return fd;
      }
      why = std::strerror(err);
    }
    return {};
  }

  // The peer's numeric address of an accepted connection.
  static std::string peer_of(int fd) {
    sockaddr_storage a{};
    socklen_t len = sizeof a;
    std::array<char, NI_MAXHOST> host{};
    std::array<char, NI_MAXSERV> serv{};
    // NOLINTNEXTLINE(cppcoreguidelines-pro-type-reinterpret-cast): the socket API's own cast
    auto* sa = reinterpret_cast<sockaddr*>(&a);
    if (::getpeername(fd, sa, &len) != 0 ||
        ::getnameinfo(sa, len, host.data(), host.size(), serv.data(), serv.size(),
                      NI_NUMERICHOST | NI_NUMERICSERV) != 0) {
      return "an unknown address";
    }
    return a.ss_family == AF_INET6 ? fmt::format("[{}]:{}", host.data(), serv.data())
                                   : fmt::format("{}:{}", host.data(), serv.data());
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
        stats_.connections.bump();
        note(false,
             [&] { return fmt::format("{}: a robot connected from {}", name(), peer_of(conn.get())); });
      }
      const End end = session(conn.get(), true);
      if (end == End::stop) {
        return;
      }
      stats_.disconnects.bump();
      conn.reset();
      if (end == End::replaced) {
        conn = std::move(next_);
        stats_.connections.bump();
        note(true, [&] {
          return fmt::format("{}: a robot connected from {} and replaces the current one", name(),
                             peer_of(conn.get()));
        });
      } else {
        note(true, [&] { return fmt::format("{}: the robot disconnected; waiting for it", name()); });
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
      for (;;) {
        const IgtlFrame f =
            next_igtl_frame(std::span(buffer_.data() + used, have - used), options_.max_message_bytes);
        const IgtlHeader& h = f.header;
        if (f.status == IgtlFrame::Status::oversized) {
          // The framing cannot be trusted past this header: drop the connection.
          drop(stats_, events_, DropReason::oversized, [&] {
            return fmt::format(
                "OpenIGTLink {} from '{}' announces a body of {} bytes (at most {}): connection "
                "closed, its framing cannot be trusted",
                h.type, h.device, h.body_bytes, options_.max_message_bytes);
          });
          return End::closed;
        }
        if (f.status == IgtlFrame::Status::incomplete) {
          break;
        }
        handle(h, std::span<const std::uint8_t>(buffer_.data() + used + kIgtlHeaderBytes, h.body_bytes));
        used += f.bytes;
      }
      std::memmove(buffer_.data(), buffer_.data() + used, have - used);
      have -= used;
    }
  }

  void handle(const IgtlHeader& h, std::span<const std::uint8_t> body) noexcept {
    const IgtlMessage m = open_igtl_message(h, body);
    switch (m.fault) {
      case IgtlFault::none:
        break;
      case IgtlFault::version:
        drop(stats_, events_, DropReason::format, [&] {
          return fmt::format(
              "OpenIGTLink message with header version {} dropped: this source reads versions 1 "
              "and 2 (protocols 1 to 3)",
              h.version);
        });
        return;
      case IgtlFault::crc:
        drop(stats_, events_, DropReason::crc, [&] {
          return fmt::format("OpenIGTLink {} from '{}' dropped: its body does not match its CRC-64", h.type,
                             h.device);
        });
        return;
      case IgtlFault::extended_header:
        drop(stats_, events_, DropReason::length, [&] {
          return fmt::format(
              "OpenIGTLink {} from '{}' dropped: its version 2 extended header does not fit its body", h.type,
              h.device);
        });
        return;
      default:  // IgtlFault::type: open_igtl_message() gives no other
        drop(stats_, events_, DropReason::type, [&] {
          return fmt::format(
              "OpenIGTLink {} from '{}' ignored: this source reads SENSOR (force), TRANSFORM, "
              "POSITION, QTDATA, TDATA (pose) and NDARRAY (pressure map)",
              h.type, h.device);
        });
        return;
    }
    const TimePoint arrival = now();
    const std::int64_t robot_ns = h.timestamp != 0 ? igtl_timestamp_ns(h.timestamp) : arrival.count();
    switch (m.kind) {
      case IgtlKind::force:
        if (wanted(options_.igtl_force_device, h, EventKey::device_force, "force_device")) {
          sensor(h.device, m.content, robot_ns, arrival);
        }
        break;
      case IgtlKind::pose:
        if (wanted(options_.igtl_pose_device, h, EventKey::device_pose, "pose_device")) {
          pose(h.type, h.device, m.content, robot_ns);
        }
        break;
      case IgtlKind::map:
        if (wanted(options_.igtl_map_device, h, EventKey::device_map, "map_device")) {
          pressure_map(m.content, robot_ns, arrival);
        }
        break;
    }
  }

  // True when the message's device name is the one configured for its kind; else counted and,
  // once per kind, explained with the key that takes it.
  bool wanted(const std::string& name, const IgtlHeader& h, EventKey key, std::string_view option) noexcept {
    if (matches(name, h.device)) {
      return true;
    }
    stats_.count(DropReason::device);
    events_.once(static_cast<unsigned>(key), true, [&] {
      return fmt::format(
          "OpenIGTLink {} from device '{}' ignored: this source takes {} from '{}'; set "
          "{}={} (in the source URI or the daemon's [stream] table; * takes any name)",
          h.type, h.device,
          option == "force_device"  ? "forces"
          : option == "pose_device" ? "poses"
                                    : "pressure maps",
          name, option, h.device);
    });
    return false;
  }

  // SENSOR: a pulling force (< 0) is no contact.
  void sensor(std::string_view device, std::span<const std::uint8_t> body, std::int64_t robot_ns,
              TimePoint arrival) noexcept {
    const IgtlForce f = parse_igtl_sensor(body, options_.robot_to_tissue);
    switch (f.fault) {
      case IgtlFault::none:
        emit(std::max(f.normal_N, 0.0), 0.0, 0.0, robot_ns, arrival, force_gate_);
        return;
      case IgtlFault::sensor_length:
        drop(stats_, events_, DropReason::length, [&] {
          return fmt::format("SENSOR from '{}' dropped: a body of {} bytes does not hold its values", device,
                             body.size());
        });
        return;
      case IgtlFault::sensor_count:
        drop(stats_, events_, DropReason::length, [&] {
          return fmt::format(
              "SENSOR from '{}' with {} values dropped: send 1 (the normal force), 3 (a force "
              "vector) or 6 (a wrench: force, then torque)",
              device, f.values);
        });
        return;
      case IgtlFault::sensor_unit:
        drop(stats_, events_, DropReason::unit, [&] {
          return fmt::format(
              "SENSOR from '{}' dropped: its unit is not a force; send newtons (N, or with a "
              "prefix: mN, kN, ...)",
              device);
        });
        return;
      default:  // IgtlFault::non_finite
        drop(stats_, events_, DropReason::non_finite,
             [&] { return fmt::format("SENSOR from '{}' dropped: a value is NaN or Inf", device); });
        return;
    }
  }

  // A pose: millimetres in the robot's frame, mapped into the tissue frame (z along the outward
  // normal, the surface at 0).
  void pose(std::string_view type, std::string_view device, std::span<const std::uint8_t> body,
            std::int64_t robot_ns) noexcept {
    const IgtlPosition at = parse_igtl_pose(type, body, options_.igtl_pose_tool);
    if (at.fault == IgtlFault::no_tool) {
      no_tool(type, device, body);
      return;
    }
    if (at.fault != IgtlFault::none) {
      drop(stats_, events_, DropReason::length, [&] {
        return fmt::format("OpenIGTLink {} from '{}' dropped: a body of {} bytes does not fit its type", type,
                           device, body.size());
      });
      return;
    }
    const std::array<double, 3> p =
        rotate(options_.robot_to_tissue, 1e-3 * at.x_mm, 1e-3 * at.y_mm, 1e-3 * at.z_mm);
    Pose next;
    next.x_m = p[0] + options_.robot_origin_m[0];
    next.y_m = p[1] + options_.robot_origin_m[1];
    next.indentation_m = -(p[2] + options_.robot_origin_m[2]);
    SlaveSample check;
    check.contact_x_m = next.x_m;
    check.contact_y_m = next.y_m;
    check.indentation_m = next.indentation_m;
    if (!values_ok(check, options_, stats_, events_) || !ordered(pose_gate_, robot_ns)) {
      return;
    }
    pose_ = next;
    stats_.poses.bump();
  }

  // A QTDATA or TDATA body without the tool pose_tool names: counted, explained once.
  void no_tool(std::string_view type, std::string_view device, std::span<const std::uint8_t> body) noexcept {
    const std::size_t element = type == "TDATA" ? kIgtlTdataElementBytes : kIgtlQtdataElementBytes;
    stats_.count(DropReason::device);
    events_.once(static_cast<unsigned>(EventKey::pose_tool), true, [&] {
      std::string tools;
      for (std::size_t at = 0; at < body.size(); at += element) {
        tools += (tools.empty() ? "'" : ", '") +
                 std::string(igtl_field(body.data() + at, kIgtlTrackNameBytes)) + "'";
      }
      return fmt::format("{} from '{}' has no tool '{}' (it carries {}): set pose_tool=NAME (or *)", type,
                         device, options_.igtl_pose_tool, tools);
    });
  }

  // NDARRAY: a rows x cols map of pressures; the force and the contact's shift from the array's
  // centre (column index along +x, row index along +y).
  void pressure_map(std::span<const std::uint8_t> body, std::int64_t robot_ns, TimePoint arrival) noexcept {
    const IgtlPressureMap m = parse_igtl_pressure_map(body, options_.tactile_pitch_m);
    switch (m.fault) {
      case IgtlFault::none:
        emit(m.force_N, m.dx_m, m.dy_m, robot_ns, arrival, map_gate_);
        return;
      case IgtlFault::map_type:
        drop(stats_, events_, DropReason::type, [&] {
          return fmt::format(
              "NDARRAY of scalar type {} in {} dimensions dropped: send a 2-D map of real "
              "numbers (int8..uint32, float32, float64)",
              m.scalar_type, m.dims);
        });
        return;
      case IgtlFault::map_oversized:
        drop(stats_, events_, DropReason::oversized, [&] {
          return fmt::format("NDARRAY of {} x {} dropped: at most {} cells", m.rows, m.cols,
                             kIgtlMaxMapCells);
        });
        return;
      case IgtlFault::non_finite:
        drop(stats_, events_, DropReason::non_finite,
             [] { return std::string("NDARRAY dropped: a cell is NaN or Inf"); });
        return;
      default:  // IgtlFault::map_length
        drop(stats_, events_, DropReason::length, [&] {
          return fmt::format("NDARRAY dropped: a body of {} bytes does not fit its sizes", body.size());
        });
        return;
    }
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
    if (!values_ok(s, options_, stats_, events_) || !ordered(gate, robot_ns)) {
      return;
    }
    s.stamp = mapper_.map(robot_ns, arrival);
    s.received = arrival;
    s.valid = true;
    publish(s);
  }

  bool ordered(OrderGate& gate, std::int64_t robot_ns) noexcept {
    return admit(gate, robot_ns, mapper_, stats_, events_, "OpenIGTLink message");
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
