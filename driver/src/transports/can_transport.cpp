#include <fmt/format.h>
#include <linux/can.h>
#include <linux/can/error.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <sys/eventfd.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <charconv>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <thread>
#include <utility>

#include "can_socket_api.hpp"
#include "event_fd.hpp"
#include "mrskin/driver/queued_transport.hpp"

namespace mrskin {
namespace proto = mrskin::protocol;

// ============================================================================ URI

namespace {

constexpr std::string_view kScheme = "can://";
constexpr std::string_view kUriForm = "can://IFACE?node=N[&fd=1], e.g. can://can0?node=3";

[[noreturn]] void bad_uri(std::string_view uri, std::string_view what) {
  throw InvalidArgument(fmt::format("'{}': {} (expected {})", uri, what, kUriForm));
}

}  // namespace

CanUri parse_can_uri(std::string_view uri) {
  if (!uri.starts_with(kScheme)) {
    bad_uri(uri, "not a can:// URI");
  }
  const std::string_view rest = uri.substr(kScheme.size());
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

// ============================================================================ codec

namespace {

bool sent_by_host(const proto::Message& m) noexcept {
  return std::holds_alternative<proto::IdentifyRequest>(m) ||
         std::holds_alternative<proto::ValveCurrents>(m) || std::holds_alternative<proto::CellTargets>(m) ||
         std::holds_alternative<proto::Heartbeat>(m) || std::holds_alternative<proto::StateRequest>(m) ||
         std::holds_alternative<proto::ConfigRead>(m) || std::holds_alternative<proto::ConfigWrite>(m);
}
bool sent_by_device(const proto::Message& m) noexcept {
  return std::holds_alternative<proto::Identity>(m) || std::holds_alternative<proto::Telemetry>(m) ||
         std::holds_alternative<proto::TimeSync>(m) || std::holds_alternative<proto::Status>(m) ||
         std::holds_alternative<proto::Heartbeat>(m) || std::holds_alternative<proto::ConfigData>(m) ||
         std::holds_alternative<proto::ConfigAck>(m);
}
bool sent_by(CanRole role, const proto::Message& m) noexcept {
  return role == CanRole::host ? sent_by_host(m) : sent_by_device(m);
}

constexpr auto fn_of(std::uint32_t id) noexcept { return static_cast<std::uint8_t>((id >> 8U) & 0x7U); }
constexpr auto block_of(std::uint32_t id) noexcept { return static_cast<std::uint8_t>((id >> 4U) & 0xFU); }
constexpr std::uint8_t u8(proto::CanFunction f) noexcept { return static_cast<std::uint8_t>(f); }
constexpr std::uint8_t u8(proto::CanManagement m) noexcept { return static_cast<std::uint8_t>(m); }

// Whether a frame identifier is one the other side of role sends.
bool from_peer(CanRole role, std::uint32_t id) noexcept {
  const std::uint8_t fn = fn_of(id);
  const std::uint8_t block = block_of(id);
  using F = proto::CanFunction;
  using M = proto::CanManagement;
  if (role == CanRole::host) {
    return (fn == u8(F::management) && (block == u8(M::status) || block == u8(M::time_sync) ||
                                        block == u8(M::segmented_device_to_host))) ||
           fn == u8(F::sensor_block) || fn == u8(F::fd_device_to_host);
  }
  return (fn == u8(F::management) && (block == u8(M::heartbeat) || block == u8(M::state_request) ||
                                      block == u8(M::segmented_host_to_device))) ||
         fn == u8(F::valve_block) || fn == u8(F::cell_target) || fn == u8(F::fd_host_to_device);
}

bool is_segmented_id(std::uint32_t id) noexcept {
  return fn_of(id) == u8(proto::CanFunction::management) &&
         (block_of(id) == u8(proto::CanManagement::segmented_host_to_device) ||
          block_of(id) == u8(proto::CanManagement::segmented_device_to_host));
}

}  // namespace

CanPacketCodec::CanPacketCodec(CanRole role, std::uint8_t node, bool fd) noexcept
    : role_(role), node_(node), fd_(fd), decoder_(node) {}

proto::Error CanPacketCodec::check(CanRole role, bool fd, std::span<const std::uint8_t> packet) noexcept {
  const proto::PacketDecoded p = proto::decode_packet(packet);
  if (p.error != proto::Error::ok) {
    return p.error;
  }
  if (!sent_by(role, p.message)) {
    return proto::Error::unknown_type;
  }
  if (fd) {
    return proto::Error::ok;
  }
  if (const auto* v = std::get_if<proto::ValveCurrents>(&p.message)) {
    return v->first + v->count > kBlockValues ? proto::Error::out_of_range : proto::Error::ok;
  }
  if (const auto* t = std::get_if<proto::Telemetry>(&p.message)) {
    return t->first + t->count > kBlockValues ? proto::Error::out_of_range : proto::Error::ok;
  }
  if (const auto* c = std::get_if<proto::CellTargets>(&p.message)) {
    return c->first + c->count - 1 > proto::kCellIndexMaxCan ? proto::Error::out_of_range : proto::Error::ok;
  }
  return proto::Error::ok;
}

CanPacketCodec::Encoded CanPacketCodec::encode(std::span<const std::uint8_t> packet,
                                               std::span<proto::CanFrame, kMaxFrames> out) noexcept {
  const proto::PacketDecoded p = proto::decode_packet(packet);
  if (p.error != proto::Error::ok) {
    return {p.error, 0};
  }
  const proto::Message& m = p.message;
  if (!sent_by(role_, m)) {
    return {proto::Error::unknown_type, 0};
  }
  if (fd_) {
    const auto dir =
        role_ == CanRole::host ? proto::Direction::host_to_device : proto::Direction::device_to_host;
    const proto::CanEncodeResult r = proto::encode_canfd(m, node_, dir, p.sequence, out[0]);
    return {r.error, r.frames};
  }
  if (std::holds_alternative<proto::ValveCurrents>(m) || std::holds_alternative<proto::Telemetry>(m)) {
    return encode_blocks(m, out);
  }
  std::uint8_t counter = 0;
  if (std::holds_alternative<proto::Heartbeat>(m)) {
    if (role_ == CanRole::device) {
      return {proto::Error::ok, 0};  // classic CAN has no heartbeat echo
    }
    counter = tx_heartbeat_++;
  } else if (std::holds_alternative<proto::CellTargets>(m)) {
    counter = tx_cells_++;
  } else if (std::holds_alternative<proto::StateRequest>(m) || std::holds_alternative<proto::Status>(m)) {
    counter = tx_state_++;
  } else if (std::holds_alternative<proto::TimeSync>(m)) {
    counter = tx_blocks_++;
  }
  const proto::CanEncodeResult r =
      proto::encode_can(m, node_, static_cast<std::uint8_t>(counter & 0xFU), p.sequence, out);
  return {r.error, r.frames};
}

CanPacketCodec::Encoded CanPacketCodec::encode_blocks(const proto::Message& m,
                                                      std::span<proto::CanFrame, kMaxFrames> out) noexcept {
  const auto* v = std::get_if<proto::ValveCurrents>(&m);
  const auto* t = std::get_if<proto::Telemetry>(&m);
  const std::size_t first = v != nullptr ? v->first : t->first;
  const std::size_t count = v != nullptr ? v->count : t->count;
  if (first + count > kBlockValues) {
    return {proto::Error::out_of_range, 0};
  }
  for (std::size_t i = 0; i < count; ++i) {
    shadow_[first + i] = v != nullptr ? v->counts[i] : static_cast<std::uint16_t>(t->counts[i]);
  }
  const auto counter = static_cast<std::uint8_t>(tx_blocks_ & 0xFU);
  ++tx_blocks_;
  std::size_t n = 0;
  if (t != nullptr) {
    const proto::CanEncodeResult r =
        proto::encode_can(proto::TimeSync{t->device_time_us}, node_, counter, 0, out.subspan(0, 1));
    if (r.error != proto::Error::ok) {
      return {r.error, 0};
    }
    n = 1;
  }
  const std::size_t end = first + count;
  for (std::size_t b = first / proto::kCanValuesPerBlock; b * proto::kCanValuesPerBlock < end; ++b) {
    const std::size_t start = b * proto::kCanValuesPerBlock;
    const auto values = static_cast<std::uint8_t>(std::min(proto::kCanValuesPerBlock, end - start));
    const proto::Message block = v != nullptr ? proto::Message(valve_block(start, values))
                                              : proto::Message(sensor_block(start, values));
    const proto::CanEncodeResult r = proto::encode_can(block, node_, counter, 0, out.subspan(n, 1));
    if (r.error != proto::Error::ok) {
      return {r.error, 0};
    }
    ++n;
  }
  return {proto::Error::ok, n};
}

proto::ValveCurrents CanPacketCodec::valve_block(std::size_t start, std::uint8_t values) const noexcept {
  proto::ValveCurrents c;
  c.first = static_cast<std::uint16_t>(start);
  c.count = values;
  std::copy_n(shadow_.begin() + static_cast<std::ptrdiff_t>(start), values, c.counts.begin());
  return c;
}

proto::Telemetry CanPacketCodec::sensor_block(std::size_t start, std::uint8_t values) const noexcept {
  proto::Telemetry s;
  s.first = static_cast<std::uint16_t>(start);
  s.count = values;
  for (std::size_t i = 0; i < values; ++i) {
    s.counts[i] = static_cast<std::int16_t>(shadow_[start + i]);
  }
  return s;
}

void CanPacketCodec::finish(Decoded& d, const proto::Message& message, std::uint8_t sequence) noexcept {
  const proto::EncodeResult r = proto::encode_packet(message, sequence, d.packet.bytes);
  d.error = r.error;
  d.complete = r.error == proto::Error::ok;
  d.packet.length = static_cast<std::uint8_t>(r.bytes);
}

CanPacketCodec::Decoded CanPacketCodec::decode(const proto::CanFrame& frame) noexcept {
  Decoded out;
  if (frame.id > 0x7FFU) {
    out.error = proto::Error::unknown_type;
    return out;
  }
  if ((frame.id & 0xFU) != node_) {
    out.error = proto::Error::wrong_node;
    return out;
  }
  if (!from_peer(role_, frame.id)) {
    out.error = proto::Error::unknown_type;  // our own direction: another host, or an echo
    return out;
  }
  const proto::CanDecoded d = decoder_.decode(frame);
  if (d.error != proto::Error::ok) {
    out.error = d.error;
    // A frame of our node that did not arrive whole: the session should see a gap.
    if (d.error != proto::Error::unknown_type) {
      ++lost_;
    }
    return out;
  }
  if (!d.complete) {
    return out;  // a segmented transfer goes on
  }
  const proto::Message& m = d.message;
  if (!sent_by(role_ == CanRole::host ? CanRole::device : CanRole::host, m)) {
    out.error = proto::Error::unknown_type;
    return out;
  }
  if (frame.fd) {
    // The peer's own packet and sequence, end to end.
    finish(out, m, d.sequence);
    rx_sequence_ = static_cast<std::uint8_t>(d.sequence + 1U);
    lost_ = 0;
    return out;
  }
  proto::Message handed = m;
  if (role_ == CanRole::host && !is_segmented_id(frame.id)) {
    if (const auto* ts = std::get_if<proto::TimeSync>(&m)) {
      if (sample_counter_.accept(d.counter) == proto::Error::counter_gap) {
        lost_ = std::max(lost_, sample_counter_.missed());  // a refused frame may be the one missed
      }
      have_time_ = true;
      time_counter_ = d.counter;
      time_us_ = ts->device_time_us;
      return out;  // stamps the sensor blocks that follow
    }
    if (auto* t = std::get_if<proto::Telemetry>(&handed)) {
      if (!have_time_ || d.counter != time_counter_) {
        ++lost_;  // its TimeSync was lost: the sample's time is unknown
        out.error = proto::Error::counter_gap;
        return out;
      }
      t->device_time_us = time_us_;
    } else if (std::holds_alternative<proto::Status>(m)) {
      if (status_counter_.accept(d.counter) == proto::Error::counter_gap) {
        lost_ = std::max(lost_, status_counter_.missed());
      }
    }
  }
  // Never a skip of 255 (mod 256 the session would read it as a duplicate).
  constexpr std::uint32_t kMaxSkip = 128;
  const auto sequence = static_cast<std::uint8_t>(rx_sequence_ + std::min(lost_, kMaxSkip));
  finish(out, handed, sequence);
  rx_sequence_ = static_cast<std::uint8_t>(sequence + 1U);
  lost_ = 0;
  return out;
}

void CanPacketCodec::reset() noexcept {
  decoder_ = proto::CanDecoder(node_);
  sample_counter_.reset();
  status_counter_.reset();
  have_time_ = false;
  lost_ = 0;
}

CanIdFilters can_receive_filters(CanRole role, std::uint8_t node) noexcept {
  // Standard data frames only: the EFF and RTR flags are part of every mask.
  constexpr std::uint32_t kExact = CAN_SFF_MASK | CAN_EFF_FLAG | CAN_RTR_FLAG;
  constexpr std::uint32_t kAnyBlock = (CAN_SFF_MASK & ~0xF0U) | CAN_EFF_FLAG | CAN_RTR_FLAG;
  using F = proto::CanFunction;
  using M = proto::CanManagement;
  CanIdFilters f;
  const auto add = [&f, node](F fn, std::uint8_t block, std::uint32_t mask) {
    f.filters[f.count++] = CanIdFilter{proto::can_id(fn, block, node), mask};
  };
  if (role == CanRole::host) {
    add(F::management, u8(M::status), kExact);
    add(F::management, u8(M::time_sync), kExact);
    add(F::management, u8(M::segmented_device_to_host), kExact);
    add(F::sensor_block, 0, kAnyBlock);
    add(F::fd_device_to_host, 0, kExact);
  } else {
    add(F::management, u8(M::heartbeat), kExact);
    add(F::management, u8(M::state_request), kExact);
    add(F::management, u8(M::segmented_host_to_device), kExact);
    add(F::valve_block, 0, kAnyBlock);
    add(F::cell_target, 0, kAnyBlock);
    add(F::fd_host_to_device, 0, kExact);
  }
  return f;
}

// ============================================================================ sockets

namespace {

// Error frames worth knowing about; lost arbitration is normal bus traffic.
constexpr can_err_mask_t kErrorMask = CAN_ERR_TX_TIMEOUT | CAN_ERR_CRTL | CAN_ERR_PROT | CAN_ERR_TRX |
                                      CAN_ERR_ACK | CAN_ERR_BUSOFF | CAN_ERR_BUSERROR | CAN_ERR_RESTARTED;

bool no_can_in_kernel(int error) noexcept { return error == EAFNOSUPPORT || error == EPROTONOSUPPORT; }
bool link_lost(long result) noexcept { return result == -ENETDOWN || result == -ENXIO || result == -ENODEV; }

std::string error_text(int error) { return std::strerror(error); }

template <class T>
std::span<const std::byte> bytes_of(const T& value) noexcept {
  return std::as_bytes(std::span<const T, 1>(&value, 1));
}

// Where opening a bound socket stopped.
enum class OpenStage : std::uint8_t { ok, socket, index, down, mtu, fd_frames, option, bind };
struct OpenResult {
  int fd = -1;
  OpenStage stage = OpenStage::ok;
  int error = 0;  // errno of the failed call
  int mtu = 0;    // stage mtu: the interface's
};

OpenResult open_bound_socket(CanSocketApi& api, std::string_view iface, bool fd_frames,
                             std::span<const CanIdFilter> filters) noexcept {
  OpenResult r;
  const int s = api.open_socket();
  if (s < 0) {
    return {-1, OpenStage::socket, -s, 0};
  }
  const auto fail = [&api, s](OpenStage stage, int error, int mtu = 0) {
    api.close_socket(s);
    return OpenResult{-1, stage, error, mtu};
  };
  const int index = api.interface_index(s, iface);
  if (index < 0) {
    return fail(OpenStage::index, -index);
  }
  const int flags = api.interface_flags(s, iface);
  if (flags < 0) {
    return fail(OpenStage::index, -flags);
  }
  if ((static_cast<unsigned>(flags) & IFF_UP) == 0) {
    return fail(OpenStage::down, ENETDOWN);
  }
  if (fd_frames) {
    const int mtu = api.interface_mtu(s, iface);
    if (mtu < 0) {
      return fail(OpenStage::index, -mtu);
    }
    if (mtu != static_cast<int>(CANFD_MTU)) {
      return fail(OpenStage::mtu, 0, mtu);
    }
    const int on = 1;
    if (const int e = api.set_option(s, SOL_CAN_RAW, CAN_RAW_FD_FRAMES, bytes_of(on)); e < 0) {
      return fail(OpenStage::fd_frames, -e);
    }
  }
  std::array<can_filter, 8> raw{};
  const std::size_t n = std::min(filters.size(), raw.size());
  for (std::size_t i = 0; i < n; ++i) {
    raw[i].can_id = filters[i].id;
    raw[i].can_mask = filters[i].mask;
  }
  if (const int e = api.set_option(s, SOL_CAN_RAW, CAN_RAW_FILTER,
                                   std::as_bytes(std::span<const can_filter>(raw.data(), n)));
      e < 0) {
    return fail(OpenStage::option, -e);
  }
  const can_err_mask_t errors = kErrorMask;
  if (const int e = api.set_option(s, SOL_CAN_RAW, CAN_RAW_ERR_FILTER, bytes_of(errors)); e < 0) {
    return fail(OpenStage::option, -e);
  }
  // The kernel raises this to its minimum, a few frames: a full bus then blocks the writer
  // (EAGAIN, POLLOUT) long before the interface's queue overflows with ENOBUFS.
  const int send_buffer_bytes = 0;
  if (const int e = api.set_option(s, SOL_SOCKET, SO_SNDBUF, bytes_of(send_buffer_bytes)); e < 0) {
    return fail(OpenStage::option, -e);
  }
  if (const int e = api.bind_interface(s, index); e < 0) {
    return fail(e == -ENETDOWN ? OpenStage::down : OpenStage::bind, -e);
  }
  r.fd = s;
  return r;
}

std::string bring_up_command(std::string_view iface, bool fd) {
  if (iface.starts_with("vcan")) {
    return fmt::format("sudo ip link set {} up", iface);
  }
  return fmt::format("sudo ip link set {} up type can bitrate 1000000{}", iface,
                     fd ? " dbitrate 5000000 fd on" : "");
}

std::string no_can_text(int error) {
  return fmt::format("this kernel has no CAN support (socket(PF_CAN, SOCK_RAW, CAN_RAW): {})",
                     error_text(error));
}
constexpr std::string_view kNoCanFix =
    "load it with `sudo modprobe can_raw` (and `sudo modprobe vcan` for a virtual bus); a kernel built "
    "without CAN, like the development machines', cannot do it at all: run the CAN tests in the VM";

[[noreturn]] void throw_open_error(std::string_view uri, std::string_view iface, bool fd, const OpenResult& r,
                                   CanSocketApi& api) {
  const std::string why = error_text(r.error);
  switch (r.stage) {
    case OpenStage::socket:
      if (no_can_in_kernel(r.error)) {
        throw DeviceNotFound(fmt::format("{}: {}: {}", uri, no_can_text(r.error), kNoCanFix));
      }
      if (r.error == EACCES || r.error == EPERM) {
        throw PermissionDenied(fmt::format(
            "{}: the system refused a raw CAN socket ({}); SocketCAN needs no special rights, so a sandbox, "
            "container or security policy blocks it: allow AF_CAN sockets there",
            uri, why));
      }
      throw Error(fmt::format(
          "{}: cannot open a CAN socket: {}{}", uri, why,
          r.error == EMFILE || r.error == ENFILE ? " (raise the open-file limit, ulimit -n)" : ""));
    case OpenStage::index: {
      std::vector<std::string> names;
      try {
        names = api.can_interfaces();
      } catch (...) {
        names.clear();
      }
      std::string list;
      for (const std::string& n : names) {
        list += (list.empty() ? "" : ", ") + n;
      }
      throw DeviceNotFound(
          fmt::format("{}: no network interface '{}' ({}); CAN interfaces here: {}. Create a virtual bus "
                      "with `sudo modprobe "
                      "vcan && sudo ip link add dev vcan0 type vcan && sudo ip link set vcan0 up`, or plug "
                      "in an adapter and "
                      "bring it up with `sudo ip link set can0 up type can bitrate 1000000`",
                      uri, iface, why, list.empty() ? "none" : list));
    }
    case OpenStage::down:
      throw DeviceNotFound(fmt::format("{}: CAN interface {} is down: bring it up with `{}`", uri, iface,
                                       bring_up_command(iface, fd)));
    case OpenStage::mtu:
      throw InvalidArgument(
          fmt::format("{}: fd=1 needs CAN FD, but {} has MTU {} (CAN FD needs 72): `sudo ip link set {} mtu "
                      "72` for a vcan, or "
                      "`sudo ip link set {} down && sudo ip link set {} up type can bitrate 1000000 dbitrate "
                      "5000000 fd on` for "
                      "an adapter; or leave out fd=1 for classic CAN",
                      uri, iface, r.mtu, iface, iface, iface));
    case OpenStage::fd_frames:
      throw Error(
          fmt::format("{}: this kernel refuses CAN FD frames on raw sockets (CAN_RAW_FD_FRAMES: {}): use a "
                      "newer kernel, or leave out fd=1",
                      uri, why));
    case OpenStage::bind:
      if (r.error == ENODEV) {
        throw DeviceNotFound(
            fmt::format("{}: '{}' is not a CAN interface (`ip link show type can` lists them)", uri, iface));
      }
      throw Error(fmt::format("{}: cannot bind to {}: {}", uri, iface, why));
    case OpenStage::option:
    case OpenStage::ok:
      break;
  }
  throw Error(fmt::format("{}: cannot set up the CAN socket on {}: {}", uri, iface, why));
}

// struct canfd_frame <-> protocol frame. Error, remote and extended frames are not ours.
proto::CanFrame from_wire(const canfd_frame& raw, bool fd) noexcept {
  proto::CanFrame f;
  f.id = raw.can_id & CAN_SFF_MASK;
  f.fd = fd;
  f.length = std::min<std::uint8_t>(raw.len, fd ? CANFD_MAX_DLEN : CAN_MAX_DLEN);
  std::copy_n(std::begin(raw.data), f.length, f.data.begin());
  return f;
}
canfd_frame to_wire(const proto::CanFrame& f) noexcept {
  canfd_frame raw{};
  raw.can_id = f.id & CAN_SFF_MASK;
  raw.len = std::min<std::uint8_t>(f.length, f.fd ? CANFD_MAX_DLEN : CAN_MAX_DLEN);
  std::copy_n(f.data.begin(), raw.len, std::begin(raw.data));
  return raw;
}

Duration scaled(Duration d, double scale) noexcept {
  return Duration{static_cast<Duration::rep>(static_cast<double>(d.count()) * scale)};
}

// ============================================================================ transport

class CanTransport final : public QueuedTransport {
 public:
  CanTransport(const CanUri& parsed, const CanTransportOptions& options, std::shared_ptr<CanSocketApi> api)
      : QueuedTransport(format_can_uri(parsed), options.send_queue, options.receive_queue),
        uri_(parsed),
        role_(options.role),
        api_(std::move(api)),
        codec_(options.role, parsed.node, parsed.fd),
        filters_(can_receive_filters(options.role, parsed.node)),
        reopen_min_(scaled(options.reopen_backoff_min, options.time_scale)),
        reopen_max_(scaled(options.reopen_backoff_max, options.time_scale)),
        enobufs_min_(scaled(options.enobufs_backoff_min, options.time_scale)),
        enobufs_max_(scaled(options.enobufs_backoff_max, options.time_scale)) {
    const OpenResult r = open();
    if (r.fd < 0) {
      throw_open_error(uri(), uri_.interface, uri_.fd, r, *api_);
    }
    socket_ = r.fd;
    set_state(TransportState::open);
    thread_ = std::thread([this] { run(); });
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
    const auto r = [](const std::atomic<std::uint64_t>& c) { return c.load(std::memory_order_relaxed); };
    CanTransportStats s;
    s.frames_written = r(stats_.frames_written);
    s.frames_read = r(stats_.frames_read);
    s.enobufs = r(stats_.enobufs);
    s.send_buffer_full = r(stats_.send_buffer_full);
    s.foreign_frames = r(stats_.foreign_frames);
    s.dropped_packets = r(stats_.dropped_packets);
    return s;
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
        bump(counters_.io_errors);
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
        bump(counters_.io_errors);
        return true;
      }
      handle_frame(static_cast<std::size_t>(n));
      bump(stats_.frames_read);  // after the frame is handled: tests wait on it
    }
    return true;
  }

  void handle_frame(std::size_t size) noexcept {
    if (size != CAN_MTU && size != CANFD_MTU) {
      bump(counters_.malformed);
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
      bump(counters_.malformed);
      bump(stats_.foreign_frames);
      return;
    }
    const CanPacketCodec::Decoded d = codec_.decode(from_wire(raw, size == CANFD_MTU));
    if (d.error == proto::Error::wrong_node || d.error == proto::Error::unknown_type) {
      bump(counters_.malformed);
      bump(stats_.foreign_frames);
      return;
    }
    if (d.error != proto::Error::ok) {
      bump(counters_.malformed);
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
    bump(counters_.error_frames);
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
          bump(stats_.dropped_packets);
          continue;
        }
        next_frame_ = 0;
        frame_count_ = e.frames;
        if (e.frames == 0) {
          bump(stats_.dropped_packets);  // nothing on this framing (a classic heartbeat echo)
          continue;
        }
      }
      const proto::CanFrame& f = frames_[next_frame_];
      const canfd_frame raw = to_wire(f);
      const std::size_t size = f.fd ? CANFD_MTU : CAN_MTU;
      std::memcpy(tx_raw_.data(), &raw, size);
      const long n = api_->write_frame(socket_, std::span<const std::byte>(tx_raw_.data(), size));
      if (n >= 0) {
        bump(stats_.frames_written);
        wait_ = Wait::nothing;
        enobufs_backoff_ = Duration{0};
        if (++next_frame_ == frame_count_) {
          bump(counters_.sent);
        }
        continue;
      }
      if (n == -EAGAIN || n == -EWOULDBLOCK) {
        bump(stats_.send_buffer_full);
        wait_ = Wait::writable;
        return;
      }
      if (n == -ENOBUFS) {
        // The interface's queue is full: keep the frame and try again shortly.
        bump(stats_.enobufs);
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
      bump(counters_.io_errors);  // this frame cannot go out (EINVAL, EMSGSIZE): drop its packet
      bump(stats_.dropped_packets);
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
    std::atomic<std::uint64_t> frames_written{0};
    std::atomic<std::uint64_t> frames_read{0};
    std::atomic<std::uint64_t> enobufs{0};
    std::atomic<std::uint64_t> send_buffer_full{0};
    std::atomic<std::uint64_t> foreign_frames{0};
    std::atomic<std::uint64_t> dropped_packets{0};
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

// ============================================================================ the kernel

class SystemCanApi final : public CanSocketApi {
 public:
  int open_socket() noexcept override {
    const int fd = ::socket(PF_CAN, SOCK_RAW | SOCK_NONBLOCK | SOCK_CLOEXEC, CAN_RAW);
    return fd < 0 ? -errno : fd;
  }
  void close_socket(int fd) noexcept override { ::close(fd); }
  int interface_index(int fd, std::string_view name) noexcept override {
    ifreq req = request(name);
    if (!fits(name) || ::ioctl(fd, SIOCGIFINDEX, &req) < 0) {  // NOLINT(cppcoreguidelines-pro-type-vararg)
      return fits(name) ? -errno : -ENODEV;
    }
    return req.ifr_ifindex;  // NOLINT(cppcoreguidelines-pro-type-union-access)
  }
  int interface_mtu(int fd, std::string_view name) noexcept override {
    ifreq req = request(name);
    if (!fits(name) || ::ioctl(fd, SIOCGIFMTU, &req) < 0) {  // NOLINT(cppcoreguidelines-pro-type-vararg)
      return fits(name) ? -errno : -ENODEV;
    }
    return req.ifr_mtu;  // NOLINT(cppcoreguidelines-pro-type-union-access)
  }
  int interface_flags(int fd, std::string_view name) noexcept override {
    ifreq req = request(name);
    if (!fits(name) || ::ioctl(fd, SIOCGIFFLAGS, &req) < 0) {  // NOLINT(cppcoreguidelines-pro-type-vararg)
      return fits(name) ? -errno : -ENODEV;
    }
    return static_cast<int>(
        static_cast<unsigned short>(req.ifr_flags));  // NOLINT(cppcoreguidelines-pro-type-union-access)
  }
  int set_option(int fd, int level, int option, std::span<const std::byte> value) noexcept override {
    return ::setsockopt(fd, level, option, value.data(), static_cast<socklen_t>(value.size())) < 0 ? -errno
                                                                                                   : 0;
  }
  int bind_interface(int fd, int ifindex) noexcept override {
    sockaddr_can addr{};
    addr.can_family = AF_CAN;
    addr.can_ifindex = ifindex;
    // NOLINTNEXTLINE(cppcoreguidelines-pro-type-reinterpret-cast): the sockets API's own cast
    return ::bind(fd, reinterpret_cast<const sockaddr*>(&addr), sizeof addr) < 0 ? -errno : 0;
  }
  long read_frame(int fd, std::span<std::byte> frame) noexcept override {
    const ssize_t n = ::read(fd, frame.data(), frame.size());
    return n < 0 ? -errno : n;
  }
  long write_frame(int fd, std::span<const std::byte> frame) noexcept override {
    const ssize_t n = ::write(fd, frame.data(), frame.size());
    return n < 0 ? -errno : n;
  }
  int poll(std::span<pollfd> fds, Duration timeout) noexcept override {
    timespec ts{};
    ts.tv_sec = static_cast<time_t>(timeout.count() / 1'000'000'000);
    ts.tv_nsec = static_cast<long>(timeout.count() % 1'000'000'000);
    const int n = ::ppoll(fds.data(), fds.size(), timeout.count() < 0 ? nullptr : &ts, nullptr);
    return n < 0 ? -errno : n;
  }
  std::vector<std::string> can_interfaces() override {
    std::vector<std::string> names;
    std::error_code ec;
    for (const auto& entry : std::filesystem::directory_iterator("/sys/class/net", ec)) {
      std::ifstream type(entry.path() / "type");
      int t = 0;
      if (type >> t && t == ARPHRD_CAN_TYPE) {
        names.push_back(entry.path().filename().string());
      }
    }
    std::sort(names.begin(), names.end());
    return names;
  }

 private:
  static constexpr int ARPHRD_CAN_TYPE = 280;  // <linux/if_arp.h> ARPHRD_CAN
  static bool fits(std::string_view name) noexcept { return !name.empty() && name.size() < IFNAMSIZ; }
  static ifreq request(std::string_view name) noexcept {
    ifreq req{};
    if (fits(name)) {
      std::copy_n(name.data(), name.size(),
                  std::begin(req.ifr_name));  // NOLINT(cppcoreguidelines-pro-type-union-access)
    }
    return req;
  }
};

}  // namespace

std::shared_ptr<CanSocketApi> make_system_can_api() { return std::make_shared<SystemCanApi>(); }

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

// ============================================================================ enumeration

namespace {

// The nodes 1..15 of one interface, asked for their Identity: the codecs that frame the requests
// and read the answers, and what each node answered (0 nothing, 1 classic, 2 FD).
struct NodeProbe {
  explicit NodeProbe(bool interface_fd) : fd(interface_fd) {
    for (std::uint8_t n = 1; n <= kNodes; ++n) {
      classic.emplace_back(CanRole::host, n, false);
      fds.emplace_back(CanRole::host, n, true);
    }
  }
  static constexpr std::size_t kNodes = proto::kCanNodeMax;
  bool fd;
  std::vector<CanPacketCodec> classic;
  std::vector<CanPacketCodec> fds;
  std::vector<canfd_frame> to_send;
  std::vector<bool> fd_frame;
  std::vector<int> answered = std::vector<int>(kNodes, 0);
  std::vector<proto::Identity> identity = std::vector<proto::Identity>(kNodes);

  // An IdentifyRequest to every node, classic and (when the interface carries them) FD.
  void frame_requests() {
    std::array<std::uint8_t, proto::kPacketMaxBytes> packet{};
    const proto::EncodeResult request = proto::encode_packet(proto::IdentifyRequest{}, 0, packet);
    std::array<proto::CanFrame, CanPacketCodec::kMaxFrames> frames{};
    for (std::size_t i = 0; i < kNodes; ++i) {
      for (CanPacketCodec* codec : {&classic[i], &fds[i]}) {
        if (codec->fd() && !fd) {
          continue;
        }
        const auto e = codec->encode(std::span<const std::uint8_t>(packet.data(), request.bytes), frames);
        for (std::size_t k = 0; k < e.frames; ++k) {
          to_send.push_back(to_wire(frames[k]));
          fd_frame.push_back(frames[k].fd);
        }
      }
    }
  }

  // One frame read from the bus: an Identity completes its node's answer (classic wins).
  void take(const std::array<std::byte, CANFD_MTU>& buffer, long n) {
    canfd_frame raw{};
    std::memcpy(&raw, buffer.data(), static_cast<std::size_t>(n));
    if ((raw.can_id & (CAN_ERR_FLAG | CAN_EFF_FLAG | CAN_RTR_FLAG)) != 0) {
      return;
    }
    const bool is_fd = n == static_cast<long>(CANFD_MTU);
    const proto::CanFrame f = from_wire(raw, is_fd);
    const std::size_t node = f.id & 0xFU;
    if (node < 1 || node > kNodes) {
      return;
    }
    CanPacketCodec& codec = is_fd ? fds[node - 1] : classic[node - 1];
    const CanPacketCodec::Decoded d = codec.decode(f);
    if (!d.complete) {
      return;
    }
    const proto::PacketDecoded p =
        proto::decode_packet(std::span<const std::uint8_t>(d.packet.bytes.data(), d.packet.length));
    if (const auto* id = std::get_if<proto::Identity>(&p.message); id != nullptr && answered[node - 1] != 1) {
      answered[node - 1] = is_fd ? 2 : 1;
      identity[node - 1] = *id;
    }
  }

  // Writes the requests as the queue takes them and reads answers until timeout.
  void exchange(CanSocketApi& api, int socket, Duration timeout) {
    const auto start = std::chrono::steady_clock::now();
    std::size_t next = 0;
    std::array<std::byte, CANFD_MTU> buffer{};
    for (;;) {
      const Duration left = timeout - (std::chrono::steady_clock::now() - start);
      if (left <= Duration{0}) {
        break;
      }
      while (next < to_send.size()) {
        const std::size_t size = fd_frame[next] ? CANFD_MTU : CAN_MTU;
        std::memcpy(buffer.data(), &to_send[next], size);
        const long n = api.write_frame(socket, std::span<const std::byte>(buffer.data(), size));
        if (n < 0 && (n == -EAGAIN || n == -ENOBUFS || n == -EINTR)) {
          break;  // a full queue: try again after the next wait
        }
        ++next;  // written, or refused for good
      }
      std::array<pollfd, 1> p{{{socket, POLLIN, 0}}};
      const Duration wait =
          next < to_send.size() ? std::min(left, Duration{std::chrono::milliseconds(1)}) : left;
      (void)api.poll(p, wait);
      for (;;) {
        const long n = api.read_frame(socket, buffer);
        if (n != static_cast<long>(CAN_MTU) && n != static_cast<long>(CANFD_MTU)) {
          break;
        }
        take(buffer, n);
      }
    }
  }
};

// Probes one interface that is up: an IdentifyRequest to every node, classic and (when the
// interface carries them) FD, then the Identities that come back before the deadline.
void probe_interface(CanSocketApi& api, const std::string& iface, Duration timeout,
                     std::vector<DeviceListing>& out) {
  const int mtu = [&api, &iface] {
    const int s = api.open_socket();
    if (s < 0) {
      return 0;
    }
    const int m = api.interface_mtu(s, iface);
    api.close_socket(s);
    return m;
  }();
  const bool fd = mtu == static_cast<int>(CANFD_MTU);
  constexpr std::uint32_t kAnyNode = (CAN_SFF_MASK & ~0xFU) | CAN_EFF_FLAG | CAN_RTR_FLAG;
  const std::array<CanIdFilter, 2> filters{{
      {proto::can_id(proto::CanFunction::management,
                     static_cast<std::uint8_t>(proto::CanManagement::segmented_device_to_host), 0),
       kAnyNode},
      {proto::can_id(proto::CanFunction::fd_device_to_host, 0, 0), kAnyNode},
  }};
  const OpenResult r = open_bound_socket(api, iface, fd, filters);
  DeviceListing base;
  base.bus = "can";
  base.path = iface;
  if (r.fd < 0) {
    DeviceListing l = base;
    l.problem = r.stage == OpenStage::down ? "interface is down"
                                           : fmt::format("cannot open: {}", error_text(r.error));
    l.fix = r.stage == OpenStage::down ? bring_up_command(iface, false)
                                       : "check `ip -details link show " + iface + "`";
    out.push_back(std::move(l));
    return;
  }
  NodeProbe probe(fd);
  probe.frame_requests();
  probe.exchange(api, r.fd, timeout);
  api.close_socket(r.fd);
  for (std::size_t i = 0; i < NodeProbe::kNodes; ++i) {
    if (probe.answered[i] == 0) {
      continue;
    }
    const proto::Identity& id = probe.identity[i];
    DeviceListing l = base;
    l.uri = format_can_uri(CanUri{iface, static_cast<std::uint8_t>(i + 1), probe.answered[i] == 2});
    l.serial = fmt::format("{:08X}", id.serial);
    l.firmware = fmt::format("{}.{}.{}", id.fw_major, id.fw_minor, id.fw_patch);
    l.protocol = fmt::format("{}.{}", id.proto_major, id.proto_minor);
    out.push_back(std::move(l));
  }
}

}  // namespace

std::vector<DeviceListing> list_can_devices(CanSocketApi& api, Duration timeout) {
  std::vector<DeviceListing> out;
  try {
    const int s = api.open_socket();
    if (s < 0) {
      DeviceListing l;
      l.bus = "can";
      l.problem = no_can_in_kernel(-s) ? no_can_text(-s)
                                       : fmt::format("cannot open a CAN socket: {}", error_text(-s));
      l.fix = no_can_in_kernel(-s) ? std::string(kNoCanFix) : "check the system's socket policy";
      out.push_back(std::move(l));
      return out;
    }
    api.close_socket(s);
    for (const std::string& iface : api.can_interfaces()) {
      probe_interface(api, iface, timeout, out);
    }
  } catch (...) {
    // Out of memory while listing: what was found so far.
    (void)0;
  }
  return out;
}

std::vector<DeviceListing> list_can_devices(Duration timeout) {
  try {
    const std::shared_ptr<CanSocketApi> api = make_system_can_api();
    return list_can_devices(*api, timeout);
  } catch (...) {
    return {};
  }
}

}  // namespace mrskin
