// SocketCAN for the CAN transport and the CAN enumeration: a raw socket bound to an interface, what
// stopped it opening (and the error a caller sees), and the kernel's frames. Internal header.
#pragma once

#include <linux/can.h>

#include <algorithm>
#include <cerrno>
#include <cstdint>
#include <iterator>
#include <span>
#include <string>
#include <string_view>

#include "can_socket_api.hpp"
#include "mrskin/driver/transports/can.hpp"
#include "mrskin/protocol/can.hpp"

namespace mrskin::socketcan {

// socket(PF_CAN) errors of a kernel built or loaded without CAN.
inline bool no_can_in_kernel(int error) noexcept { return error == EAFNOSUPPORT || error == EPROTONOSUPPORT; }
// Errors (-errno) of a socket call once its interface went down or away.
inline bool link_lost(long result) noexcept {
  return result == -ENETDOWN || result == -ENXIO || result == -ENODEV;
}

std::string error_text(int error);

// Where opening a bound socket stopped.
enum class OpenStage : std::uint8_t { ok, socket, index, down, mtu, fd_frames, option, bind };
struct OpenResult {
  int fd = -1;
  OpenStage stage = OpenStage::ok;
  int error = 0;  // errno of the failed call
  int mtu = 0;    // stage mtu: the interface's
};

// A raw socket on iface (which must be up) with filters (the first 8), the error frames worth
// knowing about and the smallest send buffer, bound; CAN FD frames too when fd_frames. fd < 0 and
// the stage that failed when it cannot be had.
OpenResult open_bound_socket(CanSocketApi& api, std::string_view iface, bool fd_frames,
                             std::span<const CanIdFilter> filters) noexcept;

// The command that brings iface up (for CAN FD too when fd).
std::string bring_up_command(std::string_view iface, bool fd);

// What a kernel without CAN support is told, and what to do about it.
std::string no_can_text(int error);
inline constexpr std::string_view kNoCanFix =
    "load it with `sudo modprobe can_raw` (and `sudo modprobe vcan` for a virtual bus); a kernel built "
    "without CAN, like the development machines', cannot do it at all: run the CAN tests in the VM";

// Why opening uri's socket failed, as the error open_can_transport throws (DeviceNotFound,
// PermissionDenied, InvalidArgument or Error), with what to do about it.
[[noreturn]] void throw_open_error(std::string_view uri, std::string_view iface, bool fd, const OpenResult& r,
                                   CanSocketApi& api);

// struct canfd_frame <-> protocol frame. Error, remote and extended frames are not ours.
inline protocol::CanFrame from_wire(const canfd_frame& raw, bool fd) noexcept {
  protocol::CanFrame f;
  f.id = raw.can_id & CAN_SFF_MASK;
  f.fd = fd;
  f.length = std::min<std::uint8_t>(raw.len, fd ? CANFD_MAX_DLEN : CAN_MAX_DLEN);
  std::copy_n(std::begin(raw.data), f.length, f.data.begin());
  return f;
}
inline canfd_frame to_wire(const protocol::CanFrame& f) noexcept {
  canfd_frame raw{};
  raw.can_id = f.id & CAN_SFF_MASK;
  raw.len = std::min<std::uint8_t>(f.length, f.fd ? CANFD_MAX_DLEN : CAN_MAX_DLEN);
  std::copy_n(f.data.begin(), raw.len, std::begin(raw.data));
  return raw;
}

}  // namespace mrskin::socketcan
