// mrskin-vm-udev-relay: inside the VM, which runs no udev daemon, re-broadcasts the kernel's
// uevents the way udevd does once it has processed them (netlink group 2, libudev's message
// header with the subsystem and devtype hashes its monitors filter on). libusb (built with
// udev) keeps its device list and hotplug callbacks from those broadcasts only, so without
// this a USB device that arrives after libusb_init() is never seen. No rules are applied.
// Runs until SIGTERM or SIGINT.
#include <linux/netlink.h>
#include <signal.h>
#include <sys/socket.h>
#include <unistd.h>

#include <array>
#include <cerrno>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <string>
#include <string_view>
#include <vector>

namespace {

volatile sig_atomic_t g_stop = 0;
void on_signal(int /*signal*/) { g_stop = 1; }

// systemd's string_hash32: MurmurHash2 with seed 0.
std::uint32_t murmur2(std::string_view key) {
  constexpr std::uint32_t m = 0x5bd1e995;
  std::uint32_t h = static_cast<std::uint32_t>(key.size());
  const auto* data = reinterpret_cast<const unsigned char*>(key.data());
  std::size_t len = key.size();
  while (len >= 4) {
    std::uint32_t k = static_cast<std::uint32_t>(data[0]) | (static_cast<std::uint32_t>(data[1]) << 8U) |
                      (static_cast<std::uint32_t>(data[2]) << 16U) |
                      (static_cast<std::uint32_t>(data[3]) << 24U);
    k *= m;
    k ^= k >> 24U;
    k *= m;
    h *= m;
    h ^= k;
    data += 4;
    len -= 4;
  }
  switch (len) {
    case 3:
      h ^= static_cast<std::uint32_t>(data[2]) << 16U;
      [[fallthrough]];
    case 2:
      h ^= static_cast<std::uint32_t>(data[1]) << 8U;
      [[fallthrough]];
    case 1:
      h ^= data[0];
      h *= m;
      break;
    default:
      break;
  }
  h ^= h >> 13U;
  h *= m;
  h ^= h >> 15U;
  return h;
}

// libudev's monitor_netlink_header.
struct Header {
  std::array<char, 8> prefix{};
  std::uint32_t magic = 0;  // big-endian 0xfeedcafe
  std::uint32_t header_size = 0;
  std::uint32_t properties_off = 0;
  std::uint32_t properties_len = 0;
  std::uint32_t filter_subsystem_hash = 0;  // big-endian
  std::uint32_t filter_devtype_hash = 0;    // big-endian
  std::uint32_t filter_tag_bloom_hi = 0;
  std::uint32_t filter_tag_bloom_lo = 0;
};

}  // namespace

int main() {
  struct sigaction sa {};
  sa.sa_handler = on_signal;
  sigaction(SIGTERM, &sa, nullptr);
  sigaction(SIGINT, &sa, nullptr);

  const int in = socket(AF_NETLINK, SOCK_RAW | SOCK_CLOEXEC, NETLINK_KOBJECT_UEVENT);
  const int out = socket(AF_NETLINK, SOCK_RAW | SOCK_CLOEXEC, NETLINK_KOBJECT_UEVENT);
  if (in < 0 || out < 0) {
    std::perror("udev-relay: socket");
    return 1;
  }
  sockaddr_nl kernel{};
  kernel.nl_family = AF_NETLINK;
  kernel.nl_groups = 1;  // the kernel's uevents
  if (bind(in, reinterpret_cast<sockaddr*>(&kernel), sizeof kernel) != 0) {
    std::perror("udev-relay: bind");
    return 1;
  }
  sockaddr_nl self{};
  self.nl_family = AF_NETLINK;
  if (bind(out, reinterpret_cast<sockaddr*>(&self), sizeof self) != 0) {
    std::perror("udev-relay: bind");
    return 1;
  }
  timeval tv{0, 200000};
  setsockopt(in, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
  std::fprintf(stderr, "udev-relay: running\n");
  std::fflush(stderr);

  std::vector<char> buffer(16384);
  std::uint64_t relayed = 0;
  while (g_stop == 0) {
    const ssize_t n = recv(in, buffer.data(), buffer.size(), 0);
    if (n <= 0) {
      continue;
    }
    // "ACTION@DEVPATH\0KEY=VALUE\0...": keep the properties, note SUBSYSTEM and DEVTYPE.
    std::string properties;
    std::string subsystem;
    std::string devtype;
    std::size_t pos = std::strlen(buffer.data()) + 1;
    while (pos < static_cast<std::size_t>(n)) {
      const std::string_view kv(buffer.data() + pos);
      if (kv.starts_with("SUBSYSTEM=")) {
        subsystem = kv.substr(10);
      } else if (kv.starts_with("DEVTYPE=")) {
        devtype = kv.substr(8);
      }
      properties.append(kv);
      properties.push_back('\0');
      pos += kv.size() + 1;
    }
    if (subsystem.empty()) {
      continue;
    }
    properties.append("USEC_INITIALIZED=1");
    properties.push_back('\0');
    Header h;
    std::memcpy(h.prefix.data(), "libudev", 8);
    h.magic = htobe32(0xfeedcafeU);
    h.header_size = sizeof(Header);
    h.properties_off = sizeof(Header);
    h.properties_len = static_cast<std::uint32_t>(properties.size());
    h.filter_subsystem_hash = htobe32(murmur2(subsystem));
    h.filter_devtype_hash = devtype.empty() ? 0 : htobe32(murmur2(devtype));
    std::array<iovec, 2> iov{};
    iov[0].iov_base = &h;
    iov[0].iov_len = sizeof h;
    iov[1].iov_base = properties.data();
    iov[1].iov_len = properties.size();
    sockaddr_nl group{};
    group.nl_family = AF_NETLINK;
    group.nl_groups = 2;  // udev's
    msghdr msg{};
    msg.msg_name = &group;
    msg.msg_namelen = sizeof group;
    msg.msg_iov = iov.data();
    msg.msg_iovlen = iov.size();
    if (sendmsg(out, &msg, 0) >= 0 || errno == ECONNREFUSED) {
      ++relayed;
    }
  }
  std::fprintf(stderr, "udev-relay: relayed %llu events\n", static_cast<unsigned long long>(relayed));
  return 0;
}
