#include "mrskin/protocol/bus_budget.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <vector>

#include "mrskin/protocol/can.hpp"
#include "mrskin/protocol/messages.hpp"
#include "mrskin/protocol/packet.hpp"

namespace mrskin::protocol {
namespace {

constexpr std::uint8_t kBudgetNode = 1;
// Classic CAN blocks hold 4 values and a message's first value must start a block: chunks of 24
// (the largest multiple of 4 within both packets' counts) give the same frames as any split.
constexpr std::size_t kCanChunk = 24;

// The messages of one full update of n values (valve currents or sensor readings), chunked as a
// sender splits them.
std::vector<Message> full_update(bool currents, std::size_t n, std::size_t chunk) {
  std::vector<Message> out;
  for (std::size_t first = 0; first < n; first += chunk) {
    const auto count = static_cast<std::uint8_t>(std::min(chunk, n - first));
    if (currents) {
      ValveCurrents m;
      m.first = static_cast<std::uint16_t>(first);
      m.count = count;
      out.emplace_back(m);
    } else {
      Telemetry m;
      m.first = static_cast<std::uint16_t>(first);
      m.count = count;
      out.emplace_back(m);
    }
  }
  return out;
}

// What sending a group of messages at one instant costs on the bus.
struct Cost {
  double units = 0.0;  // reports or frames
  double bytes = 0.0;
  double time_s = 0.0;  // CAN: bus time
  bool ok = true;
};

Cost& operator+=(Cost& a, const Cost& b) {
  a.units += b.units;
  a.bytes += b.bytes;
  a.time_s += b.time_s;
  a.ok = a.ok && b.ok;
  return a;
}

Cost scaled(Cost c, double per_s) {
  c.units *= per_s;
  c.bytes *= per_s;
  c.time_s *= per_s;
  return c;
}

// Packets (the encoder's sizes) into reports or FD frames of `room` bytes: one each, or packed
// back to back in order (a packet that does not fit starts the next).
Cost packet_cost(const BusSpec& bus, const std::vector<Message>& group, bool packed) {
  Cost c;
  const bool fd = bus.kind == BusKind::can_fd;
  const std::size_t room = fd ? kPacketMaxBytes : bus.usb.report_bytes;
  std::array<std::uint8_t, kPacketMaxBytes> buffer{};
  std::vector<std::size_t> containers;  // bytes in each report or frame
  for (const Message& m : group) {
    const EncodeResult r = encode_packet(m, 0, buffer);
    if (r.error != Error::ok) {
      c.ok = false;
      return c;
    }
    c.bytes += static_cast<double>(r.bytes);
    if (packed && !containers.empty() && containers.back() + r.bytes <= room) {
      containers.back() += r.bytes;
    } else {
      containers.push_back(r.bytes);
    }
  }
  c.units = static_cast<double>(containers.size());
  if (fd) {
    for (const std::size_t bytes : containers) {
      c.time_s += can_frame_time_worst_case_s(canfd_padded_length(bytes), true, bus.nominal_bitrate_bit_per_s,
                                              bus.data_bitrate_bit_per_s);
    }
  }
  return c;
}

// Classic CAN: the frames encode_can writes (and a TimeSync before each Telemetry).
Cost classic_cost(const BusSpec& bus, const std::vector<Message>& group) {
  Cost c;
  std::array<CanFrame, kCanMaxFramesPerMessage> frames{};
  for (const Message& m : group) {
    std::vector<Message> sent;
    if (const auto* t = std::get_if<Telemetry>(&m); t != nullptr && t->first == 0) {
      sent.emplace_back(TimeSync{});
    }
    sent.push_back(m);
    for (const Message& s : sent) {
      const CanEncodeResult r = encode_can(s, kBudgetNode, 0, 0, frames);
      if (r.error != Error::ok) {
        c.ok = false;
        return c;
      }
      for (std::size_t i = 0; i < r.frames; ++i) {
        c.units += 1.0;
        c.bytes += frames.at(i).length;
        c.time_s += can_frame_time_worst_case_s(frames.at(i).length, false, bus.nominal_bitrate_bit_per_s,
                                                bus.data_bitrate_bit_per_s);
      }
    }
  }
  return c;
}

Cost group_cost(const BusSpec& bus, const std::vector<Message>& group, bool packed) {
  return bus.kind == BusKind::can_classic ? classic_cost(bus, group) : packet_cost(bus, group, packed);
}

std::vector<Message> with(std::vector<Message> group, const Message& extra) {
  group.push_back(extra);
  return group;
}

// A cyclic group at rate_hz with extras at their own rates: each extra rides along with a
// different cycle (the worst case: none share one), or alone when there are more extras than cycles.
Cost per_second(const BusSpec& bus, const std::vector<Message>& cyclic, double rate_hz,
                const std::vector<std::pair<Message, double>>& extras, bool packed) {
  Cost total;
  double riding_hz = 0.0;
  for (const auto& [m, hz] : extras) {
    const double along_hz = std::min(hz, std::max(0.0, rate_hz - riding_hz));
    riding_hz += along_hz;
    total += scaled(group_cost(bus, with(cyclic, m), packed), along_hz);
    total += scaled(group_cost(bus, {m}, packed), hz - along_hz);
  }
  total += scaled(group_cost(bus, cyclic, packed), rate_hz - riding_hz);
  return total;
}

DirectionLoad load_of(const BusSpec& bus, const Cost& c) {
  DirectionLoad d;
  d.units_per_s = c.units;
  d.bytes_per_s = c.bytes;
  if (bus.kind == BusKind::hid_full_speed || bus.kind == BusKind::hid_high_speed) {
    d.load = c.bytes / usb_report_bytes_per_s(bus.usb);
    d.slot_fraction = c.units / usb_reports_per_s(bus.usb);
  } else {
    d.load = c.time_s;
    d.slot_fraction = c.time_s;
  }
  return d;
}

}  // namespace

const char* to_string(BusKind kind) noexcept {
  switch (kind) {
    case BusKind::hid_full_speed:
      return "hid-fs";
    case BusKind::hid_high_speed:
      return "hid-hs";
    case BusKind::can_classic:
      return "can";
    case BusKind::can_fd:
      return "canfd";
  }
  return "?";
}

BusSpec default_bus_spec(BusKind kind, bool packed) noexcept {
  BusSpec s;
  s.kind = kind;
  s.usb = kind == BusKind::hid_high_speed ? kUsbHighSpeedMaxSlots : kUsbFullSpeedSlots;
  if (kind == BusKind::hid_high_speed && !packed) {
    s.usb.report_bytes = kHidReportBytes;
  }
  return s;
}

double BusBudget::load() const noexcept {
  if (!encodable) {
    return INFINITY;
  }
  return one_bus ? host_to_device.load + device_to_host.load
                 : std::max(host_to_device.load, device_to_host.load);
}

bool BusBudget::fits(double max_load) const noexcept {
  const bool slots = one_bus || (host_to_device.slot_fraction <= 1.0 && device_to_host.slot_fraction <= 1.0);
  return encodable && slots && load() <= max_load;
}

BusBudget compute_bus_budget(const BusSpec& bus, const CyclicTraffic& traffic) noexcept {
  BusBudget b;
  try {
    const bool classic = bus.kind == BusKind::can_classic;
    const std::size_t valve_chunk = classic ? kCanChunk : kMaxValveCurrents;
    const std::size_t sensor_chunk = classic ? kCanChunk : kMaxTelemetryValues;
    const bool packed = traffic.packed && !classic;
    const Cost h2d = per_second(bus, full_update(true, traffic.valves, valve_chunk), traffic.update_rate_hz,
                                {{Heartbeat{}, traffic.heartbeat_hz}}, packed);
    // Classic CAN has no heartbeat echo (docs/protocol.md, "Heartbeat").
    std::vector<std::pair<Message, double>> extras{{Status{}, traffic.status_hz}};
    if (!classic) {
      extras.emplace_back(Heartbeat{}, traffic.heartbeat_hz);
    }
    const Cost d2h = per_second(bus, full_update(false, traffic.sensors, sensor_chunk),
                                traffic.telemetry_rate_hz, extras, packed);
    if (!h2d.ok || !d2h.ok) {
      b.encodable = false;
      b.why_not = classic ? "classic CAN addresses at most 64 valves and 64 sensors a node"
                          : "a value count beyond what the packets address";
      return b;
    }
    b.one_bus = classic || bus.kind == BusKind::can_fd;
    b.host_to_device = load_of(bus, h2d);
    b.device_to_host = load_of(bus, d2h);
  } catch (...) {  // std::bad_alloc from the small vectors above: report it as not computable
    b.encodable = false;
    b.why_not = "out of memory";
  }
  return b;
}

double highest_update_rate_hz(const BusSpec& bus, CyclicTraffic traffic, double max_load) noexcept {
  const auto fits = [&](double hz) {
    traffic.update_rate_hz = hz;
    return compute_bus_budget(bus, traffic).fits(max_load);
  };
  if (!fits(1.0)) {
    return 0.0;
  }
  double lo = 1.0;
  double hi = 1.0;
  while (hi < 1e6 && fits(hi * 2.0)) {
    hi *= 2.0;
  }
  hi *= 2.0;
  while (hi - lo > 1.0) {  // fits(lo), !fits(hi)
    const double mid = std::floor((lo + hi) / 2.0);
    (fits(mid) ? lo : hi) = mid;
  }
  return lo;
}

std::size_t config_bytes_beside_telemetry(std::size_t sensors, std::size_t report_bytes) noexcept {
  constexpr std::size_t kFraming = kPacketHeaderBytes + kPacketCrcBytes;
  std::size_t last = 0;  // bytes of the sample's last report, packed as the unit packs them
  for (std::size_t first = 0; first < sensors; first += kMaxTelemetryValues) {
    Telemetry t;
    t.count = static_cast<std::uint8_t>(std::min(kMaxTelemetryValues, sensors - first));
    const std::size_t bytes = kFraming + packet_payload_length(Message{t});
    last = last > 0 && last + bytes <= report_bytes ? last + bytes : bytes;
  }
  const std::size_t reply_framing = kFraming + packet_payload_length(Message{ConfigData{}});
  if (last + reply_framing >= report_bytes) {
    return 0;
  }
  return std::min(kMaxConfigBytes, report_bytes - last - reply_framing);
}

}  // namespace mrskin::protocol
