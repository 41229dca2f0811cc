// The can:// transport and its packet <-> frame codec, on a fake SocketCAN (FakeCan): a
// virtual bus with the kernel's filter semantics, errno injection and a simulated node
// (CanPacketCodec in the device role in front of the mock device's firmware).
#include <gtest/gtest.h>
#include <linux/can.h>
#include <linux/can/error.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <sys/eventfd.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <cstring>
#include <functional>
#include <initializer_list>
#include <map>
#include <mutex>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "../protocol/test_support.hpp"
#include "counting_new.hpp"
#include "mrskin/driver/session.hpp"
#include "mrskin/protocol/can.hpp"
#include "mrskin/protocol/packed_report.hpp"
#include "mrskin/protocol/packet.hpp"
#include "mrskin/sim/mock_device.hpp"
#include "transports/can_socket_api.hpp"

namespace mrskin {
namespace {

namespace proto = mrskin::protocol;
using std::chrono::milliseconds;

// --- helpers -----------------------------------------------------------------------------------

std::vector<std::uint8_t> packet_of(const proto::Message& m, std::uint8_t sequence = 0) {
  std::vector<std::uint8_t> p(proto::kPacketMaxBytes);
  const proto::EncodeResult r = proto::encode_packet(m, sequence, p);
  EXPECT_EQ(r.error, proto::Error::ok);
  p.resize(r.bytes);
  return p;
}

proto::PacketDecoded decoded(const Datagram& d) {
  return proto::decode_packet(std::span<const std::uint8_t>(d.bytes.data(), d.length));
}

// Waits (real time, bounded) for a condition the I/O thread brings about.
bool eventually(const std::function<bool()>& condition) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(20);
  while (!condition()) {
    if (std::chrono::steady_clock::now() > deadline) {
      return false;
    }
    std::this_thread::sleep_for(std::chrono::microseconds(100));
  }
  return true;
}

canfd_frame raw_of(const proto::CanFrame& f) {
  canfd_frame raw{};
  raw.can_id = f.id;
  raw.len = f.length;
  std::copy_n(f.data.begin(), f.length, std::begin(raw.data));
  return raw;
}

// A golden message (tests/protocol/test_support.hpp) by name.
proto::Message golden(std::string_view name) {
  for (const auto& nm : proto::test::golden_messages()) {
    if (nm.name == name) {
      return nm.message;
    }
  }
  ADD_FAILURE() << "no golden message " << name;
  return {};
}
proto::Message sample_status() { return golden("status"); }
proto::Message sample_identity() { return golden("identity"); }

proto::ValveCurrents valves(std::uint16_t first, std::uint8_t count, std::uint16_t base) {
  proto::ValveCurrents v;
  v.first = first;
  v.count = count;
  for (std::size_t i = 0; i < count; ++i) {
    v.counts[i] = static_cast<std::uint16_t>(base + i);
  }
  return v;
}

proto::Telemetry telemetry(std::uint32_t time_us, std::uint16_t first, std::uint8_t count) {
  proto::Telemetry t;
  t.device_time_us = time_us;
  t.first = first;
  t.count = count;
  for (std::size_t i = 0; i < count; ++i) {
    t.counts[i] = static_cast<std::int16_t>(static_cast<int>(i * 37) - 200);
  }
  return t;
}

// Frames of one packet sent by a codec.
std::vector<proto::CanFrame> encode(CanPacketCodec& codec, const proto::Message& m,
                                    std::uint8_t sequence = 0) {
  std::array<proto::CanFrame, CanPacketCodec::kMaxFrames> frames{};
  const std::vector<std::uint8_t> p = packet_of(m, sequence);
  const CanPacketCodec::Encoded e = codec.encode(p, frames);
  EXPECT_EQ(e.error, proto::Error::ok);
  return {frames.begin(), frames.begin() + static_cast<std::ptrdiff_t>(e.frames)};
}

// Packets a codec hands on for frames.
std::vector<proto::PacketDecoded> decode(CanPacketCodec& codec, const std::vector<proto::CanFrame>& frames) {
  std::vector<proto::PacketDecoded> out;
  for (const proto::CanFrame& f : frames) {
    const CanPacketCodec::Decoded d = codec.decode(f);
    if (d.complete) {
      out.push_back(decoded(d.packet));
    }
  }
  return out;
}

// --- the fake SocketCAN ------------------------------------------------------------------------

class FakeCan final : public CanSocketApi {
 public:
  struct Interface {
    int index = 0;
    int mtu = CAN_MTU;
    bool up = true;
    bool exists = true;
  };
  struct Socket {
    int fd = -1;  // a semaphore eventfd: readable while rx holds frames (or an error waits)
    bool open = true;
    int ifindex = 0;
    bool fd_frames = false;
    bool filtered = false;
    std::vector<can_filter> filters;
    can_err_mask_t error_mask = 0;
    int send_buffer = -1;
    int pending_error = 0;
    // Frames to read from rx_head on; a vector that keeps its capacity, so that a steady
    // stream of frames allocates nothing (the allocation test counts every thread).
    std::vector<std::pair<canfd_frame, std::size_t>> rx;
    std::size_t rx_head = 0;
    [[nodiscard]] bool rx_empty() const { return rx_head == rx.size(); }
  };

  FakeCan() { interfaces["vcan0"] = Interface{3, CAN_MTU, true, true}; }
  FakeCan(const FakeCan&) = delete;
  FakeCan& operator=(const FakeCan&) = delete;
  FakeCan(FakeCan&&) = delete;
  FakeCan& operator=(FakeCan&&) = delete;
  ~FakeCan() override {
    for (const Socket& s : sockets) {
      if (s.open) {
        ::close(s.fd);
      }
    }
  }

  int open_socket() noexcept override {
    const std::lock_guard lock(mu);
    if (socket_error != 0) {
      return -socket_error;
    }
    Socket s;
    s.fd = ::eventfd(0, EFD_NONBLOCK | EFD_SEMAPHORE | EFD_CLOEXEC);
    sockets.push_back(s);
    return s.fd;
  }
  void close_socket(int fd) noexcept override {
    const std::lock_guard lock(mu);
    Socket* s = find(fd);
    if (s != nullptr) {
      s->open = false;
      ::close(fd);
    }
  }
  int interface_index(int /*fd*/, std::string_view name) noexcept override {
    const std::lock_guard lock(mu);
    const Interface* i = iface(name);
    return i == nullptr ? -ENODEV : i->index;
  }
  int interface_mtu(int /*fd*/, std::string_view name) noexcept override {
    const std::lock_guard lock(mu);
    const Interface* i = iface(name);
    return i == nullptr ? -ENODEV : i->mtu;
  }
  int interface_flags(int /*fd*/, std::string_view name) noexcept override {
    const std::lock_guard lock(mu);
    const Interface* i = iface(name);
    return i == nullptr ? -ENODEV : (i->up ? IFF_UP | IFF_RUNNING : 0);
  }
  int set_option(int fd, int level, int option, std::span<const std::byte> value) noexcept override {
    const std::lock_guard lock(mu);
    Socket* s = find(fd);
    if (s == nullptr) {
      return -EBADF;
    }
    if (level == SOL_CAN_RAW && option == CAN_RAW_FILTER) {
      s->filters.resize(value.size() / sizeof(can_filter));
      std::memcpy(s->filters.data(), value.data(), s->filters.size() * sizeof(can_filter));
      s->filtered = true;
    } else if (level == SOL_CAN_RAW && option == CAN_RAW_ERR_FILTER &&
               value.size() == sizeof(can_err_mask_t)) {
      std::memcpy(&s->error_mask, value.data(), sizeof(can_err_mask_t));
    } else if (level == SOL_CAN_RAW && option == CAN_RAW_FD_FRAMES && value.size() == sizeof(int)) {
      int on = 0;
      std::memcpy(&on, value.data(), sizeof on);
      s->fd_frames = on != 0;
    } else if (level == SOL_SOCKET && option == SO_SNDBUF && value.size() == sizeof(int)) {
      std::memcpy(&s->send_buffer, value.data(), sizeof(int));
    } else {
      return -ENOPROTOOPT;
    }
    return 0;
  }
  int bind_interface(int fd, int ifindex) noexcept override {
    const std::lock_guard lock(mu);
    Socket* s = find(fd);
    if (s == nullptr) {
      return -EBADF;
    }
    s->ifindex = ifindex;
    return 0;
  }
  long read_frame(int fd, std::span<std::byte> frame) noexcept override {
    const std::lock_guard lock(mu);
    Socket* s = find(fd);
    if (s == nullptr) {
      return -EBADF;
    }
    if (s->pending_error != 0) {
      consume(*s);
      return -std::exchange(s->pending_error, 0);
    }
    if (s->rx_empty()) {
      return -EAGAIN;
    }
    const auto [raw, size] = s->rx[s->rx_head++];
    if (s->rx_empty()) {
      s->rx.clear();
      s->rx_head = 0;
    }
    consume(*s);
    std::memcpy(frame.data(), &raw, std::min(size, frame.size()));
    ++frames_read;
    return static_cast<long>(size);
  }
  long write_frame(int fd, std::span<const std::byte> frame) noexcept override {
    const std::lock_guard lock(mu);
    Socket* s = find(fd);
    if (s == nullptr) {
      return -EBADF;
    }
    const Interface* i = iface_by_index(s->ifindex);
    if (i == nullptr || !i->up) {
      return -ENETDOWN;
    }
    if (enobufs > 0) {
      --enobufs;
      return -ENOBUFS;
    }
    if (eagain > 0) {
      --eagain;
      return -EAGAIN;
    }
    if (frame.size() != CAN_MTU && !(frame.size() == CANFD_MTU && s->fd_frames)) {
      return -EINVAL;
    }
    canfd_frame raw{};
    std::memcpy(&raw, frame.data(), frame.size());
    proto::CanFrame f;
    f.id = raw.can_id;
    f.length = raw.len;
    f.fd = frame.size() == CANFD_MTU;
    std::copy_n(std::begin(raw.data), raw.len, f.data.begin());
    if (written.empty()) {
      written.reserve(kReserve);
    }
    written.push_back(f);
    deliver_locked(raw, frame.size(), s->ifindex, s);  // other sockets see it, as on a bus
    if (on_write) {
      on_write(f);
    }
    return static_cast<long>(frame.size());
  }
  int poll(std::span<pollfd> fds, Duration timeout) noexcept override {
    ++polls;
    return kernel->poll(fds, timeout);  // the descriptors are real eventfds
  }
  std::vector<std::string> can_interfaces() override {
    const std::lock_guard lock(mu);
    std::vector<std::string> names;
    for (const auto& [name, i] : interfaces) {
      if (i.exists) {
        names.push_back(name);
      }
    }
    return names;
  }

