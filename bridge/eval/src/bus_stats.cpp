#include "mrskin/eval/bus_stats.hpp"

#include <algorithm>

namespace mrskin::eval {
namespace {

bridge::BridgeStats::Direction direction_of(const sim::MockBusDirection& d) noexcept {
  bridge::BridgeStats::Direction out;
  out.load = d.load;
  out.packets = d.packets;
  out.carried = d.carried;
  out.bytes = d.bytes;
  out.dropped = d.dropped;
  out.unsent = d.unsent;
  out.max_wait_s = d.max_wait_s;
  return out;
}

}  // namespace

void fill_bus_stats(const sim::MockDevice& mock, bridge::BridgeStats& stats) noexcept {
  const sim::MockBusStats bus = mock.bus_stats();
  stats.bus.kind = sim::to_string(bus.kind);
  stats.bus.host_to_device = direction_of(bus.host_to_device);
  stats.bus.device_to_host = direction_of(bus.device_to_host);
  stats.bus.enobufs = bus.enobufs;
  if (bus.kind != sim::MockBusKind::none) {
    stats.bus_load = std::max(bus.host_to_device.load, bus.device_to_host.load);
  }
}

}  // namespace mrskin::eval
