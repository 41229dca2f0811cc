// The SocketCAN calls of the CAN transport behind one virtual per call: the seam its tests
// drive with a fake bus. Private to the driver (and its tests): it names OS types (pollfd).
#pragma once

#include <poll.h>

#include <cstddef>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/enumerate.hpp"
#include "mrskin/driver/transport.hpp"
#include "mrskin/driver/transports/can.hpp"

namespace mrskin {

// The socket calls of the transport, one virtual per call. Each returns >= 0 on success or
// -errno (errno itself is not used), so fakes need no thread-local state. Frames are the
// kernel's struct can_frame (CAN_MTU bytes) or struct canfd_frame (CANFD_MTU bytes).
class CanSocketApi {
 public:
  CanSocketApi() = default;
  CanSocketApi(const CanSocketApi&) = delete;
  CanSocketApi& operator=(const CanSocketApi&) = delete;
  CanSocketApi(CanSocketApi&&) = delete;
  CanSocketApi& operator=(CanSocketApi&&) = delete;
  virtual ~CanSocketApi() = default;

  // socket(PF_CAN, SOCK_RAW | SOCK_NONBLOCK | SOCK_CLOEXEC, CAN_RAW): a pollable descriptor.
  virtual int open_socket() noexcept = 0;
  virtual void close_socket(int fd) noexcept = 0;
  // ioctl(SIOCGIFINDEX), ioctl(SIOCGIFMTU), ioctl(SIOCGIFFLAGS) for the interface name.
  virtual int interface_index(int fd, std::string_view name) noexcept = 0;
  virtual int interface_mtu(int fd, std::string_view name) noexcept = 0;
  virtual int interface_flags(int fd, std::string_view name) noexcept = 0;
  // setsockopt(fd, level, option, value, size).
  virtual int set_option(int fd, int level, int option, std::span<const std::byte> value) noexcept = 0;
  // bind() to a sockaddr_can of the interface index.
  virtual int bind_interface(int fd, int ifindex) noexcept = 0;
  // read() / write() of one frame: the bytes moved, or -errno (-EAGAIN: nothing now / full).
  virtual long read_frame(int fd, std::span<std::byte> frame) noexcept = 0;
  virtual long write_frame(int fd, std::span<const std::byte> frame) noexcept = 0;
  // ppoll(): timeout < 0 waits without limit. Returns the ready count, 0 on timeout.
  virtual int poll(std::span<pollfd> fds, Duration timeout) noexcept = 0;
  // The interfaces of type ARPHRD_CAN (/sys/class/net/*/type == 280), sorted. Setup only.
  virtual std::vector<std::string> can_interfaces() = 0;
};

// The kernel's SocketCAN.
std::shared_ptr<CanSocketApi> make_system_can_api();

// open_can_transport() on a given seam.
std::unique_ptr<Transport> open_can_transport(std::string_view uri, const CanTransportOptions& options,
                                              std::shared_ptr<CanSocketApi> api);

// list_can_devices() on a given seam: the interfaces api lists, each probed for nodes 1..15.
std::vector<DeviceListing> list_can_devices(CanSocketApi& api, Duration timeout);

}  // namespace mrskin