  // --- test controls -------------------------------------------------------------------------
  // A frame on the wire of vcan0 (filters apply, as in the kernel).
  void inject(const proto::CanFrame& f) {
    const std::lock_guard lock(mu);
    inject_locked(f);
  }
  void inject_locked(const proto::CanFrame& f) {
    deliver_locked(raw_of(f), f.fd ? CANFD_MTU : CAN_MTU, interfaces["vcan0"].index, nullptr);
  }
  // bypass_filters: as if the socket had no filters (what the transport itself does with it).
  void inject_raw(const canfd_frame& raw, std::size_t size, bool bypass_filters = false) {
    const std::lock_guard lock(mu);
    deliver_locked(raw, size, interfaces["vcan0"].index, nullptr, bypass_filters);
  }
  // The interface goes down (ENETDOWN on every socket bound to it) or away (ENODEV).
  void take_down(const std::string& name, bool remove) {
    const std::lock_guard lock(mu);
    Interface& i = interfaces[name];
    i.up = false;
    i.exists = !remove;
    for (Socket& s : sockets) {
      if (s.open && s.ifindex == i.index) {
        s.pending_error = remove ? ENODEV : ENETDOWN;
        signal(s);
      }
    }
  }
  void bring_up(const std::string& name) {
    const std::lock_guard lock(mu);
    interfaces[name].up = true;
    interfaces[name].exists = true;
  }
  Socket last_socket() {
    const std::lock_guard lock(mu);
    return sockets.back();
  }
  std::size_t open_sockets() {
    const std::lock_guard lock(mu);
    return static_cast<std::size_t>(
        std::count_if(sockets.begin(), sockets.end(), [](const Socket& s) { return s.open; }));
  }
  std::vector<proto::CanFrame> written_frames() {
    const std::lock_guard lock(mu);
    return written;
  }
  std::size_t written_count() {
    const std::lock_guard lock(mu);
    return written.size();
  }
  // Every frame queued for reading has been read.
  bool drained() {
    const std::lock_guard lock(mu);
    return std::all_of(sockets.begin(), sockets.end(),
                       [](const Socket& s) { return !s.open || s.rx_empty(); });
  }
  std::uint64_t read_count() {
    const std::lock_guard lock(mu);
    return frames_read;
  }
  void set_write_errors(int enobufs_count, int eagain_count) {
    const std::lock_guard lock(mu);
    enobufs = enobufs_count;
    eagain = eagain_count;
  }

  std::mutex mu;
  std::map<std::string, Interface, std::less<>> interfaces;
  std::vector<Socket> sockets;
  int socket_error = 0;
  std::function<void(const proto::CanFrame&)> on_write;  // runs under mu
  std::atomic<std::uint64_t> polls{0};
  std::shared_ptr<CanSocketApi> kernel = make_system_can_api();

 private:
  Socket* find(int fd) {
    for (Socket& s : sockets) {
      if (s.open && s.fd == fd) {
        return &s;
      }
    }
    return nullptr;
  }
  Interface* iface(std::string_view name) {
    const auto it = interfaces.find(name);
    return it == interfaces.end() || !it->second.exists ? nullptr : &it->second;
  }
  Interface* iface_by_index(int index) {
    for (auto& [name, i] : interfaces) {
      if (i.index == index && i.exists) {
        return &i;
      }
    }
    return nullptr;
  }
  static void signal(const Socket& s) {
    const std::uint64_t one = 1;
    EXPECT_EQ(::write(s.fd, &one, sizeof one), static_cast<ssize_t>(sizeof one));
  }
  static void consume(const Socket& s) {
    std::uint64_t v = 0;
    (void)!::read(s.fd, &v, sizeof v);
  }
  static bool passes(const Socket& s, const canfd_frame& raw, std::size_t size) {
    if (size == CANFD_MTU && !s.fd_frames) {
      return false;
    }
    if ((raw.can_id & CAN_ERR_FLAG) != 0) {
      return (raw.can_id & CAN_ERR_MASK & s.error_mask) != 0;
    }
    if (!s.filtered) {
      return true;
    }
    return std::any_of(s.filters.begin(), s.filters.end(), [&raw](const can_filter& f) {
      return (raw.can_id & f.can_mask) == (f.can_id & f.can_mask);
    });
  }
  void deliver_locked(const canfd_frame& raw, std::size_t size, int ifindex, const Socket* from,
                      bool bypass_filters = false) {
    for (Socket& s : sockets) {
      if (s.open && &s != from && s.ifindex == ifindex && (bypass_filters || passes(s, raw, size))) {
        if (s.rx.empty()) {
          s.rx.reserve(kReserve);
        }
        s.rx.emplace_back(raw, size);
        signal(s);
      }
    }
  }

  static constexpr std::size_t kReserve = 8192;
  std::vector<proto::CanFrame> written;
  std::uint64_t frames_read = 0;
  int enobufs = 0;
  int eagain = 0;
};

CanTransportOptions fast_options() {
  CanTransportOptions o;
  o.reopen_backoff_min = milliseconds(1);
  o.reopen_backoff_max = milliseconds(4);
  return o;
}

std::unique_ptr<Transport> open_on(const std::shared_ptr<FakeCan>& bus, std::string_view uri,
                                   CanTransportOptions options = fast_options()) {
  return open_can_transport(uri, options, bus);
}

CanTransportStats stats_of(const Transport& t) {
  const auto s = can_transport_stats(t);
  EXPECT_TRUE(s.has_value());
  return s.value_or(CanTransportStats{});
}

std::vector<proto::PacketDecoded> receive_all(Transport& t, std::size_t want) {
  std::vector<proto::PacketDecoded> out;
  Datagram d;
  while (out.size() < want && t.receive_for(d, std::chrono::seconds(20)) == ResultCode::ok) {
    out.push_back(decoded(d));
  }
  return out;
}

// ================================================================================= URI

TEST(CanUri, ParsesInterfaceNodeAndFd) {
  const CanUri a = parse_can_uri("can://can0?node=3");
  EXPECT_EQ(a.interface, "can0");
  EXPECT_EQ(a.node, 3);
  EXPECT_FALSE(a.fd);
  const CanUri b = parse_can_uri("can://vcan0?fd=1&node=15");
  EXPECT_EQ(b.interface, "vcan0");
  EXPECT_EQ(b.node, 15);
  EXPECT_TRUE(b.fd);
  EXPECT_FALSE(parse_can_uri("can://x?node=1&fd=0").fd);
  EXPECT_EQ(format_can_uri(b), "can://vcan0?node=15&fd=1");
  EXPECT_EQ(parse_can_uri(format_can_uri(a)).node, 3);
}

TEST(CanUri, RefusesBadUrisNamingTheBadPart) {
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"hid://can0?node=1", "not a can:// URI"},
      {"can://?node=1", "names no CAN interface"},
      {"can://can0", "needs node=N"},
      {"can://can0?fd=1", "needs node=N"},
      {"can://can0?node=0", "node '0'"},
      {"can://can0?node=16", "node '16'"},
      {"can://can0?node=3x", "node '3x'"},
      {"can://can0?node=", "node ''"},
      {"can://can0?node=1&fd=2", "fd '2'"},
      {"can://can0?node=1&bitrate=500000", "unknown parameter 'bitrate'"},
      {"can://can0?node", "parameter 'node' needs a value"},
      {"can://averyveryverylongname?node=1", "longer than 15"},
      {"can://a/b?node=1", "'a/b' is not an interface name"},
  };
  for (const auto& [uri, part] : cases) {
    try {
      (void)parse_can_uri(uri);
      ADD_FAILURE() << uri << " was accepted";
    } catch (const InvalidArgument& e) {
      EXPECT_NE(std::string(e.what()).find(part), std::string::npos) << uri << ": " << e.what();
    }
  }
}

