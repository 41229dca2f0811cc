#include "mrskin/eval/bus_stats.hpp"

#include <algorithm>

namespace mrskin::eval {
namespace {

// The traffic between `before` and `now`: counts subtract; a load is a fraction of the elapsed
// time (CAN's busy time, USB's bytes over what the slots carry), so load x elapsed adds up.
bridge::BridgeStats::Direction direction_of(const sim::MockBusDirection& now, double now_s,
                                            const sim::MockBusDirection& before, double before_s) noexcept {
  bridge::BridgeStats::Direction out;
  const double span_s = now_s - before_s;
  out.load = span_s > 0.0 && before_s > 0.0
                 ? std::max(0.0, (now.load * now_s - before.load * before_s) / span_s)
                 : now.load;
  out.packets = now.packets - std::min(before.packets, now.packets);
  out.carried = now.carried - std::min(before.carried, now.carried);
  out.bytes = now.bytes - std::min(before.bytes, now.bytes);
  out.dropped = now.dropped - std::min(before.dropped, now.dropped);
  out.unsent = now.unsent - std::min(before.unsent, now.unsent);
  out.max_wait_s = now.max_wait_s;
  return out;
}

}  // namespace

void fill_bus_stats(const sim::MockDevice& mock, bridge::BridgeStats& stats,
                    const sim::MockBusStats& since) noexcept {
  const sim::MockBusStats bus = mock.bus_stats();
  stats.bus.kind = sim::to_string(bus.kind);
  stats.bus.host_to_device =
      direction_of(bus.host_to_device, bus.elapsed_s, since.host_to_device, since.elapsed_s);
  stats.bus.device_to_host =
      direction_of(bus.device_to_host, bus.elapsed_s, since.device_to_host, since.elapsed_s);
  stats.bus.enobufs = bus.enobufs - std::min(since.enobufs, bus.enobufs);
  if (bus.kind != sim::MockBusKind::none) {
    stats.bus_load = std::max(stats.bus.host_to_device.load, stats.bus.device_to_host.load);
  }
}

}  // namespace mrskin::eval
