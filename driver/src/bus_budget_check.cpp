#include "mrskin/driver/bus_budget_check.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <string>

#include "mrskin/driver/errors.hpp"
#include "mrskin/protocol/messages.hpp"

namespace mrskin {
namespace {

constexpr double kHeartbeat_hz = 50.0;  // SessionOptions::heartbeat_period's 20 ms
constexpr double kStatus_hz = 10.0;     // the firmware's status period

std::string direction_text(const protocol::BusBudget& b, const protocol::DirectionLoad& d) {
  return b.one_bus
             ? fmt::format("{:.1f} %", 100.0 * d.load)
             : fmt::format("{:.1f} % of the bytes, {:.2f} reports a slot", 100.0 * d.load, d.slot_fraction);
}

std::string load_text(const protocol::BusBudget& b) {
  return fmt::format("host to device {}, device to host {}{}", direction_text(b, b.host_to_device),
                     direction_text(b, b.device_to_host),
                     b.one_bus ? fmt::format(": {:.1f} % of the bus", 100.0 * b.load()) : std::string());
}

// The buses (their usual spec) that carry the traffic within 80 %, else within 100 %.
std::string buses_that_carry(const protocol::CyclicTraffic& traffic) {
  std::string within_80;
  std::string within_100;
  for (std::size_t k = 0; k < protocol::kBusKindCount; ++k) {
    const auto kind = static_cast<protocol::BusKind>(k);
    const protocol::BusBudget b =
        compute_bus_budget(protocol::default_bus_spec(kind, traffic.packed), traffic);
    std::string& list = b.fits(0.8) ? within_80 : within_100;
    if (b.fits()) {
      list += fmt::format("{}{} ({:.0f} %)", list.empty() ? "" : ", ", protocol::to_string(kind),
                          100.0 * b.load());
    }
  }
  if (!within_80.empty()) {
    return "it fits " + within_80;
  }
  return within_100.empty() ? std::string("no bus carries it") : "it fits, above 80 %, " + within_100;
}

}  // namespace

protocol::CyclicTraffic cyclic_traffic_of(const DeviceInfo& info, double update_rate_hz) noexcept {
  protocol::CyclicTraffic t;
  t.valves = info.valves;
  t.sensors = info.sensors;
  t.update_rate_hz = update_rate_hz;
  t.telemetry_rate_hz = info.telemetry_rate_hz;
  t.heartbeat_hz = kHeartbeat_hz;
  t.status_hz = kStatus_hz;
  t.packed = std::min<int>(protocol::kVersionMinor, info.protocol_minor) >= 2 && info.protocol_major == 1;
  return t;
}

BusBudgetCheck check_bus_budget(const DeviceInfo& info, const Transport& transport, double update_rate_hz,
                                double warn_load) {
  BusBudgetCheck c;
  const std::optional<protocol::BusSpec> bus = transport.bus();
  if (!bus) {
    return c;
  }
  c.limited = true;
  c.bus = *bus;
  // A USB unit's declared reports (1.2's UsbSlots) are the bus this session uses.
  if (info.usb_slots &&
      (c.bus.kind == protocol::BusKind::hid_full_speed || c.bus.kind == protocol::BusKind::hid_high_speed)) {
    c.bus.usb = *info.usb_slots;
    c.bus.kind = info.usb_slots->interval_s < protocol::kUsbFullSpeedFrame_s
                     ? protocol::BusKind::hid_high_speed
                     : protocol::BusKind::hid_full_speed;
  }
  c.traffic = cyclic_traffic_of(info, update_rate_hz);
  c.budget = protocol::compute_bus_budget(c.bus, c.traffic);
  c.highest_rate_hz = protocol::highest_update_rate_hz(c.bus, c.traffic);
  const std::string unit = fmt::format("the {}x{} unit ({} valves, {} sensors, protocol {}.{})", info.rows,
                                       info.cols, info.valves, info.sensors, info.protocol_major,
                                       std::min<int>(protocol::kVersionMinor, info.protocol_minor));
  const char* kind = protocol::to_string(c.bus.kind);
  if (!c.budget.fits()) {
    const std::string why = c.budget.encodable ? load_text(c.budget) : c.budget.why_not;
    const std::string highest =
        c.highest_rate_hz > 0.0
            ? fmt::format("the highest loop rate {} carries is {:.0f} Hz", kind, c.highest_rate_hz)
            : fmt::format("{} carries no loop rate: the unit's own telemetry and status fill it", kind);
    throw BusOverloaded(fmt::format(
        "{}: {} at {:.0f} Hz does not fit the {} bus ({}); {}; at {:.0f} Hz {}. Lower the loop rate or use "
        "a unit on a bus that carries it (docs/protocol.md, \"Bus budget\"; mrskinctl budget)",
        transport.uri(), unit, update_rate_hz, kind, why, highest, update_rate_hz,
        buses_that_carry(c.traffic)));
  }
  if (!c.budget.fits(warn_load)) {
    c.warning = fmt::format(
        "{} at {:.0f} Hz needs {:.1f} % of the {} bus ({}), above {:.0f} %: little room for "
        "retries and bursts (docs/protocol.md, \"Bus budget\")",
        unit, update_rate_hz, 100.0 * c.budget.load(), kind, load_text(c.budget), 100.0 * warn_load);
  }
  return c;
}

}  // namespace mrskin