// ================================================================================= codec

TEST(CanCodec, EveryGoldenMessageRoundTripsOnClassicAndFd) {
  for (const bool fd : {false, true}) {
    for (const auto& [name, m] : proto::test::golden_messages()) {
      const bool from_host = proto::test::direction_of(m) == proto::Direction::host_to_device;
      CanPacketCodec sender(from_host ? CanRole::host : CanRole::device, 5, fd);
      CanPacketCodec receiver(from_host ? CanRole::device : CanRole::host, 5, fd);
      const auto packets = decode(receiver, encode(sender, m, 0x2A));
      if (!fd && std::holds_alternative<proto::TimeSync>(m)) {
        EXPECT_TRUE(packets.empty());  // it stamps the sensor blocks that follow
        continue;
      }
      ASSERT_FALSE(packets.empty()) << name << " fd " << fd;
      proto::test::BlockMerger merged;
      for (const auto& p : packets) {
        EXPECT_EQ(p.error, proto::Error::ok);
        EXPECT_TRUE(merged.add(p.message)) << name;
      }
      EXPECT_EQ(merged.result(), m) << name << " fd " << fd;
      if (fd) {
        EXPECT_EQ(packets[0].sequence, 0x2A);
      }
    }
  }
}

// Protocol 1.2: the packets of one packed report, sequences from 0.
std::vector<std::uint8_t> packed_report(std::initializer_list<proto::Message> messages) {
  std::array<std::uint8_t, proto::kHidReportBytes> report{};
  std::size_t used = 0;
  std::uint8_t sequence = 0;
  for (const proto::Message& m : messages) {
    const proto::EncodeResult r = proto::append_packet(m, sequence++, report, used);
    EXPECT_EQ(r.error, proto::Error::ok);
    used += r.bytes;
  }
  return {report.begin(), report.begin() + static_cast<std::ptrdiff_t>(used)};
}

TEST(CanCodec, APackedReportOnClassicCanIsItsPacketsFramesAsIfSentAlone) {
  CanPacketCodec packed(CanRole::host, 5, false);
  CanPacketCodec alone(CanRole::host, 5, false);
  const proto::ValveCurrents v = valves(0, 12, 1000);
  std::array<proto::CanFrame, CanPacketCodec::kMaxFrames> frames{};
  const CanPacketCodec::Encoded e = packed.encode(packed_report({proto::Heartbeat{3}, v}), frames);
  ASSERT_EQ(e.error, proto::Error::ok);
  std::vector<proto::CanFrame> expected = encode(alone, proto::Heartbeat{3}, 0);
  const std::vector<proto::CanFrame> blocks = encode(alone, v, 1);
  expected.insert(expected.end(), blocks.begin(), blocks.end());
  ASSERT_EQ(e.frames, expected.size());  // 1 heartbeat + 3 valve blocks
  for (std::size_t i = 0; i < expected.size(); ++i) {
    EXPECT_EQ(frames[i], expected[i]) << i;
  }
  EXPECT_EQ(CanPacketCodec::check(CanRole::host, false, packed_report({proto::Heartbeat{3}, v})),
            proto::Error::ok);
  // A packet of the other direction anywhere in the report refuses it all.
  EXPECT_EQ(
      CanPacketCodec::check(CanRole::host, false, packed_report({proto::Heartbeat{3}, proto::Status{}})),
      proto::Error::unknown_type);
  // The unit's echo has no classic form: counted, not sent.
  CanPacketCodec device(CanRole::device, 5, false);
  const CanPacketCodec::Encoded d =
      device.encode(packed_report({proto::Status{}, proto::Heartbeat{3}, telemetry(7, 0, 12)}), frames);
  ASSERT_EQ(d.error, proto::Error::ok);
  EXPECT_EQ(d.frames, 1U + 1U + 3U);  // status, TimeSync, 3 sensor blocks
  EXPECT_EQ(d.unsent, 1U);
}

TEST(CanCodec, APackedReportOnCanFdIsOneFrameHandedOnWhole) {
  CanPacketCodec device(CanRole::device, 5, true);
  CanPacketCodec host(CanRole::host, 5, true);
  const std::vector<std::uint8_t> report =
      packed_report({proto::Status{}, proto::Heartbeat{3}, telemetry(7, 0, 12)});
  std::array<proto::CanFrame, CanPacketCodec::kMaxFrames> frames{};
  const CanPacketCodec::Encoded e = device.encode(report, frames);
  ASSERT_EQ(e.error, proto::Error::ok);
  ASSERT_EQ(e.frames, 1U);
  EXPECT_EQ(frames[0].length, proto::canfd_padded_length(report.size()));
  const CanPacketCodec::Decoded d = host.decode(frames[0]);
  ASSERT_TRUE(d.complete);
  ASSERT_GE(d.packet.length, report.size());
  EXPECT_TRUE(
      std::equal(report.begin(), report.end(), d.packet.bytes.begin()));  // every packet, for the walk
  // A lone packet is handed on as before: the packet alone.
  const CanPacketCodec::Decoded one = host.decode(encode(device, proto::Status{}, 9)[0]);
  ASSERT_TRUE(one.complete);
  EXPECT_EQ(one.packet.length, packet_of(proto::Status{}, 9).size());
}

TEST(CanCodec, ClassicFramesAreTheProtocolEncodersFrames) {
  CanPacketCodec host(CanRole::host, 5, false);
  const proto::ValveCurrents v = valves(0, 12, 1000);
  const auto frames = encode(host, v, 7);
  std::array<proto::CanFrame, 12> expected{};
  const proto::CanEncodeResult r = proto::encode_can(v, 5, 0, 7, expected);
  ASSERT_EQ(r.frames, 3U);
  ASSERT_EQ(frames.size(), 3U);
  for (std::size_t i = 0; i < 3; ++i) {
    EXPECT_EQ(frames[i], expected[i]) << i;
  }
  // The next update carries the next rolling counter.
  const auto next = encode(host, v, 8);
  ASSERT_EQ(proto::encode_can(v, 5, 1, 8, expected).frames, 3U);
  EXPECT_EQ(next[0], expected[0]);
}

TEST(CanCodec, DeviceToHostMessagesRoundTripAndTelemetryIsStampedByItsTimeSync) {
  CanPacketCodec device(CanRole::device, 9, false);
  CanPacketCodec host(CanRole::host, 9, false);
  const proto::Telemetry t = telemetry(0x12345678, 0, 12);
  const auto frames = encode(device, t);
  ASSERT_EQ(frames.size(), 4U);  // TimeSync + 3 sensor blocks
  EXPECT_EQ(frames[0].id, proto::can_id(proto::CanFunction::management, 2, 9));
  const auto packets = decode(host, frames);
  ASSERT_EQ(packets.size(), 3U);
  for (std::size_t b = 0; b < 3; ++b) {
    const auto& block = std::get<proto::Telemetry>(packets[b].message);
    EXPECT_EQ(block.device_time_us, 0x12345678U);
    EXPECT_EQ(block.first, 4 * b);
    ASSERT_EQ(block.count, 4);
    for (std::size_t i = 0; i < 4; ++i) {
      EXPECT_EQ(block.counts[i], t.counts[4 * b + i]);
    }
  }
  EXPECT_EQ(packets[1].sequence, static_cast<std::uint8_t>(packets[0].sequence + 1));
  // No heartbeat echo on classic CAN; on CAN FD the echo goes back.
  EXPECT_TRUE(encode(device, proto::Heartbeat{7}).empty());
  CanPacketCodec device_fd(CanRole::device, 9, true);
  CanPacketCodec host_fd(CanRole::host, 9, true);
  const auto echo = decode(host_fd, encode(device_fd, proto::Heartbeat{7}, 0x33));
  ASSERT_EQ(echo.size(), 1U);
  EXPECT_EQ(echo[0].message, proto::Message(proto::Heartbeat{7}));
  EXPECT_EQ(echo[0].sequence, 0x33);  // FD keeps the device's own sequence
}

