// SocketCAN: opening a raw socket bound to an interface, the errors of doing so, and the kernel's
// calls behind the CanSocketApi seam.
#include "can_socket.hpp"

#include <fmt/format.h>
#include <linux/can.h>
#include <linux/can/error.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <memory>
#include <string>
#include <vector>

#include "mrskin/driver/errors.hpp"

namespace mrskin {
namespace socketcan {
namespace {

// Error frames worth knowing about; lost arbitration is normal bus traffic.
constexpr can_err_mask_t kErrorMask = CAN_ERR_TX_TIMEOUT | CAN_ERR_CRTL | CAN_ERR_PROT | CAN_ERR_TRX |
                                      CAN_ERR_ACK | CAN_ERR_BUSOFF | CAN_ERR_BUSERROR | CAN_ERR_RESTARTED;

template <class T>
std::span<const std::byte> bytes_of(const T& value) noexcept {
  return std::as_bytes(std::span<const T, 1>(&value, 1));
}

}  // namespace

std::string error_text(int error) { return std::strerror(error); }

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

}  // namespace socketcan

namespace {

// The kernel's calls, one per seam method.
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

}  // namespace mrskin
