// The device of a running mrskin-bridged, leased over its control socket ("lease" request): the
// daemon disables the bridge, keeps its tick off the device and carries the device's datagrams
// over this connection, a two-byte little-endian length then the bytes, both ways, until the connection
// closes (the bridge then stays halted until enabled). A DeviceSession on it is an ordinary session, so set,
// selftest and calibrate run through the daemon as on a free device (without the mock's press fixture: it
// lives in the daemon's process).
#pragma once

#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <chrono>
#include <cstdint>
#include <cstring>
#include <optional>
#include <span>
#include <string>
#include <string_view>

#include "bridge_client.hpp"
#include "lease_framing.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/transport.hpp"
#include "mrskin/protocol/bus_budget.hpp"

namespace mrskin::ctl {

class TunnelTransport final : public Transport {
 public:
  // Throws DeviceNotFound (no daemon, exit 3), DeviceBusy (the daemon refused the lease: another
  // client holds it, or the bridge did not halt; exit 5) or Error (no answer).
  explicit TunnelTransport(const std::string& socket_path) : uri_("bridge:" + socket_path) {
    using namespace std::chrono_literals;
    LineClient c = connect_bridge(socket_path);
    const std::optional<std::string> ack = c.request(R"({"cmd":"lease"})", 5s);
    if (!ack) {
      throw Error(fmt::format("mrskin-bridged on {} did not answer the device lease request within 5 s",
                              socket_path));
    }
    const JsonReply reply(*ack);
    if (reply.text("ok") != "true") {
      throw DeviceBusy(fmt::format("mrskin-bridged on {} refused the device lease: {}", socket_path,
                                   reply.text("error").value_or(*ack)));
    }
    if (const std::optional<std::string> framing = reply.text("framing"); framing != tools::kLeaseFraming) {
      throw Error(fmt::format(
          "mrskin-bridged on {} frames its device lease as '{}', this mrskinctl as '{}': use mrskinctl "
          "and mrskin-bridged of the same mrskin release",
          socket_path, framing.value_or("(not said: an older daemon, one length byte)"),
          tools::kLeaseFraming));
    }
    bus_ = bus_of(reply);
    auto [fd, rest] = c.release();
    fd_ = fd;
    const std::size_t n = std::min(rest.size(), in_.size());
    std::memcpy(in_.data(), rest.data(), n);
    in_length_ = n;
  }
  TunnelTransport(const TunnelTransport&) = delete;
  TunnelTransport& operator=(const TunnelTransport&) = delete;
  TunnelTransport(TunnelTransport&&) = delete;
  TunnelTransport& operator=(TunnelTransport&&) = delete;
  ~TunnelTransport() override {
    if (fd_ >= 0) {
      ::close(fd_);  // ends the lease
    }
  }

