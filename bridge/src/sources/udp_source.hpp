// udp://HOST:PORT (docs/sources.md). Private to the bridge library.
#pragma once

#include <span>
#include <thread>

#include "core.hpp"

namespace mrskin::bridge::sources {

// A datagram's sample, or why it is dropped (oversized, length, format or crc). Without I/O: used
// by UdpSource and by the fuzzer (tests/fuzz/fuzz_udp.cpp).
struct UdpParsed {
  bool ok = false;
  DropReason reason = DropReason::format;  // when not ok
  UdpSample sample;                        // when ok
};
// d: the bytes received; length: the datagram's real length (it may exceed d's, MSG_TRUNC).
[[nodiscard]] UdpParsed parse_udp_datagram(std::span<const std::uint8_t> d, std::size_t length) noexcept;

class UdpSource final : public QueuedSource {
 public:
  UdpSource(const Endpoint& where, const SourceOptions& options, Clock* clock);
  UdpSource(const UdpSource&) = delete;
  UdpSource& operator=(const UdpSource&) = delete;
  UdpSource(UdpSource&&) = delete;
  UdpSource& operator=(UdpSource&&) = delete;
  ~UdpSource() override;
  [[nodiscard]] std::uint16_t local_port() const noexcept override { return port_; }

 private:
  void run() noexcept;
  // length: the datagram's real length (it may exceed the bytes in d).
  void handle(std::span<const std::uint8_t> d, std::size_t length, TimePoint arrival) noexcept;
  Fd socket_;
  std::uint16_t port_;
  StopSignal stop_;
  OrderGate gate_;
  ClockMapper mapper_;
  std::thread thread_;
};

}  // namespace mrskin::bridge::sources
