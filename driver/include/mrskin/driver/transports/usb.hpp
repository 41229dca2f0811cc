// usb://VID:PID[?serial=XXXXXXXX]: the unit's HID interface driven directly through
// libusb-1.0 interrupt transfers (no hidraw). Opening detaches the kernel's HID driver from
// interface 0 and closing re-attaches it. An event thread keeps IN transfers submitted and
// writes queued datagrams from a fixed pool of OUT transfers (no allocation per transfer);
// an unplug turns the state to disconnected and the transport reopens the unit by itself
// (hotplug callbacks where libusb has them, polling with backoff where not).
//
// Every libusb call goes through LibusbApi (driver/src/transports/libusb_api.hpp, not
// installed), so tests run the transport's logic on a fake; no libusb or OS type here.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/enumerate.hpp"
#include "mrskin/driver/export.hpp"
#include "mrskin/driver/transport.hpp"
#include "mrskin/protocol/usb.hpp"

namespace mrskin {

struct UsbUri {
  std::uint16_t vendor_id = protocol::kUsbVendorId;
  std::uint16_t product_id = protocol::kUsbProductId;
  std::string serial;  // 8 upper-case hex digits, or "" for any unit
};
// usb:// alone means the default VID:PID. Throws InvalidArgument naming the bad part.
MRSKIN_DRIVER_API UsbUri parse_usb_uri(std::string_view uri);

struct UsbTransportOptions {
  std::size_t in_transfers = 4;   // IN transfers kept submitted
  std::size_t out_transfers = 4;  // OUT transfers in the pool
  std::size_t send_queue = 64;    // datagrams
  std::size_t receive_queue = 256;
  Duration out_timeout = std::chrono::milliseconds(100);  // an OUT not taken by then: counted timeout
  Duration reopen_backoff_min = std::chrono::milliseconds(10);
  Duration reopen_backoff_max = std::chrono::milliseconds(1000);
  // With hotplug, reopening is retried this long after a loss or an arrival (udev applies
  // permissions a moment after the device appears), then waits for the next arrival.
  Duration reopen_window = std::chrono::milliseconds(3000);
  // IN/OUT errors in a row (no success between) after which the device counts as lost.
  std::size_t max_consecutive_errors = 100;
  double time_scale = 1.0;  // multiplies every duration above (slow environments, VMs)
};

// Opens the unit (first match of VID:PID and serial) and starts the event thread; the state
// is open on return. Throws InvalidArgument (URI), DeviceNotFound (no such unit, or no USB
// at all), PermissionDenied (names the /dev/bus/usb node, the udev rule and the group),
// DeviceBusy (another program or driver holds the interface) or Error.
MRSKIN_DRIVER_API std::unique_ptr<Transport> open_usb_transport(std::string_view uri,
                                                                const UsbTransportOptions& options = {});

}  // namespace mrskin