  ResultCode send(std::span<const std::uint8_t> bytes) noexcept override {
    if (bytes.empty() || bytes.size() > kMaxDatagramBytes) {
      return ResultCode::invalid_value;
    }
    if (fd_ < 0) {
      return ResultCode::disconnected;
    }
    // The lease's framing: the length (u16, little-endian), then the bytes (docs/daemon.md).
    std::array<std::uint8_t, kMaxDatagramBytes + 2> frame{};
    frame[0] = static_cast<std::uint8_t>(bytes.size() & 0xFFU);
    frame[1] = static_cast<std::uint8_t>(bytes.size() >> 8U);
    std::copy(bytes.begin(), bytes.end(), frame.begin() + 2);
    const std::size_t total = bytes.size() + 2;
    std::size_t done = 0;
    // A frame is never left half-written (it would shift every frame after it): a full socket
    // buffer is waited out for up to 100 ms, then the lease counts as lost.
    while (done < total) {
      const ssize_t n = ::send(fd_, frame.data() + done, total - done, MSG_NOSIGNAL | MSG_DONTWAIT);
      if (n > 0) {
        done += static_cast<std::size_t>(n);
        continue;
      }
      if (n < 0 && errno == EINTR) {
        continue;
      }
      pollfd p{fd_, POLLOUT, 0};
      if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK) && ::poll(&p, 1, 100) > 0) {
        continue;
      }
      lost();
      return ResultCode::disconnected;
    }
    ++counters_.sent;
    return ResultCode::ok;
  }

  ResultCode receive(Datagram& out) noexcept override {
    if (fd_ >= 0 && in_length_ < in_.size()) {
      const ssize_t n = ::recv(fd_, in_.data() + in_length_, in_.size() - in_length_, MSG_DONTWAIT);
      if (n > 0) {
        in_length_ += static_cast<std::size_t>(n);
      } else if (n == 0 || (errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR)) {
        lost();  // the daemon closed the lease (it stopped, or dropped us)
      }
    }
    if (in_length_ < 2) {
      return fd_ < 0 ? ResultCode::disconnected : ResultCode::would_block;
    }
    const std::size_t length = in_[0] | (static_cast<std::size_t>(in_[1]) << 8U);
    if (length == 0 || length > kMaxDatagramBytes) {
      ++counters_.malformed;
      lost();
      in_length_ = 0;
      return ResultCode::disconnected;
    }
    if (in_length_ < 2 + length) {
      return fd_ < 0 ? ResultCode::disconnected : ResultCode::would_block;
    }
    std::copy_n(in_.begin() + 2, length, out.bytes.begin());
    out.length = static_cast<std::uint16_t>(length);
    std::memmove(in_.data(), in_.data() + 2 + length, in_length_ - 2 - length);
    in_length_ -= 2 + length;
    ++counters_.received;
    return ResultCode::ok;
  }

  [[nodiscard]] TransportState state() const noexcept override {
    return fd_ >= 0 ? TransportState::open : TransportState::disconnected;
  }
  [[nodiscard]] std::string_view uri() const noexcept override { return uri_; }
  // The daemon's device's bus, as its lease answer declares it (none from an older daemon).
  [[nodiscard]] std::optional<protocol::BusSpec> bus() const noexcept override { return bus_; }
  [[nodiscard]] TransportCounters counters() const noexcept override { return counters_; }

 private:
  void lost() noexcept {
    if (fd_ >= 0) {
      ::close(fd_);
      fd_ = -1;
      ++counters_.disconnects;
    }
  }

  static std::optional<protocol::BusSpec> bus_of(const JsonReply& reply) {
    const std::optional<std::string> kind = reply.text("bus");
    for (std::size_t k = 0; kind && k < protocol::kBusKindCount; ++k) {
      const auto candidate = static_cast<protocol::BusKind>(k);
      if (*kind != protocol::to_string(candidate)) {
        continue;
      }
      protocol::BusSpec b = protocol::default_bus_spec(candidate);
      const auto positive = [&](std::string_view key, double fallback) {
        const std::optional<double> v = reply.number(key);
        return v && *v > 0.0 && *v < 1e12 ? *v : fallback;
      };
      b.usb.interval_s = positive("bus_usb_interval_s", b.usb.interval_s);
      b.usb.reports_per_interval = static_cast<std::size_t>(
          positive("bus_usb_reports_per_interval", static_cast<double>(b.usb.reports_per_interval)));
      b.usb.report_bytes = static_cast<std::size_t>(
          std::min(positive("bus_usb_report_bytes", static_cast<double>(b.usb.report_bytes)),
                   static_cast<double>(protocol::kUsbHighSpeedMaxReportBytes)));
      b.nominal_bitrate_bit_per_s = positive("bus_nominal_bitrate_bit_per_s", b.nominal_bitrate_bit_per_s);
      b.data_bitrate_bit_per_s = positive("bus_data_bitrate_bit_per_s", b.data_bitrate_bit_per_s);
      return b;
    }
    return std::nullopt;
  }

  std::string uri_;
  std::optional<protocol::BusSpec> bus_;
  int fd_ = -1;
  std::array<std::uint8_t, 8192> in_{};
  std::size_t in_length_ = 0;
  TransportCounters counters_;
};

}  // namespace mrskin::ctl