TEST(CanCodec, CurrentsOffABlockBoundaryFillTheBlockFromTheValuesLastSent) {
  CanPacketCodec host(CanRole::host, 2, false);
  CanPacketCodec device(CanRole::device, 2, false);
  // 32 valves, as the session sends them: 27, then 5 from valve 27.
  const auto first = decode(device, encode(host, valves(0, 27, 100)));
  ASSERT_EQ(first.size(), 7U);
  const auto second = decode(device, encode(host, valves(27, 5, 500)));
  ASSERT_EQ(second.size(), 2U);
  const auto& b6 = std::get<proto::ValveCurrents>(second[0].message);
  EXPECT_EQ(b6.first, 24);
  ASSERT_EQ(b6.count, 4);
  EXPECT_EQ(b6.counts[0], 124);  // from the first packet
  EXPECT_EQ(b6.counts[2], 126);
  EXPECT_EQ(b6.counts[3], 500);  // valve 27, new
  const auto& b7 = std::get<proto::ValveCurrents>(second[1].message);
  EXPECT_EQ(b7.first, 28);
  EXPECT_EQ(b7.count, 4);
  EXPECT_EQ(b7.counts[3], 504);
  // A node addresses 64 valves; a cell index above 255 does not fit classic CAN.
  EXPECT_EQ(CanPacketCodec::check(CanRole::host, false, packet_of(valves(60, 5, 0))),
            proto::Error::out_of_range);
  EXPECT_EQ(CanPacketCodec::check(CanRole::host, true, packet_of(valves(60, 5, 0))), proto::Error::ok);
  proto::CellTargets far;
  far.first = 255;
  far.count = 2;
  EXPECT_EQ(CanPacketCodec::check(CanRole::host, false, packet_of(far)), proto::Error::out_of_range);
  // Each role sends only its own direction.
  EXPECT_EQ(CanPacketCodec::check(CanRole::host, false, packet_of(sample_status())),
            proto::Error::unknown_type);
  EXPECT_EQ(CanPacketCodec::check(CanRole::device, false, packet_of(valves(0, 1, 0))),
            proto::Error::unknown_type);
  const std::vector<std::uint8_t> garbage{1, 2, 3};
  EXPECT_NE(CanPacketCodec::check(CanRole::host, false, garbage), proto::Error::ok);
}

TEST(CanCodec, FramesOfOtherNodesOrOfOurOwnDirectionAreRefused) {
  CanPacketCodec host(CanRole::host, 5, false);
  CanPacketCodec other(CanRole::device, 6, false);
  CanPacketCodec another_host(CanRole::host, 5, false);
  for (const proto::CanFrame& f : encode(other, sample_status())) {
    EXPECT_EQ(host.decode(f).error, proto::Error::wrong_node);
  }
  // Another host's (or our own echoed) frames for node 5.
  for (const proto::CanFrame& f : encode(another_host, proto::Heartbeat{1})) {
    const auto d = host.decode(f);
    EXPECT_EQ(d.error, proto::Error::unknown_type);
    EXPECT_FALSE(d.complete);
  }
  for (const proto::CanFrame& f : encode(another_host, proto::IdentifyRequest{})) {
    EXPECT_EQ(host.decode(f).error, proto::Error::unknown_type);
  }
}

TEST(CanCodec, LossesBecomeSequenceGapsForTheSession) {
  CanPacketCodec device(CanRole::device, 4, false);
  CanPacketCodec host(CanRole::host, 4, false);
  const auto s0 = encode(device, sample_status());
  const auto s1 = encode(device, sample_status());
  const auto s2 = encode(device, sample_status());  // lost on the way
  const auto s3 = encode(device, sample_status());
  const auto a = decode(host, s0);
  const auto b = decode(host, s1);
  const auto c = decode(host, s3);
  ASSERT_EQ(a.size() + b.size() + c.size(), 3U);
  EXPECT_EQ(b[0].sequence, static_cast<std::uint8_t>(a[0].sequence + 1));
  EXPECT_EQ(c[0].sequence, static_cast<std::uint8_t>(b[0].sequence + 2));  // one status missed
  // A corrupted frame: refused, and the next packet shows the gap.
  auto bad = encode(device, sample_status());
  bad[0].data[1] ^= 0x10U;
  EXPECT_EQ(host.decode(bad[0]).error, proto::Error::bad_crc);
  const auto d = decode(host, encode(device, sample_status()));
  ASSERT_EQ(d.size(), 1U);
  EXPECT_EQ(d[0].sequence, static_cast<std::uint8_t>(c[0].sequence + 2));
  // Sensor blocks without their TimeSync have no time: dropped, counted as a gap.
  auto sample = encode(device, telemetry(5, 0, 8));
  ASSERT_EQ(sample.size(), 3U);
  const auto e = host.decode(sample[1]);  // TimeSync lost: the block is stale
  (void)host.decode(sample[2]);
  EXPECT_FALSE(e.complete);
  const auto next = decode(host, encode(device, telemetry(6, 0, 4)));
  ASSERT_EQ(next.size(), 1U);
  EXPECT_EQ(std::get<proto::Telemetry>(next[0].message).device_time_us, 6U);
  EXPECT_EQ(next[0].sequence, static_cast<std::uint8_t>(d[0].sequence + 3));
}

// ================================================================================= transport

TEST(CanTransport, SetsNodeFiltersErrorFramesAndAMinimalSendBuffer) {
  auto bus = std::make_shared<FakeCan>();
  auto t = open_on(bus, "can://vcan0?node=7");
  EXPECT_EQ(t->state(), TransportState::open);
  EXPECT_EQ(t->uri(), "can://vcan0?node=7");
  const FakeCan::Socket s = bus->last_socket();
  EXPECT_EQ(s.ifindex, 3);
  EXPECT_FALSE(s.fd_frames);
  EXPECT_EQ(s.send_buffer, 0);  // the kernel clamps it to its minimum
  EXPECT_NE(s.error_mask & CAN_ERR_BUSOFF, 0U);
  EXPECT_NE(s.error_mask & CAN_ERR_RESTARTED, 0U);
  EXPECT_EQ(s.error_mask & CAN_ERR_LOSTARB, 0U);
  const CanIdFilters want = can_receive_filters(CanRole::host, 7);
  ASSERT_EQ(s.filters.size(), want.count);
  for (std::size_t i = 0; i < want.count; ++i) {
    EXPECT_EQ(s.filters[i].can_id, want.filters[i].id);
    EXPECT_EQ(s.filters[i].can_mask, want.filters[i].mask);
  }
  // What the filters let through: this node's device->host identifiers only.
  const auto passes = [&s](std::uint32_t id) {
    return std::any_of(s.filters.begin(), s.filters.end(),
                       [id](const can_filter& f) { return (id & f.can_mask) == (f.can_id & f.can_mask); });
  };
  EXPECT_TRUE(passes(0x017));   // status
  EXPECT_TRUE(passes(0x027));   // time sync
  EXPECT_TRUE(passes(0x057));   // segmented device->host
  EXPECT_TRUE(passes(0x2F7));   // sensor block 15
  EXPECT_TRUE(passes(0x507));   // FD device->host
  EXPECT_FALSE(passes(0x007));  // heartbeat (host->device)
  EXPECT_FALSE(passes(0x107));  // valve block
  EXPECT_FALSE(passes(0x018));  // status of node 8
  EXPECT_FALSE(passes(0x017 | CAN_EFF_FLAG));
  EXPECT_FALSE(passes(0x017 | CAN_RTR_FLAG));
}

