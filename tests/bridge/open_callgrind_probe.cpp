// What opening a unit costs a console application (issue 21: palm-64x64 in at most 5e9
// instructions): open_device on the mock (the handshake and the configuration read, the mock's
// plant built), a Bridge built on it, enabled, and its first 10 ticks with the unit's re-seed on
// enable. Run under
//   valgrind --tool=callgrind --instr-atstart=no --collect-atstart=no (open_callgrind_gate.sh):
// collection is on around all of it. The synchronous mock steps on this thread, so its work counts.
//   open_callgrind_probe [URI]   (default mock://palm-64x64)
#include <valgrind/callgrind.h>

#include <chrono>
#include <cstdio>
#include <string>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/sim/open_mock.hpp"

int main(int argc, char** argv) {
  using namespace mrskin;
  const std::string uri = argc > 1 ? argv[1] : "mock://palm-64x64";
  sim::register_mock_scheme();
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  CALLGRIND_START_INSTRUMENTATION;
  CALLGRIND_TOGGLE_COLLECT;
  OpenedDevice dev = open_device(uri, clock, open);
  auto scene = bridge::make_scene("demo");
  bridge::Bridge loop(*dev.session, *scene);
  scene->set_start(clock.now());
  const bool enabled = loop.enable() == ResultCode::ok;
  for (int k = 0; k < 10; ++k) {
    sim::mock_of(dev)->step(clock.now());
    (void)loop.step(clock.now());
    clock.advance(std::chrono::milliseconds(1));
  }
  CALLGRIND_TOGGLE_COLLECT;
  CALLGRIND_STOP_INSTRUMENTATION;
  std::printf("opened %s: %s, %zu fluid cells\n", uri.c_str(), enabled ? "enabled" : "NOT enabled",
              sim::mock_of(dev)->layout().fluid_cell_count());
  return enabled && dev.session->state() == DeviceState::enabled ? 0 : 1;
}
