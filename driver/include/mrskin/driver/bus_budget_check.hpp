// The bus budget of an open unit at a loop rate (protocol/bus_budget.hpp, docs/protocol.md "Bus
// budget"), checked before a loop starts: refused above 100 % of the bus (or with more reports
// than slots), one warning line above 80 %. Setup only (allocates, may throw).
#pragma once

#include <string>

#include "mrskin/driver/export.hpp"
#include "mrskin/driver/session.hpp"
#include "mrskin/protocol/bus_budget.hpp"

namespace mrskin {

struct BusBudgetCheck {
  bool limited = false;  // false: the transport's link has no limit, nothing was checked
  protocol::BusSpec bus;
  protocol::CyclicTraffic traffic;
  protocol::BusBudget budget;
  double highest_rate_hz = 0.0;  // the highest loop rate this bus carries within 100 %
  std::string warning;           // above warn_load: one line for the log, else empty
};

// The unit's cyclic traffic from its Identity (valves, sensors, telemetry rate), the protocol
// version both sides speak (1.2 packs), a heartbeat every 20 ms and a status at 10 Hz.
MRSKIN_DRIVER_API protocol::CyclicTraffic cyclic_traffic_of(const DeviceInfo& info,
                                                            double update_rate_hz) noexcept;

// Throws BusOverloaded when the traffic at update_rate_hz does not fit the transport's bus, with
// the highest rate that does and the buses that would carry update_rate_hz.
MRSKIN_DRIVER_API BusBudgetCheck check_bus_budget(const DeviceInfo& info, const Transport& transport,
                                                  double update_rate_hz, double warn_load = 0.8);

}  // namespace mrskin