TEST(CanTransport, SendsPacketsAsFramesAndDeliversFramesAsPackets) {
  auto bus = std::make_shared<FakeCan>();
  auto t = open_on(bus, "can://vcan0?node=5");
  const proto::ValveCurrents v = valves(0, 12, 2000);
  ASSERT_EQ(t->send(packet_of(v, 0x11)), ResultCode::ok);
  ASSERT_EQ(t->send(packet_of(proto::IdentifyRequest{}, 0x12)), ResultCode::ok);
  ASSERT_TRUE(eventually([&] { return t->counters().sent == 2; }));
  const auto written = bus->written_frames();
  std::array<proto::CanFrame, 12> expected{};
  ASSERT_EQ(proto::encode_can(v, 5, 0, 0x11, expected).frames, 3U);
  ASSERT_EQ(proto::encode_can(proto::IdentifyRequest{}, 5, 0, 0x12, std::span(expected).subspan(3)).frames,
            2U);
  ASSERT_EQ(written.size(), 5U);
  for (std::size_t i = 0; i < 5; ++i) {
    EXPECT_EQ(written[i], expected[i]) << i;
  }
  EXPECT_EQ(stats_of(*t).frames_written, 5U);

  CanPacketCodec device(CanRole::device, 5, false);
  for (const proto::Message& m :
       std::vector<proto::Message>{sample_identity(), sample_status(), telemetry(777, 0, 12)}) {
    for (const proto::CanFrame& f : encode(device, m)) {
      bus->inject(f);
    }
  }
  const auto got = receive_all(*t, 5);
  ASSERT_EQ(got.size(), 5U);
  EXPECT_EQ(got[0].message, proto::Message(sample_identity()));
  EXPECT_EQ(got[1].message, proto::Message(sample_status()));
  for (std::size_t i = 2; i < 5; ++i) {
    const auto& block = std::get<proto::Telemetry>(got[i].message);
    EXPECT_EQ(block.device_time_us, 777U);
    EXPECT_EQ(block.first, 4 * (i - 2));
  }
  for (std::size_t i = 1; i < got.size(); ++i) {
    EXPECT_EQ(got[i].sequence, static_cast<std::uint8_t>(got[i - 1].sequence + 1));
  }
  EXPECT_EQ(t->counters().malformed, 0U);
}

TEST(CanTransport, RefusesPacketsItsFramingCannotCarry) {
  auto bus = std::make_shared<FakeCan>();
  auto t = open_on(bus, "can://vcan0?node=5");
  EXPECT_EQ(t->send(packet_of(sample_status())), ResultCode::invalid_value);   // device->host
  EXPECT_EQ(t->send(packet_of(valves(62, 3, 0))), ResultCode::invalid_value);  // valve 64
  const std::vector<std::uint8_t> empty;
  EXPECT_EQ(t->send(empty), ResultCode::invalid_value);
  EXPECT_EQ(t->send(packet_of(proto::Heartbeat{1})), ResultCode::ok);
  ASSERT_TRUE(eventually([&] { return t->counters().sent == 1; }));
  EXPECT_EQ(bus->written_count(), 1U);
}

TEST(CanTransport, ForeignAndMalformedFramesAreCountedAndNeverDelivered) {
  auto bus = std::make_shared<FakeCan>();
  auto t = open_on(bus, "can://vcan0?node=5");
  CanPacketCodec device(CanRole::device, 5, false);
  CanPacketCodec other_node(CanRole::device, 6, false);
  CanPacketCodec other_host(CanRole::host, 5, false);
  std::size_t expected_malformed = 0;
  const auto raw = [&](const proto::CanFrame& f, std::uint32_t flags = 0, std::size_t size = CAN_MTU) {
    canfd_frame r = raw_of(f);
    r.can_id |= flags;
    bus->inject_raw(r, size, true);
    ++expected_malformed;
  };
  const proto::CanFrame status = encode(device, sample_status())[0];
  raw(encode(other_node, sample_status())[0]);      // another node
  raw(encode(other_host, proto::Heartbeat{3})[0]);  // another host's heartbeat for our node
  raw(status, CAN_EFF_FLAG);                        // extended identifier
  raw(status, CAN_RTR_FLAG);                        // remote frame
  proto::CanFrame corrupt = status;
  corrupt.data[0] ^= 1U;
  raw(corrupt);  // CRC fails
  proto::CanFrame shorter = status;
  shorter.length = 5;
  raw(shorter);  // DLC 5
  proto::CanFrame unknown = status;
  unknown.id = 0x765;  // function 7: reserved
  raw(unknown);
  canfd_frame odd = raw_of(status);
  bus->inject_raw(odd, 10, true);  // neither CAN_MTU nor CANFD_MTU
  ++expected_malformed;
  // Random frames of our node id, fixed seed: no crash, nothing but valid packets delivered.
  std::mt19937 rng(20260707);
  std::uniform_int_distribution<int> byte(0, 255);
  std::size_t random_frames = 0;
  for (int i = 0; i < 3000; ++i) {
    proto::CanFrame f;
    // One draw a statement, in the order g++ took them: the order of `|`'s operands is unspecified.
    const int mid = byte(rng);
    const int high = byte(rng);
    f.id = static_cast<std::uint32_t>((high & 0x7) << 8 | (mid & 0xF) << 4 | 5);
    f.length = static_cast<std::uint8_t>(byte(rng) % 9);
    for (auto& b : f.data) {
      b = static_cast<std::uint8_t>(byte(rng));
    }
    canfd_frame r = raw_of(f);
    bus->inject_raw(r, CAN_MTU, true);
    ++random_frames;
  }
  ASSERT_TRUE(eventually([&] { return stats_of(*t).frames_read == expected_malformed + random_frames; }));
  Datagram d;
  while (t->receive(d) == ResultCode::ok) {
    EXPECT_EQ(decoded(d).error, proto::Error::ok);  // anything delivered is a valid packet
  }
  const std::uint64_t malformed = t->counters().malformed;
  EXPECT_GE(malformed, expected_malformed);
  EXPECT_GE(stats_of(*t).foreign_frames, 4U);
  // The link still works.
  bus->inject(status);
  const auto got = receive_all(*t, 1);
  ASSERT_EQ(got.size(), 1U);
  EXPECT_EQ(got[0].message, proto::Message(sample_status()));
  EXPECT_EQ(t->state(), TransportState::open);
}

TEST(CanTransport, EnobufsKeepsTheFrameAndRetriesIt) {
  auto bus = std::make_shared<FakeCan>();
  bus->set_write_errors(7, 3);
  auto t = open_on(bus, "can://vcan0?node=5");
  for (std::uint16_t i = 0; i < 4; ++i) {
    ASSERT_EQ(t->send(packet_of(proto::Heartbeat{i})), ResultCode::ok);
  }
  ASSERT_TRUE(eventually([&] { return t->counters().sent == 4; }));
  const auto written = bus->written_frames();
  ASSERT_EQ(written.size(), 4U);  // none lost...
  for (std::size_t i = 0; i < 4; ++i) {
    EXPECT_EQ(written[i].data[0], i);  // ...and in order
  }
  const CanTransportStats s = stats_of(*t);
  EXPECT_EQ(s.enobufs, 7U);
  EXPECT_EQ(s.send_buffer_full, 3U);
  EXPECT_EQ(s.dropped_packets, 0U);
  EXPECT_EQ(t->counters().io_errors, 0U);
}

TEST(CanTransport, AStalledBusGivesBackPressureNotLoss) {
  auto bus = std::make_shared<FakeCan>();
  CanTransportOptions o = fast_options();
  o.send_queue = 8;
  bus->set_write_errors(1'000'000, 0);  // the interface's queue stays full
  auto t = open_on(bus, "can://vcan0?node=5", o);
  std::uint16_t accepted = 0;
  ResultCode rc = ResultCode::ok;
  for (int i = 0; i < 100 && rc == ResultCode::ok; ++i) {
    rc = t->send(packet_of(proto::Heartbeat{accepted}));
    accepted = static_cast<std::uint16_t>(accepted + (rc == ResultCode::ok ? 1 : 0));
  }
  EXPECT_EQ(rc, ResultCode::would_block);
  EXPECT_GE(t->counters().send_would_block, 1U);
  EXPECT_GE(accepted, 8U);
  EXPECT_TRUE(eventually([&] { return stats_of(*t).enobufs >= 3; }));
  EXPECT_EQ(bus->written_count(), 0U);
  bus->set_write_errors(0, 0);  // the bus drains
  ASSERT_TRUE(eventually([&] { return t->counters().sent == accepted; }));
  const auto written = bus->written_frames();
  ASSERT_EQ(written.size(), accepted);
  for (std::size_t i = 0; i < written.size(); ++i) {
    EXPECT_EQ(written[i].data[0] | written[i].data[1] << 8U, static_cast<int>(i));
  }
}

canfd_frame error_frame(std::uint32_t classes, std::uint8_t controller = 0) {
  canfd_frame f{};
  f.can_id = CAN_ERR_FLAG | classes;
  f.len = CAN_ERR_DLC;
  f.data[1] = controller;
  return f;
}

