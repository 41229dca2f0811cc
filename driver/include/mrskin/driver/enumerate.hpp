// Finding MR skins: what `mrskinctl list` shows. Each bus lists the units it can see, with a
// URI that opens exactly that unit, and when the OS refuses access, the problem and its fix.
// Setup only (allocates, may take up to a few hundred ms for CAN probing); never throws for a
// missing bus: an absent backend or a kernel without CAN gives an entry with the problem.
#pragma once

#include <string>
#include <vector>

#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/export.hpp"

namespace mrskin {

struct DeviceListing {
  std::string bus;       // "hid", "usb" or "can"
  std::string uri;       // opens this unit: hid://1209:4d52?serial=0000BEEF, can://can0?node=3
  std::string path;      // /dev/hidraw3, the USB bus-port path "1-2.3", or the CAN interface
  std::string serial;    // as the unit reports it ("" when unknown before opening)
  std::string firmware;  // "MAJOR.MINOR.PATCH" when known without a session (CAN probe), else ""
  std::string protocol;  // "MAJOR.MINOR" likewise
  std::string problem;   // "" when the unit can be opened, else what is wrong ("permission denied")
  std::string fix;       // what to do about the problem
};

// hidraw nodes with the unit's VID:PID (hidapi, hidraw backend).
MRSKIN_DRIVER_API std::vector<DeviceListing> list_hid_devices();
// USB devices with the unit's VID:PID (libusb).
MRSKIN_DRIVER_API std::vector<DeviceListing> list_usb_devices();
// Every CAN interface that exists, probed for nodes 1..15 with an identify request; waits
// at most timeout per interface. An interface that is down or a kernel without CAN gives
// one entry with the problem and the command that fixes it.
MRSKIN_DRIVER_API std::vector<DeviceListing> list_can_devices(
    Duration timeout = std::chrono::milliseconds(100));

}  // namespace mrskin
