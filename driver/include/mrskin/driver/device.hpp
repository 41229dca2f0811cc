// Opening a device by URI. Setup only: throws typed exceptions that say what to do.
//   mock://[PROFILE][?seed=N&perturbation=F&faults=LIST&time_scale=K&bus=KIND&bitrate=B[/D]]
//     the simulated unit, in-process, built to a device profile: PROFILE is a name in the
//     profile search path (mr-skin-5x5, fingertip-16x16, palm-64x64, ...), a file path
//     (mock:///path/to/unit.toml), or empty / "default" for the default profile. The grid,
//     the current range and resolution and the sensors come from the profile. faults is a
//     comma list of drop:P, dup:P, corrupt:P, reorder:P, delay:S, disconnect:AT+FOR,
//     stuck:SENSOR, noisy:SENSOR, overheat:VALVE[+FOR], busoff:AT (probabilities per
//     datagram, times in seconds of device time). bus models the link on the simulated
//     clock: none (default: an ideal link), hid-fs, hid-hs, can or canfd; bitrate=B (can) or
//     B/D (canfd), bit/s (docs/protocol.md, "The mock's bus model"). The simulation is a
//     library of its own, mrskin::sim (mrskin/sim/open_mock.hpp): mock:// opens only in a
//     process linked with it.
//   hid://VID:PID[?serial=S]   the unit through hidapi (hidraw); usb://VID:PID[?serial=S] through
//     libusb, talking to its HID interface directly; can://IFACE?node=N[&fd=1] over SocketCAN.
//     One ownership lock per unit: hid:// and usb:// to the same VID:PID:serial exclude each other.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <string_view>

#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/export.hpp"
#include "mrskin/driver/session.hpp"

namespace mrskin {

struct OpenOptions {
  // Simulated units (mock://) only: true = the caller steps the simulation (deterministic, one
  // thread); false = it runs on its own thread against the clock.
  bool synchronous_mock = false;
  SessionOptions session{};
};

// Advisory ownership of one device: an flock()ed file under $XDG_RUNTIME_DIR (or /tmp)
// holding the owner's PID. A mock device lives inside its process, so its lock name
// carries the PID: two sessions on one mock:// name in one process are refused.
class MRSKIN_DRIVER_API DeviceLock {
 public:
  // Throws DeviceBusy naming the owning process.
  explicit DeviceLock(std::string_view uri);
  DeviceLock(const DeviceLock&) = delete;
  DeviceLock& operator=(const DeviceLock&) = delete;
  DeviceLock(DeviceLock&&) = delete;
  DeviceLock& operator=(DeviceLock&&) = delete;
  ~DeviceLock();
  [[nodiscard]] const std::string& path() const noexcept { return path_; }

 private:
  std::string path_;
  int fd_ = -1;
  bool per_process_ = false;
};

// An in-process simulated unit behind a session (mrskin::sim's MockDevice). The driver only
// keeps it alive; mrskin::sim::mock_of() gives it back to the simulation's users.
class MRSKIN_DRIVER_API SimulatedUnit {
 public:
  SimulatedUnit() = default;
  SimulatedUnit(const SimulatedUnit&) = delete;
  SimulatedUnit& operator=(const SimulatedUnit&) = delete;
  SimulatedUnit(SimulatedUnit&&) = delete;
  SimulatedUnit& operator=(SimulatedUnit&&) = delete;
  virtual ~SimulatedUnit() = default;
};

struct OpenedDevice {
  std::unique_ptr<DeviceLock> lock;  // destroyed last
  // Declared before the session so it is destroyed after it: the session's destructor
  // still talks to it. Set for simulated units only.
  std::shared_ptr<SimulatedUnit> simulation;
  std::unique_ptr<DeviceSession> session;
};

// Opens one URI scheme ("mock" for mrskin::sim); open_device() asks the registered opener of a
// URI's scheme first, then its own (hid, usb, can). The SessionOptions are the caller's with
// MRSKIN_TIME_SCALE applied.
using DeviceOpener = OpenedDevice (*)(std::string_view uri, Clock& clock, const OpenOptions& options,
                                      const SessionOptions& session_options);
// Registers (or replaces) the opener of `scheme` (without "://"). Setup only (it takes a lock).
MRSKIN_DRIVER_API void register_device_scheme(std::string_view scheme, DeviceOpener opener);

MRSKIN_DRIVER_API OpenedDevice open_device(std::string_view uri, Clock& clock,
                                           const OpenOptions& options = {});
// Checks a device URI as open_device would take it, opening nothing: the scheme, and the syntax
// of hid://, usb:// and can:// URIs. A scheme registered with register_device_scheme passes (it
// checks its URI when it opens). Throws InvalidArgument saying what is wrong.
MRSKIN_DRIVER_API void check_device_uri(std::string_view uri);

}  // namespace mrskin