TEST(CanTransport, BusOffIsReportedUntilTheControllerRestarts) {
  auto bus = std::make_shared<FakeCan>();
  auto t = open_on(bus, "can://vcan0?node=5");
  bus->inject_raw(error_frame(CAN_ERR_PROT), CAN_MTU);  // a bus error: counted, still open
  ASSERT_TRUE(eventually([&] { return t->counters().error_frames == 1; }));
  EXPECT_EQ(t->state(), TransportState::open);
  bus->inject_raw(error_frame(CAN_ERR_LOSTARB), CAN_MTU);  // not asked for: the filter drops it
  bus->inject_raw(error_frame(CAN_ERR_BUSOFF), CAN_MTU);
  ASSERT_TRUE(eventually([&] { return t->state() == TransportState::bus_off; }));
  EXPECT_EQ(t->counters().bus_off, 1U);
  EXPECT_EQ(t->counters().error_frames, 2U);
  EXPECT_EQ(t->send(packet_of(proto::Heartbeat{1})), ResultCode::disconnected);
  Datagram d;
  EXPECT_EQ(t->receive(d), ResultCode::disconnected);
  bus->inject_raw(error_frame(CAN_ERR_RESTARTED), CAN_MTU);
  ASSERT_TRUE(eventually([&] { return t->state() == TransportState::open; }));
  EXPECT_EQ(t->counters().reopens, 1U);
  // A second bus-off, and recovery by error-free traffic of our node.
  bus->inject_raw(error_frame(CAN_ERR_BUSOFF), CAN_MTU);
  ASSERT_TRUE(eventually([&] { return t->state() == TransportState::bus_off; }));
  CanPacketCodec device(CanRole::device, 5, false);
  bus->inject(encode(device, sample_status())[0]);
  ASSERT_TRUE(eventually([&] { return t->state() == TransportState::open; }));
  EXPECT_EQ(t->counters().bus_off, 2U);
  // And recovery reported by the controller going back to error-active.
  bus->inject_raw(error_frame(CAN_ERR_BUSOFF), CAN_MTU);
  ASSERT_TRUE(eventually([&] { return t->state() == TransportState::bus_off; }));
  bus->inject_raw(error_frame(CAN_ERR_CRTL, CAN_ERR_CRTL_ACTIVE), CAN_MTU);
  ASSERT_TRUE(eventually([&] { return t->state() == TransportState::open; }));
  ASSERT_EQ(t->send(packet_of(proto::Heartbeat{2})), ResultCode::ok);
  ASSERT_TRUE(eventually([&] { return t->counters().sent == 1; }));
}

TEST(CanTransport, InterfaceDownDisconnectsAndTheTransportReopensWhenItIsBack) {
  for (const bool removed : {false, true}) {
    auto bus = std::make_shared<FakeCan>();
    auto t = open_on(bus, "can://vcan0?node=5");
    bus->take_down("vcan0", removed);
    ASSERT_TRUE(eventually([&] { return t->state() == TransportState::disconnected; })) << removed;
    EXPECT_EQ(t->counters().disconnects, 1U);
    EXPECT_EQ(t->send(packet_of(proto::Heartbeat{1})), ResultCode::disconnected);
    EXPECT_TRUE(eventually([&] { return bus->polls.load() > 20; }));  // a few reopen attempts
    EXPECT_EQ(t->state(), TransportState::disconnected);
    EXPECT_EQ(bus->open_sockets(), 0U);
    bus->bring_up("vcan0");
    ASSERT_TRUE(eventually([&] { return t->state() == TransportState::open; }));
    EXPECT_EQ(t->counters().reopens, 1U);
    EXPECT_EQ(bus->open_sockets(), 1U);
    EXPECT_EQ(bus->last_socket().filters.size(), can_receive_filters(CanRole::host, 5).count);
    // Traffic flows both ways on the new socket.
    ASSERT_EQ(t->send(packet_of(proto::Heartbeat{9})), ResultCode::ok);
    ASSERT_TRUE(eventually([&] { return t->counters().sent == 1; }));
    CanPacketCodec device(CanRole::device, 5, false);
    bus->inject(encode(device, sample_status())[0]);
    EXPECT_EQ(receive_all(*t, 1).size(), 1U);
  }
}

TEST(CanTransport, KernelWithoutCanSaysSoPlainly) {
  auto bus = std::make_shared<FakeCan>();
  bus->socket_error = EAFNOSUPPORT;
  try {
    (void)open_on(bus, "can://can0?node=1");
    FAIL() << "opened without CAN";
  } catch (const DeviceNotFound& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("no CAN support"), std::string::npos) << what;
    EXPECT_NE(what.find("modprobe can_raw"), std::string::npos) << what;
    EXPECT_NE(what.find("VM"), std::string::npos) << what;
  }
  const std::vector<DeviceListing> listed = list_can_devices(*bus, milliseconds(10));
  ASSERT_EQ(listed.size(), 1U);
  EXPECT_EQ(listed[0].bus, "can");
  EXPECT_NE(listed[0].problem.find("no CAN support"), std::string::npos);
  EXPECT_NE(listed[0].fix.find("modprobe can_raw"), std::string::npos);
  bus->socket_error = EACCES;
  EXPECT_THROW((void)open_on(bus, "can://can0?node=1"), PermissionDenied);
}

TEST(CanTransport, MissingOrDownInterfaceSaysHowToBringOneUp) {
  auto bus = std::make_shared<FakeCan>();
  try {
    (void)open_on(bus, "can://can0?node=1");
    FAIL() << "opened a missing interface";
  } catch (const DeviceNotFound& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("no network interface 'can0'"), std::string::npos) << what;
    EXPECT_NE(what.find("CAN interfaces here: vcan0"), std::string::npos) << what;
    EXPECT_NE(what.find("ip link add dev vcan0 type vcan"), std::string::npos) << what;
    EXPECT_NE(what.find("bitrate 1000000"), std::string::npos) << what;
  }
  bus->interfaces["can0"] = FakeCan::Interface{4, CAN_MTU, false, true};
  try {
    (void)open_on(bus, "can://can0?node=1");
    FAIL() << "opened a down interface";
  } catch (const DeviceNotFound& e) {
    EXPECT_NE(std::string(e.what()).find("sudo ip link set can0 up type can bitrate 1000000"),
              std::string::npos)
        << e.what();
  }
  EXPECT_EQ(bus->open_sockets(), 0U);  // nothing leaked
}

