// usb://VID:PID[?serial=XXXXXXXX]: the unit's HID interface driven directly through
// libusb-1.0 interrupt transfers (no hidraw). Opening detaches the kernel's HID driver from
// interface 0 and closing re-attaches it. An event thread keeps IN transfers submitted and
// writes queued datagrams from a fixed pool of OUT transfers (no allocation per transfer);
// an unplug turns the state to disconnected and the transport reopens the unit by itself
// (hotplug callbacks where libusb has them, polling with backoff where not).
//
// Every libusb call goes through LibusbApi, so tests run the transport's logic on a fake.
// libusb.h stays out of this header (installed for hosts that have no libusb headers).
#pragma once

#include <poll.h>

#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/enumerate.hpp"
#include "mrskin/driver/transport.hpp"
#include "mrskin/protocol/usb.hpp"

struct libusb_device;
struct libusb_device_handle;
struct libusb_transfer;

namespace mrskin {

struct UsbUri {
  std::uint16_t vendor_id = protocol::kUsbVendorId;
  std::uint16_t product_id = protocol::kUsbProductId;
  std::string serial;  // 8 upper-case hex digits, or "" for any unit
};
// usb:// alone means the default VID:PID. Throws InvalidArgument naming the bad part.
UsbUri parse_usb_uri(std::string_view uri);

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

// Device descriptor fields the transport needs.
struct UsbDeviceIds {
  std::uint16_t vendor_id = 0;
  std::uint16_t product_id = 0;
  std::uint8_t serial_index = 0;  // iSerialNumber (0: none)
};

// Called from inside handle_events() on the event thread.
using UsbHotplugFn = void (*)(void* user, libusb_device* device, bool arrived) noexcept;

// The libusb-1.0 calls the transport makes, on one libusb context that the object owns.
// Return values are libusb's (0 or LIBUSB_ERROR_*) unless said otherwise.
class LibusbApi {
 public:
  LibusbApi() = default;
  LibusbApi(const LibusbApi&) = delete;
  LibusbApi& operator=(const LibusbApi&) = delete;
  LibusbApi(LibusbApi&&) = delete;
  LibusbApi& operator=(LibusbApi&&) = delete;
  virtual ~LibusbApi() = default;

  virtual int init() = 0;  // libusb_init
  virtual void exit() noexcept = 0;
  virtual bool has_hotplug() = 0;  // libusb_has_capability(LIBUSB_CAP_HAS_HOTPLUG)
  // Count of devices, or an error; free_device_list unreferences them.
  virtual std::ptrdiff_t get_device_list(libusb_device*** list) = 0;
  virtual void free_device_list(libusb_device** list) = 0;
  virtual int get_device_ids(libusb_device* device, UsbDeviceIds& out) = 0;
  // The interface's interrupt IN and OUT endpoint addresses, from the active configuration
  // descriptor (a gadget or a revised unit may number them differently from the protocol's
  // defaults). The default returns those defaults (0x81, 0x01).
  virtual int get_interrupt_endpoints(libusb_device* device, std::uint8_t interface, std::uint8_t& in,
                                      std::uint8_t& out);
  virtual std::uint8_t get_bus_number(libusb_device* device) = 0;
  virtual std::uint8_t get_device_address(libusb_device* device) = 0;
  virtual int get_port_numbers(libusb_device* device, std::span<std::uint8_t> out) = 0;  // count
  virtual int open(libusb_device* device, libusb_device_handle** handle) = 0;
  virtual void close(libusb_device_handle* handle) = 0;
  virtual libusb_device* get_device(libusb_device_handle* handle) = 0;
  // Bytes written, or an error.
  virtual int get_string_descriptor_ascii(libusb_device_handle* handle, std::uint8_t index,
                                          std::span<unsigned char> out) = 0;
  virtual int kernel_driver_active(libusb_device_handle* handle, int interface) = 0;  // 1, 0 or error
  virtual int detach_kernel_driver(libusb_device_handle* handle, int interface) = 0;
  virtual int attach_kernel_driver(libusb_device_handle* handle, int interface) = 0;
  virtual int claim_interface(libusb_device_handle* handle, int interface) = 0;
  virtual int release_interface(libusb_device_handle* handle, int interface) = 0;
  virtual int clear_halt(libusb_device_handle* handle, std::uint8_t endpoint) = 0;
  virtual libusb_transfer* alloc_transfer() = 0;  // no isochronous packets; nullptr on failure
  virtual void free_transfer(libusb_transfer* transfer) = 0;
  virtual int submit_transfer(libusb_transfer* transfer) = 0;
  virtual int cancel_transfer(libusb_transfer* transfer) = 0;
  // The descriptors to poll for libusb's events (libusb_get_pollfds).
  virtual void get_pollfds(std::vector<pollfd>& out) = 0;
  // 1 with timeout set when libusb must handle events by then even if no descriptor fires;
  // 0 when it has no such deadline (or its own timerfd covers it).
  virtual int get_next_timeout(Duration& timeout) = 0;
  // libusb_handle_events_timeout_completed: runs transfer and hotplug callbacks.
  virtual int handle_events(Duration timeout) = 0;
  virtual int hotplug_register(std::uint16_t vendor_id, std::uint16_t product_id, UsbHotplugFn fn, void* user,
                               int& handle) = 0;
  virtual void hotplug_deregister(int handle) noexcept = 0;
};

// The real libusb-1.0.
std::shared_ptr<LibusbApi> make_libusb_api();

// Opens the unit (first match of VID:PID and serial) and starts the event thread; the state
// is open on return. Throws InvalidArgument (URI), DeviceNotFound (no such unit, or no USB
// at all), PermissionDenied (names the /dev/bus/usb node, the udev rule and the group),
// DeviceBusy (another program or driver holds the interface) or Error.
std::unique_ptr<Transport> open_usb_transport(std::string_view uri, const UsbTransportOptions& options = {});
std::unique_ptr<Transport> open_usb_transport(std::string_view uri, std::shared_ptr<LibusbApi> api,
                                              const UsbTransportOptions& options = {});

// list_usb_devices() on a given libusb; never throws.
std::vector<DeviceListing> list_usb_devices(LibusbApi& api);

}  // namespace mrskin
