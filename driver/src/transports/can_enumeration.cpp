// CAN enumeration: every CAN interface that is up, each node 1..15 on it asked for its Identity.
#include <fmt/format.h>
#include <linux/can.h>

#include <array>
#include <chrono>
#include <cstring>
#include <string>
#include <vector>

#include "can_socket.hpp"

namespace mrskin {
namespace proto = mrskin::protocol;
using socketcan::bring_up_command;
using socketcan::error_text;
using socketcan::from_wire;
using socketcan::kNoCanFix;
using socketcan::no_can_in_kernel;
using socketcan::no_can_text;
using socketcan::open_bound_socket;
using socketcan::OpenResult;
using socketcan::OpenStage;
using socketcan::to_wire;

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
