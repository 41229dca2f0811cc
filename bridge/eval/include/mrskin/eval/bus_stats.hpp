// The mock's bus model (mock://?bus=...) in the bridge's statistics: the `bus` object and
// `bus_load` (docs/statistics.md).
#pragma once

#include "mrskin/bridge/stats.hpp"
#include "mrskin/eval/export.hpp"
#include "mrskin/sim/mock_device.hpp"

namespace mrskin::eval {

// Copies the bus model's counts and loads into stats.bus; with a modelled bus (not
// mock://?bus=none), bus_load becomes the busier direction's load. Any thread; after the run.
// since: the bus's statistics when the loop started (MockDevice::bus_stats()), so that the open's
// handshake and configuration reads are left out of the counts and loads; default: the whole
// run. The longest wait is over the whole run either way.
MRSKIN_EVAL_API void fill_bus_stats(const sim::MockDevice& mock, bridge::BridgeStats& stats,
                                    const sim::MockBusStats& since = {}) noexcept;

}  // namespace mrskin::eval
