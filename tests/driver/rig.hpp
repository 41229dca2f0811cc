// Test rig: a synchronous mock device stepped at 1 kHz on a simulated clock, with the session
// polled after every step.
#pragma once

#include <chrono>
#include <string>
#include <vector>

#include "mrskin/driver/device.hpp"
#include "mrskin/sim/open_mock.hpp"

namespace mrskin::test {

struct Rig {
  explicit Rig(const std::string& uri, SessionOptions session = {}) {
    OpenOptions open;
    open.synchronous_mock = true;
    open.session = session;
    dev = open_device(uri, clock, open);
    currents.assign(sim::mock_of(dev)->layout().valve_count(), 0.0);
    finger.assign(sim::mock_of(dev)->layout().fluid_cell_count(), 0.0);
  }
  // Runs for ms milliseconds; commands the currents each tick unless the host is silent.
  void run(int ms, bool host_alive = true) {
    for (int k = 0; k < ms; ++k) {
      sim::mock_of(dev)->set_finger_indentation(finger);
      sim::mock_of(dev)->step(clock.now());
      if (host_alive) {
        last = dev.session->poll(clock.now());
        if (last == ResultCode::ok) {
          (void)dev.session->send_valve_currents(currents);
        }
      }
      clock.advance(std::chrono::milliseconds(1));
    }
  }
  SimulatedClock clock;
  OpenedDevice dev;
  std::vector<double> currents;
  std::vector<double> finger;
  ResultCode last = ResultCode::ok;
};

}  // namespace mrskin::test
