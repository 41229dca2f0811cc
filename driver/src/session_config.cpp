// The session's configuration reads: chunked to the bus, several in flight, each retried.
#include <fmt/format.h>

#include <algorithm>
#include <optional>
#include <string>
#include <vector>

#include "mrskin/protocol/bus_budget.hpp"
#include "session_impl.hpp"
#include "session_names.hpp"

namespace mrskin {
namespace proto = mrskin::protocol;
using session_names::config_key_name;
using session_names::config_status_name;

namespace {
constexpr std::size_t kConfigWindow = 16;  // configuration chunks in flight
// Below this many bytes a chunk beside the telemetry costs more round trips than the samples its
// full-size reply would displace are worth: such a unit reads in full chunks.
constexpr std::size_t kMinConfigChunkBeside = 8;
// Classic CAN: a reply of this many bytes is a 41-byte packet, 6 frames (ISO-TP style: 6 + 5 x 7
// bytes), 0.8 ms of a 1 Mbit/s bus, two in flight: a unit's sample waits behind its replies but no
// newer sample replaces it. Measured on the mock's bus (the demo's open in mrskin-bridged): 16
// full replies in flight (144 frames) cost 47 samples, 4 of these 30, 2 none; the open takes
// 0.44 s against 0.26 s (docs/protocol.md, "Configuration reads beside the telemetry").
constexpr std::size_t kClassicCanConfigChunk = 28;
constexpr std::size_t kClassicCanConfigWindow = 2;

bool classic_can(const std::optional<proto::BusSpec>& bus) noexcept {
  return bus && bus->kind == proto::BusKind::can_classic;
}
}  // namespace

std::size_t DeviceSession::Impl::config_window() const {
  return options_.config_reads_beside_telemetry && classic_can(transport_->bus()) ? kClassicCanConfigWindow
                                                                                  : kConfigWindow;
}

std::size_t DeviceSession::Impl::config_chunk_bytes() const {
  const std::optional<proto::BusSpec> bus = transport_->bus();
  if (options_.config_reads_beside_telemetry && classic_can(bus)) {
    return kClassicCanConfigChunk;
  }
  if (!options_.config_reads_beside_telemetry || !packing_ || !bus || bus->kind == proto::BusKind::can_fd) {
    return proto::kMaxConfigBytes;
  }
  // The slots the unit declared (1.2's UsbSlots), else the transport's. A bus with a spare slot
  // for each sample carries full replies in slots of their own.
  const proto::UsbInterruptSlots usb = info_.usb_slots ? *info_.usb_slots : bus->usb;
  const double slots_hz = static_cast<double>(usb.reports_per_interval) / usb.interval_s;
  if (slots_hz >= 2.0 * info_.telemetry_rate_hz) {
    return proto::kMaxConfigBytes;
  }
  const std::size_t beside = proto::config_bytes_beside_telemetry(info_.sensors, usb.report_bytes);
  return beside >= kMinConfigChunkBeside ? beside : proto::kMaxConfigBytes;
}

std::string DeviceSession::Impl::read_config(proto::ConfigKey key) {
  config_ = ConfigTransfer{};
  config_.active = true;
  config_.key = static_cast<std::uint16_t>(key);
  config_.chunk = config_chunk_bytes();
  const std::size_t chunk = config_.chunk;
  const std::size_t window = config_window();
  std::vector<TimePoint> asked;  // per chunk, when last requested (-1: never)
  TimePoint first_asked{-1};
  TimePoint last_progress = clock_.now();
  // Packed (1.2), the requests of one pass share reports: one slot carries several.
  auto request = [&](std::size_t index) {
    proto::ConfigRead r;
    r.key = config_.key;
    r.offset = static_cast<std::uint16_t>(index * chunk);
    r.length = static_cast<std::uint8_t>(chunk);
    (void)send_packet(r, /*hold=*/true);
  };
  for (;;) {
    const TimePoint now = clock_.now();
    if (config_.total < 0) {
      // The first chunk tells the blob's length; ask again until it comes.
      if (first_asked.count() < 0 || now - first_asked >= options_.handshake_retry) {
        request(0);
        first_asked = now;
      }
    } else {
      if (asked.empty()) {
        asked.assign(config_.have.size(), TimePoint{-1});
      }
      std::size_t in_flight = 0;
      for (std::size_t i = 0; i < asked.size(); ++i) {
        in_flight +=
            config_.have[i] == 0 && asked[i].count() >= 0 && now - asked[i] < options_.handshake_retry ? 1U
                                                                                                       : 0U;
      }
      for (std::size_t i = 0; i < asked.size() && in_flight < window; ++i) {
        if (config_.have[i] == 0 && (asked[i].count() < 0 || now - asked[i] >= options_.handshake_retry)) {
          request(i);
          asked[i] = now;
          ++in_flight;
        }
      }
    }
    (void)flush_report();
    Datagram d;
    while (transport_->receive(d) == ResultCode::ok) {
      handle(d, now);
    }
    if (config_.acked && config_.ack_status != static_cast<std::uint8_t>(proto::ConfigStatus::ok)) {
      config_.active = false;
      throw Error(fmt::format("device on {} refused to read its {} (key {}): {}; service the unit",
                              transport_->uri(), config_key_name(config_.key), config_.key,
                              config_status_name(config_.ack_status)));
    }
    if (config_.total >= 0 && config_.received == config_.have.size()) {
      config_.active = false;
      return std::move(config_.text);
    }
    if (config_.progress) {
      config_.progress = false;
      last_progress = now;
    } else if (now - last_progress > options_.handshake_timeout) {
      config_.active = false;
      throw Timeout(fmt::format(
          "device on {} stopped returning its {} ({} of {} bytes after {:.3f} s without progress): check the "
          "link (raise the time scale in slow environments)",
          transport_->uri(), config_key_name(config_.key), config_.received * chunk,
          config_.total < 0 ? std::string("?") : std::to_string(config_.total),
          to_seconds(options_.handshake_timeout)));
    }
    clock_.sleep_until(now + std::chrono::microseconds(200));
  }
}

}  // namespace mrskin
