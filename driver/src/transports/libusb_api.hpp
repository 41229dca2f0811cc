// The libusb-1.0 calls of the USB transport behind one virtual per call: the seam its tests
// drive with a fake. Private to the driver (and its tests): it names libusb's and the OS's types.
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
#include "mrskin/driver/transports/usb.hpp"

struct libusb_device;
struct libusb_device_handle;
struct libusb_transfer;

namespace mrskin {

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
  // An endpoint's wMaxPacketSize (libusb_get_max_packet_size), or an error: the bytes of one IN
  // transfer, since a full packet does not end an interrupt transfer. The default returns 64.
  virtual int get_max_packet_size(libusb_device* device, std::uint8_t endpoint);
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

// open_usb_transport() on a given libusb.
std::unique_ptr<Transport> open_usb_transport(std::string_view uri, std::shared_ptr<LibusbApi> api,
                                              const UsbTransportOptions& options = {});

// list_usb_devices() on a given libusb; never throws.
std::vector<DeviceListing> list_usb_devices(LibusbApi& api);

}  // namespace mrskin
