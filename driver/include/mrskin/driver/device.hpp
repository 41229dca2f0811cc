// Opening a device by URI. Setup only: throws typed exceptions that say what to do.
//   mock://[?seed=N&perturbation=F&rows=R&cols=C]   the simulated unit (in-process)
// hid://, usb:// and can:// are recognised and refused until their transports land.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <string_view>

#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/mock_device.hpp"
#include "mrskin/driver/session.hpp"

namespace mrskin {

struct OpenOptions {
  // mock:// only: true = the caller steps the mock device (deterministic, one thread);
  // false = the mock runs on its own thread against the clock.
  bool synchronous_mock = false;
  SessionOptions session{};
};

struct OpenedDevice {
  // Declared first so it is destroyed last: the session's destructor still talks to it.
  std::shared_ptr<MockDevice> mock;  // set for mock:// only
  std::unique_ptr<DeviceSession> session;
};

// Parses a mock:// URI into options; throws InvalidArgument naming the bad parameter.
MockOptions parse_mock_uri(std::string_view uri, int& rows, int& cols);

OpenedDevice open_device(std::string_view uri, Clock& clock, const OpenOptions& options = {});

}  // namespace mrskin