TEST(CanTransport, FdModeNeedsMtu72AndSendsOnePacketPerFrame) {
  auto bus = std::make_shared<FakeCan>();
  try {
    (void)open_on(bus, "can://vcan0?node=5&fd=1");
    FAIL() << "fd=1 on MTU 16";
  } catch (const InvalidArgument& e) {
    EXPECT_NE(std::string(e.what()).find("ip link set vcan0 mtu 72"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("fd on"), std::string::npos) << e.what();
  }
  bus->interfaces["vcan0"].mtu = CANFD_MTU;
  auto t = open_on(bus, "can://vcan0?node=5&fd=1");
  EXPECT_TRUE(bus->last_socket().fd_frames);
  const std::vector<std::uint8_t> p = packet_of(valves(0, 12, 3000), 0x44);
  ASSERT_EQ(t->send(p), ResultCode::ok);
  ASSERT_TRUE(eventually([&] { return t->counters().sent == 1; }));
  const auto written = bus->written_frames();
  ASSERT_EQ(written.size(), 1U);
  EXPECT_TRUE(written[0].fd);
  EXPECT_EQ(written[0].id, 0x405U);
  EXPECT_EQ(written[0].length, proto::canfd_padded_length(p.size()));
  EXPECT_TRUE(std::equal(p.begin(), p.end(), written[0].data.begin()));
  // The device's packets come back with their own sequence; so does the heartbeat echo.
  CanPacketCodec device(CanRole::device, 5, true);
  for (const auto& [m, seq] : std::vector<std::pair<proto::Message, std::uint8_t>>{
           {telemetry(99, 0, 12), 0x10}, {proto::Heartbeat{4}, 0x11}, {sample_identity(), 0x13}}) {
    for (const proto::CanFrame& f : encode(device, m, seq)) {
      bus->inject(f);
    }
  }
  const auto got = receive_all(*t, 3);
  ASSERT_EQ(got.size(), 3U);
  EXPECT_EQ(got[0].message, proto::Message(telemetry(99, 0, 12)));
  EXPECT_EQ(got[0].sequence, 0x10);
  EXPECT_EQ(got[1].message, proto::Message(proto::Heartbeat{4}));
  EXPECT_EQ(got[2].sequence, 0x13);
}

TEST(CanTransport, DeviceRoleTransportIsTheOtherEndOfTheBus) {
  for (const bool fd : {false, true}) {
    auto bus = std::make_shared<FakeCan>();
    bus->interfaces["vcan0"].mtu = fd ? CANFD_MTU : CAN_MTU;
    const std::string uri = fd ? "can://vcan0?node=2&fd=1" : "can://vcan0?node=2";
    auto host = open_on(bus, uri);
    CanTransportOptions o = fast_options();
    o.role = CanRole::device;
    auto device = open_on(bus, uri, o);
    ASSERT_EQ(host->send(packet_of(proto::IdentifyRequest{}, 1)), ResultCode::ok);
    ASSERT_EQ(host->send(packet_of(valves(0, 12, 300), 2)), ResultCode::ok);
    const auto at_device = receive_all(*device, fd ? 2 : 4);  // classic: one packet per valve block
    ASSERT_EQ(at_device.size(), fd ? 2U : 4U);
    EXPECT_EQ(at_device[0].message, proto::Message(proto::IdentifyRequest{}));
    EXPECT_EQ(std::get<proto::ValveCurrents>(at_device[1].message).counts[0], 300);
    EXPECT_EQ(device->send(packet_of(valves(0, 1, 0))),
              ResultCode::invalid_value);  // not its direction
    ASSERT_EQ(device->send(packet_of(sample_identity(), 7)), ResultCode::ok);
    ASSERT_EQ(device->send(packet_of(telemetry(42, 0, 12), 8)), ResultCode::ok);
    const auto at_host = receive_all(*host, fd ? 2 : 4);
    ASSERT_EQ(at_host.size(), fd ? 2U : 4U);
    EXPECT_EQ(at_host[0].message, sample_identity());
    EXPECT_EQ(std::get<proto::Telemetry>(at_host[1].message).device_time_us, 42U);
    // The heartbeat echo: a frame on CAN FD, none on classic CAN.
    ASSERT_EQ(device->send(packet_of(proto::Heartbeat{5}, 9)), ResultCode::ok);
    ASSERT_TRUE(eventually([&] { return device->counters().sent + stats_of(*device).dropped_packets == 3; }));
    EXPECT_EQ(stats_of(*device).dropped_packets, fd ? 0U : 1U);
    if (fd) {
      const auto echo = receive_all(*host, 1);
      ASSERT_EQ(echo.size(), 1U);
      EXPECT_EQ(echo[0].message, proto::Message(proto::Heartbeat{5}));
    }
    EXPECT_EQ(host->counters().malformed, 0U);
    EXPECT_EQ(device->counters().malformed, 0U);
  }
}

TEST(CanTransport, NoAllocationPerFrameOnEitherSide) {
  auto bus = std::make_shared<FakeCan>();
  auto t = open_on(bus, "can://vcan0?node=5");
  CanPacketCodec device(CanRole::device, 5, false);
  const std::vector<std::uint8_t> currents = packet_of(valves(0, 12, 100));
  const std::vector<proto::CanFrame> sample = encode(device, telemetry(1, 0, 12));
  const auto settled = [&](std::uint64_t sent, std::uint64_t read) {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(20);
    while ((t->counters().sent < sent || stats_of(*t).frames_read < read) &&
           std::chrono::steady_clock::now() < deadline) {
      std::this_thread::yield();
    }
    Datagram d;
    while (t->receive(d) == ResultCode::ok) {
    }
  };
  // Warm up: the fake's buffers reach their capacity.
  ASSERT_EQ(t->send(currents), ResultCode::ok);
  for (const proto::CanFrame& f : sample) {
    bus->inject(f);
  }
  settled(1, sample.size());
  const std::uint64_t before = test::allocation_count();
  constexpr int kRounds = 300;
  for (int i = 0; i < kRounds; ++i) {
    while (t->send(currents) == ResultCode::would_block) {
      std::this_thread::yield();
    }
    for (const proto::CanFrame& f : sample) {
      bus->inject(f);
    }
  }
  settled(1 + kRounds, (1 + kRounds) * sample.size());
  const std::uint64_t allocations = test::allocation_count() - before;
  EXPECT_EQ(t->counters().sent, 1U + kRounds);
  EXPECT_EQ(bus->written_count(), 3U * (1 + kRounds));
  EXPECT_EQ(allocations, 0U);
}

// ================================================================================= the session

// The simulated node: the device role of the codec in front of the mock's firmware. Runs under
// the bus's lock (from the transport's writes and from the test thread's steps).
class SimNode {
 public:
  SimNode(FakeCan& bus, sim::MockDevice& mock, const Clock& clock, std::uint8_t node, bool fd)
      : bus_(bus), codec_(CanRole::device, node, fd), link_(mock.connect(true, &clock)) {}
  void on_host_frame(const proto::CanFrame& f) {
    if (drop && drop(f)) {
      return;  // lost on the bus
    }
    const CanPacketCodec::Decoded d = codec_.decode(f);
    if (d.complete) {
      (void)link_->send(std::span<const std::uint8_t>(d.packet.bytes.data(), d.packet.length));
    }
    pump();
  }
  // The firmware's answers and telemetry onto the bus.
  void pump() {
    Datagram d;
    std::array<proto::CanFrame, CanPacketCodec::kMaxFrames> frames{};
    while (link_->receive(d) == ResultCode::ok) {
      const CanPacketCodec::Encoded e =
          codec_.encode(std::span<const std::uint8_t>(d.bytes.data(), d.length), frames);
      EXPECT_EQ(e.error, proto::Error::ok);
      for (std::size_t i = 0; i < e.frames; ++i) {
        bus_.inject_locked(frames[i]);
      }
    }
  }
  [[nodiscard]] const CanPacketCodec& codec() const noexcept { return codec_; }
  std::function<bool(const proto::CanFrame&)> drop;  // host frames the bus loses

 private:
  FakeCan& bus_;
  CanPacketCodec codec_;
  std::unique_ptr<Transport> link_;
};

// Counts the datagrams the session handed over, so the test knows when the bus is idle.
class CountingTransport final : public Transport {
 public:
  explicit CountingTransport(std::unique_ptr<Transport> inner) : inner_(std::move(inner)) {}
  ResultCode send(std::span<const std::uint8_t> bytes) noexcept override {
    const ResultCode rc = inner_->send(bytes);
    taken_.fetch_add(rc == ResultCode::ok ? 1 : 0);
    return rc;
  }
  ResultCode receive(Datagram& out) noexcept override { return inner_->receive(out); }
  [[nodiscard]] TransportState state() const noexcept override { return inner_->state(); }
  [[nodiscard]] std::string_view uri() const noexcept override { return inner_->uri(); }
  [[nodiscard]] TransportCounters counters() const noexcept override { return inner_->counters(); }
  [[nodiscard]] const Transport& inner() const noexcept { return *inner_; }
  [[nodiscard]] std::uint64_t taken() const noexcept { return taken_.load(); }

 private:
  std::unique_ptr<Transport> inner_;
  std::atomic<std::uint64_t> taken_{0};
};

// Simulated time that moves only once the CAN path has gone quiet: every datagram the session
// handed over is on the bus, and every frame on the bus has been read and handled.
class LockstepClock final : public Clock {
 public:
  [[nodiscard]] TimePoint now() const noexcept override { return sim.now(); }
  void sleep_until(TimePoint t) noexcept override {
    settle();
    sim.sleep_until(t);
  }
  void settle() const noexcept {
    if (!idle) {
      return;
    }
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(20);
    while (!idle() && std::chrono::steady_clock::now() < deadline) {
      std::this_thread::yield();
    }
  }
  SimulatedClock sim;
  std::function<bool()> idle;
};

struct CanRig {
  explicit CanRig(bool fd, SessionOptions options = {}) : bus(std::make_shared<FakeCan>()) {
    bus->interfaces["vcan0"].mtu = fd ? CANFD_MTU : CAN_MTU;
    sim::MockOptions mo;
    mo.seed = 11;
    mock = sim::MockDevice::make(mo);
    node = std::make_unique<SimNode>(*bus, *mock, clock, 3, fd);
    bus->on_write = [this](const proto::CanFrame& f) { node->on_host_frame(f); };
    auto wrapper = std::make_unique<CountingTransport>(
        open_on(bus, fd ? "can://vcan0?node=3&fd=1" : "can://vcan0?node=3"));
    CountingTransport* c = wrapper.get();
    counting = c;
    clock.idle = [this, c] {
      const TransportCounters tc = c->inner().counters();
      const CanTransportStats s = stats_of(c->inner());
      return tc.sent + s.dropped_packets == c->taken() && bus->drained() &&
             bus->read_count() == s.frames_read;
    };
    session = std::make_unique<DeviceSession>(std::move(wrapper), clock, options);
  }
  ~CanRig() {
    session.reset();
    const std::lock_guard lock(bus->mu);
    bus->on_write = nullptr;
  }
  CanRig(const CanRig&) = delete;
  CanRig& operator=(const CanRig&) = delete;
  CanRig(CanRig&&) = delete;
  CanRig& operator=(CanRig&&) = delete;

  void run(int ms) {
    for (int k = 0; k < ms; ++k) {
      {
        const std::lock_guard lock(bus->mu);
        mock->set_finger_indentation(finger);
        mock->step(clock.now());
        node->pump();
      }
      clock.settle();
      if (session->poll(clock.now()) == ResultCode::ok && !currents.empty()) {
        (void)session->send_valve_currents(currents);
      }
      clock.settle();
      clock.sim.advance(milliseconds(1));
    }
  }

  LockstepClock clock;
  std::shared_ptr<FakeCan> bus;
  std::shared_ptr<sim::MockDevice> mock;
  std::unique_ptr<SimNode> node;
  std::unique_ptr<DeviceSession> session;
  const CountingTransport* counting = nullptr;
  std::vector<double> currents;
  std::vector<double> finger;
};

class CanSession : public ::testing::TestWithParam<bool> {};

TEST_P(CanSession, HandshakeEnableCurrentsAndTelemetryOverTheBus) {
  const bool fd = GetParam();
  CanRig rig(fd);
  const DeviceInfo& info = rig.session->info();
  EXPECT_EQ(info.serial, 0x4D520001U);
  EXPECT_EQ(info.rows, 5);
  EXPECT_EQ(info.valves, 12U);
  EXPECT_EQ(info.sensors, 12U);
  ASSERT_NE(rig.session->profile(), nullptr);
  EXPECT_EQ(rig.session->profile()->name, "mr-skin-5x5");
  rig.finger.assign(rig.mock->layout().fluid_cell_count(), 0.0);
  rig.finger[6] = 1e-3;  // the centre cell, pressed 1 mm
  rig.run(20);
  EXPECT_EQ(rig.session->state(), DeviceState::disabled);
  ASSERT_EQ(rig.session->request_enable(), ResultCode::ok);
  rig.currents.assign(info.valves, 0.05);
  rig.run(60);
  EXPECT_EQ(rig.session->state(), DeviceState::enabled);
  std::vector<double> applied(info.valves);
  rig.mock->applied_currents(applied);
  for (const double a : applied) {
    EXPECT_NEAR(a, 0.05, 1e-4);
  }
  const SessionCounters& c = rig.session->counters();
  EXPECT_GE(c.telemetry, 60U);
  EXPECT_EQ(c.decode_errors, 0U);
  EXPECT_EQ(c.sequence_gaps, 0U);
  EXPECT_EQ(c.duplicates, 0U);
  EXPECT_EQ(c.telemetry_timeouts, 0U);
  EXPECT_GT(rig.session->sensor_device_time_us(), 0U);
  const auto sensors = rig.session->sensors();
  EXPECT_TRUE(std::any_of(sensors.begin(), sensors.end(), [](double s) { return s > 1e-4; }));
  if (fd) {
    EXPECT_GT(c.round_trip.count(), 0U);  // heartbeat echoes on CAN FD
  } else {
    EXPECT_EQ(c.round_trip.count(), 0U);  // none on classic CAN
  }
  const TransportCounters tc = rig.counting->counters();
  EXPECT_EQ(tc.malformed, 0U);
  EXPECT_EQ(tc.send_would_block, 0U);
  EXPECT_EQ(tc.receive_overruns, 0U);
}

INSTANTIATE_TEST_SUITE_P(ClassicAndFd, CanSession, ::testing::Values(false, true),
                         [](const ::testing::TestParamInfo<bool>& i) { return i.param ? "fd" : "classic"; });

// Protocol 1.2's delta blocks over real frames both ways (the transport's codec and the unit's):
// with only valve 0 changing, a 1.2 host sends its block every tick and the other two every 10th,
// against every block every tick from a 1.1 host; the unit holds the commanded currents either
// way, and a lost frame heals at the block's refresh.
TEST(CanDelta, OnlyChangedBlocksGoAndALostFrameHealsAtTheRefresh) {
  std::uint64_t valve_frames[2] = {0, 0};
  for (const std::uint8_t minor : {std::uint8_t{2}, std::uint8_t{1}}) {
    SCOPED_TRACE(static_cast<int>(minor));
    SessionOptions options;
    options.protocol_minor = minor;
    // Written by the transport's I/O thread (under the bus's lock), read here: declared before the
    // rig, which outlives them otherwise.
    std::atomic<std::uint64_t> frames{0};
    std::atomic<bool> lose_block2{false};
    std::atomic<bool> lost{false};
    CanRig rig(false, options);
    const std::size_t valves = rig.session->info().valves;
    ASSERT_EQ(valves, 12U);
    ASSERT_EQ(rig.session->request_enable(), ResultCode::ok);
    {
      const std::lock_guard lock(rig.bus->mu);
      rig.node->drop = [&frames, &lose_block2, &lost](const proto::CanFrame& f) {
        if ((f.id >> 8U) != static_cast<unsigned>(proto::CanFunction::valve_block)) {
          return false;
        }
        frames.fetch_add(1);
        // Block 2 (valves 8..11) at the tick valve 8 changes: lost once.
        if (((f.id >> 4U) & 0xFU) == 2 && lose_block2.exchange(false)) {
          lost = true;
          return true;
        }
        return false;
      };
    }
    std::vector<double> commanded(valves, 0.0);
    std::vector<double> applied(valves);
    int wrong_ticks = 0;
    for (int k = 0; k < 200; ++k) {
      rig.currents.assign(valves, 0.04);
      rig.currents[0] = 0.001 * (k % 20);        // block 0 changes every tick
      rig.currents[8] = k >= 100 ? 0.06 : 0.04;  // block 2 changes once, at tick 100
      if (k == 100) {
        lose_block2 = true;  // the frame that carries the change is lost
      }
      rig.run(1);
      rig.mock->applied_currents(applied);
      if (k >= 10) {  // what the unit applies at a step is what it was sent the tick before
        bool right = true;
        for (std::size_t v = 0; v < valves; ++v) {
          right = right && std::abs(applied[v] - commanded[v]) < 1e-4;
        }
        wrong_ticks += right ? 0 : 1;
      }
      commanded = rig.currents;
    }
    {
      const std::lock_guard lock(rig.bus->mu);
      EXPECT_EQ(rig.node->codec().delta_blocks(), minor == 2);
    }
    valve_frames[minor == 2 ? 0 : 1] = frames.load();
    ASSERT_TRUE(lost.load());
    if (minor == 2) {
      // Block 2 is wrong from the lost frame to its refresh: at most 10 updates.
      EXPECT_GE(wrong_ticks, 1);
      EXPECT_LE(wrong_ticks, static_cast<int>(proto::kCanDeltaRefreshUpdates));
    } else {
      EXPECT_EQ(wrong_ticks, 1);  // the next tick sends every block again
    }
    EXPECT_EQ(rig.session->state(), DeviceState::enabled);
    EXPECT_EQ(rig.session->counters().decode_errors, 0U);
  }
  // 200 ticks: 1.1 sends 3 valve frames a tick; 1.2 one, plus two refreshes every 10 ticks.
  EXPECT_GE(valve_frames[1], 3U * 200U);
  EXPECT_LE(valve_frames[0], 200U + 2U * 20U + 10U);
  EXPECT_GE(valve_frames[0], 200U + 2U * 18U);
}

// ================================================================================= listing

TEST(CanList, ListsTheNodesThatAnswerAndInterfacesThatAreDown) {
  auto bus = std::make_shared<FakeCan>();
  bus->interfaces["can1"] = FakeCan::Interface{4, CAN_MTU, false, true};
  SimulatedClock clock;
  auto mock = sim::MockDevice::make(sim::MockOptions{});
  SimNode node(*bus, *mock, clock, 3, false);
  bus->on_write = [&node](const proto::CanFrame& f) { node.on_host_frame(f); };
  const std::vector<DeviceListing> listed = list_can_devices(*bus, milliseconds(200));
  {
    const std::lock_guard lock(bus->mu);
    bus->on_write = nullptr;
  }
  ASSERT_EQ(listed.size(), 2U);
  EXPECT_EQ(listed[0].path, "can1");
  EXPECT_EQ(listed[0].problem, "interface is down");
  EXPECT_EQ(listed[0].fix, "sudo ip link set can1 up type can bitrate 1000000");
  EXPECT_EQ(listed[1].bus, "can");
  EXPECT_EQ(listed[1].uri, "can://vcan0?node=3");
  EXPECT_EQ(listed[1].path, "vcan0");
  EXPECT_EQ(listed[1].serial, "4D520001");
  EXPECT_EQ(listed[1].protocol, "1." + std::to_string(protocol::kVersionMinor));
  EXPECT_FALSE(listed[1].firmware.empty());
  EXPECT_TRUE(listed[1].problem.empty());
  EXPECT_EQ(bus->open_sockets(), 0U);
}

}  // namespace
}  // namespace mrskin
