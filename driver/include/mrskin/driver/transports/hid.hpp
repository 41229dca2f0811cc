// hid://VID:PID[?serial=XXXXXXXX]: the unit's HID interface through hidapi's hidraw backend
// (only that one: hidapi's two backends cannot share a process).
//   hid://              the default VID:PID (1209:4d52), the first unit found
//   hid://1209:4d52     VID:PID in hex
//   hid://1209:4d52?serial=0000BEEF   that unit only (8 hex digits, as `mrskinctl list` shows)
// Every hidapi call goes through the HidApi seam, so the transport's logic is tested with a
// fake. Reports carry no report ID: hid_write() gets 0x00 + the 64-byte report (65 bytes),
// hid_read_timeout() gives back the 64 report bytes. An unplug is seen within one read
// timeout; the transport then reports disconnected, drops what was queued and reopens the
// unit (the same serial, when one was given) by itself when it comes back.
#pragma once

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

struct HidUri {
  std::uint16_t vendor_id = protocol::kUsbVendorId;
  std::uint16_t product_id = protocol::kUsbProductId;
  std::string serial;  // "" = any unit, else 8 upper-case hex digits
};
// Throws InvalidArgument naming the bad part.
MRSKIN_DRIVER_API HidUri parse_hid_uri(std::string_view uri);
// "hid://1209:4d52" or "hid://1209:4d52?serial=0000BEEF".
MRSKIN_DRIVER_API std::string format_hid_uri(const HidUri& uri);

// --- the OS seam ---------------------------------------------------------------------------
// One hidraw node as hid_enumerate() lists it.
struct HidDeviceInfo {
  std::string path;  // /dev/hidrawN
  std::uint16_t vendor_id = 0;
  std::uint16_t product_id = 0;
  std::string serial;  // the iSerialNumber string
};

// What an I/O call returned, and errno right after it (0 when hidapi set none: hidapi 0.13's
// hidraw backend returns -1 without errno when poll() reports the node hung up).
struct HidIoResult {
  int result = 0;
  int error = 0;
};

// One open hidraw node (hid_device). Closed by its destructor. hidapi keeps a device's last
// error inside it without a lock, so the transport opens one per thread.
class MRSKIN_DRIVER_API HidDevice {
 public:
  HidDevice() = default;
  HidDevice(const HidDevice&) = delete;
  HidDevice& operator=(const HidDevice&) = delete;
  HidDevice(HidDevice&&) = delete;
  HidDevice& operator=(HidDevice&&) = delete;
  virtual ~HidDevice() = default;
  // hid_write(): report-ID byte first.
  virtual HidIoResult write(std::span<const std::uint8_t> data) noexcept = 0;
  // hid_read_timeout(): 0 = nothing within timeout_ms, -1 = error, else the bytes read.
  virtual HidIoResult read_timeout(std::span<std::uint8_t> data, int timeout_ms) noexcept = 0;
};

class MRSKIN_DRIVER_API HidApi {
 public:
  HidApi() = default;
  HidApi(const HidApi&) = delete;
  HidApi& operator=(const HidApi&) = delete;
  HidApi(HidApi&&) = delete;
  HidApi& operator=(HidApi&&) = delete;
  virtual ~HidApi() = default;
  // hid_init() / hid_exit(), balanced.
  virtual bool init() noexcept = 0;
  virtual void exit() noexcept = 0;
  virtual std::vector<HidDeviceInfo> enumerate(std::uint16_t vendor_id, std::uint16_t product_id) = 0;
  struct Opened {
    std::unique_ptr<HidDevice> device;  // nullptr on failure...
    int error = 0;                      // ...with errno (EACCES, ENOENT, ...)
  };
  // hid_open_path().
  virtual Opened open_path(const std::string& path) = 0;
  // 0 when the node exists and we may read and write it, else errno (ENOENT: gone).
  virtual int access(const std::string& path) noexcept = 0;
};

// hidapi itself (hidraw backend). hid_init/hid_exit are reference-counted across instances.
MRSKIN_DRIVER_API std::shared_ptr<HidApi> make_system_hid_api();

// --- the transport -------------------------------------------------------------------------
struct HidTransportOptions {
  // Multiplies the durations below except read_timeout (slow environments, VMs).
  double time_scale = 1.0;
  // One hid_read_timeout(): how often the reader looks at shutdown and at the writer's
  // findings. An unplug ends a read at once (the node hangs up).
  Duration read_timeout = std::chrono::milliseconds(50);
  // Between reopen attempts while the unit is gone, doubling from min to max.
  Duration reopen_backoff_min = std::chrono::milliseconds(10);
  Duration reopen_backoff_max = std::chrono::milliseconds(500);
  // After the unit re-appears, EACCES is retried every reopen_backoff_min for this long
  // (udev applies the rule's group and mode a moment after the node appears) before it is
  // reported in problem().
  Duration permission_retry = std::chrono::seconds(2);
  // Consecutive failed reads or writes on a node that is still there before it is closed
  // and reopened (a wedged handle); fewer are counted as io_errors and skipped.
  int errors_before_reopen = 8;
  std::size_t send_queue = 64;       // datagrams
  std::size_t receive_queue = 1024;  // datagrams
};

// Opens the unit (hid_init, hid_enumerate, hid_open_path) and starts its reader and writer
// threads. Throws InvalidArgument (bad URI), DeviceNotFound (no matching unit: says what was
// searched), PermissionDenied (EACCES: names the node, the udev rule and the group), Error.
MRSKIN_DRIVER_API std::unique_ptr<Transport> open_hid_transport(std::string_view uri,
                                                                const HidTransportOptions& options = {});
MRSKIN_DRIVER_API std::unique_ptr<Transport> open_hid_transport(std::string_view uri,
                                                                const HidTransportOptions& options,
                                                                std::shared_ptr<HidApi> api);

// What is wrong with the link now, in words with the fix ("" when nothing): a unit that came
// back but cannot be opened (permission denied after permission_retry, another error).
// Allocates; not for the tick thread. transport must come from open_hid_transport().
MRSKIN_DRIVER_API std::string hid_transport_problem(const Transport& transport);

// list_hid_devices() on a given seam.
MRSKIN_DRIVER_API std::vector<DeviceListing> list_hid_devices(HidApi& api);

}  // namespace mrskin
