#include <fmt/format.h>
#include <libusb.h>
#include <poll.h>
#include <pthread.h>
#include <sys/eventfd.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cerrno>
#include <charconv>
#include <chrono>
#include <cstring>
#include <thread>
#include <utility>

#include "libusb_api.hpp"
#include "mrskin/driver/queued_transport.hpp"
#include "mrskin/protocol/packet.hpp"

namespace mrskin {

int LibusbApi::get_interrupt_endpoints(libusb_device* /*device*/, std::uint8_t /*interface*/,
                                       std::uint8_t& in, std::uint8_t& out) {
  in = protocol::kUsbEndpointIn;
  out = protocol::kUsbEndpointOut;
  return 0;
}
int LibusbApi::get_max_packet_size(libusb_device* /*device*/, std::uint8_t /*endpoint*/) {
  return static_cast<int>(protocol::kUsbMaxPacketBytes);
}
namespace {

namespace proto = protocol;
using SteadyClock = std::chrono::steady_clock;

constexpr int kInterface = proto::kUsbInterface;
// A report: 64 bytes at full speed, up to 1024 on a high-speed unit (UsbSlots).
constexpr std::size_t kReportBytes = kMaxDatagramBytes;
constexpr std::string_view kUsbScheme = "usb://";
constexpr const char* kUsbUriForm = "usb://VID:PID[?serial=XXXXXXXX], e.g. usb://1209:4d52";

// --- URI ---------------------------------------------------------------------------------

std::uint16_t parse_hex_id(std::string_view uri, std::string_view text, const char* what) {
  unsigned value = 0;
  const char* end = text.data() + text.size();
  const auto [ptr, ec] = std::from_chars(text.data(), end, value, 16);
  if (text.empty() || text.size() > 4 || ec != std::errc{} || ptr != end) {
    throw InvalidArgument(
        fmt::format("'{}': {} '{}' is not 1 to 4 hex digits ({})", uri, what, text, kUsbUriForm));
  }
  return static_cast<std::uint16_t>(value);
}

std::string device_node(std::uint8_t bus, std::uint8_t address) {
  return fmt::format("/dev/bus/usb/{:03}/{:03}", bus, address);
}

std::string permission_fix(const std::string& node) {
  return fmt::format(
      "give your user access to {}: install udev/70-mrskin.rules into /etc/udev/rules.d/ (sudo udevadm "
      "control --reload && sudo udevadm trigger), add yourself to the mrskin group (sudo groupadd --system "
      "mrskin; sudo usermod -aG mrskin $USER), log in again and re-plug the unit",
      node);
}

std::string no_usb_fix() {
  return "no USB device nodes: check that /dev/bus/usb exists (in a container, pass --device /dev/bus/usb)";
}

std::string port_path(LibusbApi& api, libusb_device* device) {
  std::array<std::uint8_t, 8> ports{};
  std::string path = std::to_string(api.get_bus_number(device));
  const int n = api.get_port_numbers(device, ports);
  for (int i = 0; i < n; ++i) {
    path += (i == 0 ? '-' : '.');
    path += std::to_string(ports[static_cast<std::size_t>(i)]);
  }
  return path;
}

// "" when the unit has no serial string or it cannot be read.
std::string read_serial(LibusbApi& api, libusb_device_handle* handle, std::uint8_t index) {
  if (index == 0) {
    return {};
  }
  std::array<unsigned char, 128> text{};
  const int n = api.get_string_descriptor_ascii(handle, index, text);
  if (n <= 0) {
    return {};
  }
  return {text.begin(), text.begin() + n};
}

timeval to_timeval(Duration d) {
  const auto us = std::chrono::duration_cast<std::chrono::microseconds>(d).count();
  return timeval{static_cast<time_t>(us / 1000000), static_cast<suseconds_t>(us % 1000000)};
}

// Owns a libusb device list for the length of a scope.
class DeviceList {
 public:
  explicit DeviceList(LibusbApi& api) : api_(api), count_(api.get_device_list(&list_)) {}
  DeviceList(const DeviceList&) = delete;
  DeviceList& operator=(const DeviceList&) = delete;
  DeviceList(DeviceList&&) = delete;
  DeviceList& operator=(DeviceList&&) = delete;
  ~DeviceList() {
    if (count_ >= 0 && list_ != nullptr) {
      api_.free_device_list(list_);
    }
  }
  [[nodiscard]] std::ptrdiff_t count() const noexcept { return count_; }
  [[nodiscard]] std::span<libusb_device*> devices() const noexcept {
    return count_ > 0 ? std::span<libusb_device*>(list_, static_cast<std::size_t>(count_))
                      : std::span<libusb_device*>{};
  }

 private:
  LibusbApi& api_;
  libusb_device** list_ = nullptr;
  std::ptrdiff_t count_;
};

// --- the real libusb ---------------------------------------------------------------------

class RealLibusb final : public LibusbApi {
 public:
  RealLibusb() = default;
  RealLibusb(const RealLibusb&) = delete;
  RealLibusb& operator=(const RealLibusb&) = delete;
  RealLibusb(RealLibusb&&) = delete;
  RealLibusb& operator=(RealLibusb&&) = delete;
  ~RealLibusb() override { exit(); }

  int init() override { return libusb_init(&ctx_); }
  void exit() noexcept override {
    if (ctx_ != nullptr) {
      libusb_exit(ctx_);
      ctx_ = nullptr;
    }
    hotplugs_.clear();
  }
  bool has_hotplug() override { return libusb_has_capability(LIBUSB_CAP_HAS_HOTPLUG) != 0; }
  std::ptrdiff_t get_device_list(libusb_device*** list) override {
    return libusb_get_device_list(ctx_, list);
  }
  void free_device_list(libusb_device** list) override { libusb_free_device_list(list, 1); }
  int get_device_ids(libusb_device* device, UsbDeviceIds& out) override {
    libusb_device_descriptor d{};
    const int rc = libusb_get_device_descriptor(device, &d);
    out = UsbDeviceIds{d.idVendor, d.idProduct, d.iSerialNumber};
    return rc;
  }
  int get_interrupt_endpoints(libusb_device* device, std::uint8_t interface, std::uint8_t& in,
                              std::uint8_t& out) override {
    libusb_config_descriptor* config = nullptr;
    const int rc = libusb_get_active_config_descriptor(device, &config);
    if (rc != LIBUSB_SUCCESS) {
      return rc;
    }
    int found = LIBUSB_ERROR_NOT_FOUND;
    for (int i = 0; i < config->bNumInterfaces; ++i) {
      const libusb_interface& it = config->interface[i];
      for (int a = 0; a < it.num_altsetting; ++a) {
        const libusb_interface_descriptor& d = it.altsetting[a];
        if (d.bInterfaceNumber != interface) {
          continue;
        }
        for (int e = 0; e < d.bNumEndpoints; ++e) {
          const libusb_endpoint_descriptor& ep = d.endpoint[e];
          if ((ep.bmAttributes & LIBUSB_TRANSFER_TYPE_MASK) != LIBUSB_TRANSFER_TYPE_INTERRUPT) {
            continue;
          }
          if ((ep.bEndpointAddress & LIBUSB_ENDPOINT_IN) != 0) {
            in = ep.bEndpointAddress;
          } else {
            out = ep.bEndpointAddress;
          }
          found = LIBUSB_SUCCESS;
        }
      }
    }
    libusb_free_config_descriptor(config);
    return found;
  }
  int get_max_packet_size(libusb_device* device, std::uint8_t endpoint) override {
    return libusb_get_max_packet_size(device, endpoint);
  }
  std::uint8_t get_bus_number(libusb_device* device) override { return libusb_get_bus_number(device); }
  std::uint8_t get_device_address(libusb_device* device) override {
    return libusb_get_device_address(device);
  }
  int get_port_numbers(libusb_device* device, std::span<std::uint8_t> out) override {
    return libusb_get_port_numbers(device, out.data(), static_cast<int>(out.size()));
  }
  int open(libusb_device* device, libusb_device_handle** handle) override {
    return libusb_open(device, handle);
  }
  void close(libusb_device_handle* handle) override { libusb_close(handle); }
  libusb_device* get_device(libusb_device_handle* handle) override { return libusb_get_device(handle); }
  int get_string_descriptor_ascii(libusb_device_handle* handle, std::uint8_t index,
                                  std::span<unsigned char> out) override {
    return libusb_get_string_descriptor_ascii(handle, index, out.data(), static_cast<int>(out.size()));
  }
  int kernel_driver_active(libusb_device_handle* handle, int interface) override {
    return libusb_kernel_driver_active(handle, interface);
  }
  int detach_kernel_driver(libusb_device_handle* handle, int interface) override {
    return libusb_detach_kernel_driver(handle, interface);
  }
  int attach_kernel_driver(libusb_device_handle* handle, int interface) override {
    return libusb_attach_kernel_driver(handle, interface);
  }
  int claim_interface(libusb_device_handle* handle, int interface) override {
    return libusb_claim_interface(handle, interface);
  }
  int release_interface(libusb_device_handle* handle, int interface) override {
    return libusb_release_interface(handle, interface);
  }
  int clear_halt(libusb_device_handle* handle, std::uint8_t endpoint) override {
    return libusb_clear_halt(handle, endpoint);
  }
  libusb_transfer* alloc_transfer() override { return libusb_alloc_transfer(0); }
  void free_transfer(libusb_transfer* transfer) override { libusb_free_transfer(transfer); }
  int submit_transfer(libusb_transfer* transfer) override { return libusb_submit_transfer(transfer); }
  int cancel_transfer(libusb_transfer* transfer) override { return libusb_cancel_transfer(transfer); }
  void get_pollfds(std::vector<pollfd>& out) override {
    out.clear();
    const libusb_pollfd** fds = libusb_get_pollfds(ctx_);
    if (fds == nullptr) {
      return;
    }
    for (const libusb_pollfd** p = fds; *p != nullptr; ++p) {
      out.push_back(pollfd{(*p)->fd, (*p)->events, 0});
    }
    libusb_free_pollfds(fds);
  }
  int get_next_timeout(Duration& timeout) override {
    timeval tv{};
    const int rc = libusb_get_next_timeout(ctx_, &tv);
    timeout = std::chrono::seconds(tv.tv_sec) + std::chrono::microseconds(tv.tv_usec);
    return rc;
  }
  int handle_events(Duration timeout) override {
    timeval tv = to_timeval(timeout);
    return libusb_handle_events_timeout_completed(ctx_, &tv, nullptr);
  }
  int hotplug_register(std::uint16_t vendor_id, std::uint16_t product_id, UsbHotplugFn fn, void* user,
                       int& handle) override {
    auto entry = std::make_unique<Hotplug>(Hotplug{fn, user});
    const int rc = libusb_hotplug_register_callback(
        ctx_, LIBUSB_HOTPLUG_EVENT_DEVICE_ARRIVED | LIBUSB_HOTPLUG_EVENT_DEVICE_LEFT, LIBUSB_HOTPLUG_NO_FLAGS,
        vendor_id, product_id, LIBUSB_HOTPLUG_MATCH_ANY, &RealLibusb::on_hotplug, entry.get(), &handle);
    if (rc == LIBUSB_SUCCESS) {
      hotplugs_.push_back(std::move(entry));
    }
    return rc;
  }
  void hotplug_deregister(int handle) noexcept override { libusb_hotplug_deregister_callback(ctx_, handle); }

 private:
  struct Hotplug {
    UsbHotplugFn fn;
    void* user;
  };
  static int LIBUSB_CALL on_hotplug(libusb_context* /*ctx*/, libusb_device* device,
                                    libusb_hotplug_event event, void* user) {
    const auto* h = static_cast<const Hotplug*>(user);
    h->fn(h->user, device, event == LIBUSB_HOTPLUG_EVENT_DEVICE_ARRIVED);
    return 0;  // stay registered
  }
  libusb_context* ctx_ = nullptr;
  std::vector<std::unique_ptr<Hotplug>> hotplugs_;  // freed after libusb_exit (no callback after)
};

// --- the transport -----------------------------------------------------------------------

enum class OpenStatus : unsigned char { ok, not_found, permission, busy, failed };
struct OpenOutcome {
  OpenStatus status = OpenStatus::not_found;
  std::string message;
};

[[noreturn]] void throw_open_failure(const OpenOutcome& outcome) {
  switch (outcome.status) {
    case OpenStatus::permission:
      throw PermissionDenied(outcome.message);
    case OpenStatus::busy:
      throw DeviceBusy(outcome.message);
    case OpenStatus::not_found:
      throw DeviceNotFound(outcome.message);
    case OpenStatus::ok:
    case OpenStatus::failed:
      break;
  }
  throw Error(outcome.message);
}

class UsbTransport final : public QueuedTransport {
 public:
  UsbTransport(std::string_view uri, std::shared_ptr<LibusbApi> api, const UsbTransportOptions& options);
  UsbTransport(const UsbTransport&) = delete;
  UsbTransport& operator=(const UsbTransport&) = delete;
  UsbTransport(UsbTransport&&) = delete;
  UsbTransport& operator=(UsbTransport&&) = delete;
  ~UsbTransport() override;
  // The unit's descriptors are full speed (usb.hpp): one 64-byte report a 1 ms frame each way.
  [[nodiscard]] std::optional<protocol::BusSpec> bus() const noexcept override {
    return protocol::default_bus_spec(protocol::BusKind::hid_full_speed);
  }

 private:
  struct Slot {
    UsbTransport* owner = nullptr;
    libusb_transfer* transfer = nullptr;
    std::array<unsigned char, kReportBytes> buffer{};
    bool in = false;
    bool busy = false;  // submitted, completion pending
  };

  static void LIBUSB_CALL on_transfer(libusb_transfer* transfer);
  static void on_hotplug(void* user, libusb_device* device, bool arrived) noexcept;

  OpenOutcome try_open();
  OpenOutcome claim(libusb_device_handle* handle, const std::string& node);
  bool submit_in() noexcept;
  void completed(Slot& slot) noexcept;
  void note_error() noexcept;
  void run() noexcept;
  void after_events() noexcept;
  void pump_outgoing() noexcept;
  void flush_outgoing() noexcept;
  void clear_halts() noexcept;
  void lose_device() noexcept;
  void try_reopen() noexcept;
  void schedule_reopen(bool restart_window) noexcept;
  void close_device() noexcept;
  void release_all() noexcept;

  std::shared_ptr<LibusbApi> api_;
  UsbUri want_;
  UsbTransportOptions options_;
  bool initialised_ = false;
  bool hotplug_ = false;
  int hotplug_handle_ = -1;
  int wake_fd_ = -1;
  std::vector<Slot> slots_;  // sized once: transfers point at their slot
  std::vector<Slot*> free_out_;
  std::size_t in_flight_ = 0;
  bool stuck_ = false;  // transfers that never completed: leaked rather than freed in flight
  // The open device (event thread only once the thread runs).
  libusb_device_handle* handle_ = nullptr;
  std::uint8_t endpoint_in_ = protocol::kUsbEndpointIn;  // from the descriptor at each open
  std::uint8_t endpoint_out_ = protocol::kUsbEndpointOut;
  std::size_t in_transfer_bytes_ = protocol::kHidReportBytes;  // the IN endpoint's wMaxPacketSize
  libusb_device* device_ = nullptr;
  bool detached_ = false;
  std::string serial_;  // of the unit opened first: a reopen takes the same unit
  std::vector<pollfd> libusb_fds_;
  std::vector<pollfd> fds_;
  bool halt_in_ = false;
  bool halt_out_ = false;
  std::size_t consecutive_errors_ = 0;
  // Set by callbacks, acted on by the event loop outside them.
  std::atomic<bool> lost_{false};
  std::atomic<bool> arrived_{false};
  std::atomic<bool> stop_{false};
  SteadyClock::time_point next_reopen_{};
  SteadyClock::time_point reopen_until_{};
  Duration backoff_{};
  std::thread thread_;
};

UsbTransport::UsbTransport(std::string_view uri, std::shared_ptr<LibusbApi> api,
                           const UsbTransportOptions& options)
    : QueuedTransport(std::string(uri), options.send_queue, options.receive_queue),
      api_(std::move(api)),
      want_(parse_usb_uri(uri)),
      options_(options) {
  options_.out_timeout = scaled_duration(options_.out_timeout, options_.time_scale);
  options_.reopen_backoff_min = scaled_duration(options_.reopen_backoff_min, options_.time_scale);
  options_.reopen_backoff_max = scaled_duration(options_.reopen_backoff_max, options_.time_scale);
  options_.reopen_window = scaled_duration(options_.reopen_window, options_.time_scale);
  if (options_.in_transfers == 0 || options_.out_transfers == 0) {
    throw InvalidArgument(
        fmt::format("'{}': set UsbTransportOptions in_transfers and out_transfers to 1 or more", uri));
  }
  try {
    if (const int rc = api_->init(); rc != LIBUSB_SUCCESS) {
      throw DeviceNotFound(fmt::format("'{}': USB is not available (libusb_init: {}): {}", uri,
                                       libusb_error_name(rc), no_usb_fix()));
    }
    initialised_ = true;
    wake_fd_ = ::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
    if (wake_fd_ < 0) {
      throw Error(
          fmt::format("'{}': eventfd: {} (raise the open-file limit, ulimit -n)", uri, std::strerror(errno)));
    }
    slots_.resize(options_.in_transfers + options_.out_transfers);
    free_out_.reserve(options_.out_transfers);
    for (std::size_t i = 0; i < slots_.size(); ++i) {
      Slot& s = slots_[i];
      s.owner = this;
      s.in = i < options_.in_transfers;
      s.transfer = api_->alloc_transfer();
      if (s.transfer == nullptr) {
        throw Error(fmt::format("'{}': libusb_alloc_transfer failed: out of memory", uri));
      }
      if (!s.in) {
        free_out_.push_back(&s);
      }
    }
    if (const OpenOutcome o = try_open(); o.status != OpenStatus::ok) {
      throw_open_failure(o);
    }
    if (!submit_in()) {
      throw Error(fmt::format(
          "'{}': cannot start reading from the unit (libusb_submit_transfer failed): re-plug it", uri));
    }
    hotplug_ = api_->has_hotplug();
    if (hotplug_ && api_->hotplug_register(want_.vendor_id, want_.product_id, &UsbTransport::on_hotplug, this,
                                           hotplug_handle_) != LIBUSB_SUCCESS) {
      hotplug_ = false;  // fall back to polling after a loss
    }
    set_state(TransportState::open);
    thread_ = std::thread([this] {
      (void)::pthread_setname_np(::pthread_self(), "mrskin-usb");
      run();
    });
  } catch (...) {
    close_device();
    release_all();
    throw;
  }
}

UsbTransport::~UsbTransport() {
  stop_.store(true, std::memory_order_release);
  const std::uint64_t one = 1;
  [[maybe_unused]] const ssize_t n = ::write(wake_fd_, &one, sizeof one);  // fails only if already woken
  if (thread_.joinable()) {
    thread_.join();
  }
  release_all();
}

void UsbTransport::release_all() noexcept {
  if (hotplug_) {
    api_->hotplug_deregister(hotplug_handle_);
    hotplug_ = false;
  }
  for (Slot& s : slots_) {
    if (s.transfer != nullptr && !(stuck_ && s.busy)) {
      api_->free_transfer(s.transfer);
    }
    s.transfer = nullptr;
  }
  if (initialised_) {
    api_->exit();
    initialised_ = false;
  }
  if (wake_fd_ >= 0) {
    ::close(wake_fd_);
    wake_fd_ = -1;
  }
}

// Finds the unit and claims its interface; on success handle_ is set. Allocates (setup and
// reopen only, never on the tick thread).
OpenOutcome UsbTransport::try_open() {
  const std::string ids = fmt::format("{:04x}:{:04x}", want_.vendor_id, want_.product_id);
  const DeviceList list(*api_);
  if (list.count() < 0) {
    return {OpenStatus::failed, fmt::format("'{}': cannot list USB devices (libusb_get_device_list: {})",
                                            uri(), libusb_error_name(static_cast<int>(list.count())))};
  }
  OpenOutcome outcome{OpenStatus::not_found, {}};
  std::string others;  // serials of the other units seen
  for (libusb_device* device : list.devices()) {
    UsbDeviceIds d;
    if (api_->get_device_ids(device, d) != LIBUSB_SUCCESS || d.vendor_id != want_.vendor_id ||
        d.product_id != want_.product_id) {
      continue;
    }
    const std::string node = device_node(api_->get_bus_number(device), api_->get_device_address(device));
    libusb_device_handle* handle = nullptr;
    const int rc = api_->open(device, &handle);
    if (rc != LIBUSB_SUCCESS) {
      if (rc == LIBUSB_ERROR_ACCESS) {
        outcome = {OpenStatus::permission,
                   fmt::format("'{}': permission denied opening the MR skin at {}: {}", uri(), node,
                               permission_fix(node))};
      } else if (outcome.status == OpenStatus::not_found && rc != LIBUSB_ERROR_NO_DEVICE) {
        outcome = {OpenStatus::failed,
                   fmt::format("'{}': cannot open the MR skin at {} (libusb_open: {}): re-plug it", uri(),
                               node, libusb_error_name(rc))};
      }
      continue;
    }
    std::string serial = read_serial(*api_, handle, d.serial_index);
    const std::string& wanted = serial_.empty() ? want_.serial : serial_;
    if (!wanted.empty() && serial != wanted) {
      others += (others.empty() ? "" : ", ") + (serial.empty() ? std::string("(unreadable)") : serial);
      api_->close(handle);
      continue;
    }
    endpoint_in_ = proto::kUsbEndpointIn;
    endpoint_out_ = proto::kUsbEndpointOut;
    // The descriptor's own endpoints; on failure the protocol's defaults stand.
    (void)api_->get_interrupt_endpoints(device, proto::kUsbInterface, endpoint_in_, endpoint_out_);
    // An IN transfer of exactly one packet: a full one would not end a longer transfer.
    // Bits 0-10 of wMaxPacketSize (bits 11-12 count a high-bandwidth endpoint's extra transactions).
    const int max_packet = api_->get_max_packet_size(device, endpoint_in_);
    const int in_bytes = max_packet > 0 ? (max_packet & 0x7FF) : max_packet;
    in_transfer_bytes_ = in_bytes > 0
                             ? std::min<std::size_t>(static_cast<std::size_t>(in_bytes), kReportBytes)
                             : proto::kHidReportBytes;
    outcome = claim(handle, node);
    if (outcome.status == OpenStatus::ok) {
      serial_ = std::move(serial);
      return outcome;
    }
  }
  if (outcome.status == OpenStatus::not_found) {
    const std::string& wanted = serial_.empty() ? want_.serial : serial_;
    outcome.message = fmt::format(
        "'{}': no MR skin with USB id {}{} is attached{}: check the cable and the URI (mrskinctl list shows "
        "the "
        "units found)",
        uri(), ids, wanted.empty() ? "" : " and serial " + wanted,
        others.empty() ? "" : " (units seen with serials " + others + ")");
  }
  return outcome;
}

// Detaches the kernel's HID driver from the interface and claims it; closes the handle on
// failure, re-attaching what it detached.
OpenOutcome UsbTransport::claim(libusb_device_handle* handle, const std::string& node) {
  bool detached = false;
  int rc = api_->kernel_driver_active(handle, kInterface);
  if (rc == 1) {
    rc = api_->detach_kernel_driver(handle, kInterface);
    detached = rc == LIBUSB_SUCCESS;
    rc = rc == LIBUSB_ERROR_NOT_FOUND ? LIBUSB_SUCCESS : rc;  // the driver went by itself
  } else {
    rc = LIBUSB_SUCCESS;  // 0, or NOT_SUPPORTED where the OS has no kernel drivers to detach
  }
  if (rc == LIBUSB_SUCCESS) {
    rc = api_->claim_interface(handle, kInterface);
  }
  if (rc == LIBUSB_SUCCESS) {
    handle_ = handle;
    device_ = api_->get_device(handle);
    detached_ = detached;
    halt_in_ = halt_out_ = false;
    consecutive_errors_ = 0;
    api_->get_pollfds(libusb_fds_);  // the device's usbfs descriptor joins libusb's set
    return {OpenStatus::ok, {}};
  }
  if (detached) {
    (void)api_->attach_kernel_driver(handle, kInterface);
  }
  api_->close(handle);
  switch (rc) {
    case LIBUSB_ERROR_ACCESS:
      return {OpenStatus::permission,
              fmt::format("'{}': permission denied claiming interface {} of the MR skin at {}: {}", uri(),
                          kInterface, node, permission_fix(node))};
    case LIBUSB_ERROR_BUSY:
      return {OpenStatus::busy,
              fmt::format(
                  "'{}': interface {} of the MR skin at {} is claimed by another program or kernel driver: "
                  "close the other program (another mrskin session on usb:// or hid://, a hidraw reader) "
                  "and retry",
                  uri(), kInterface, node)};
    case LIBUSB_ERROR_NO_DEVICE:
      return {OpenStatus::not_found, {}};
    default:
      return {OpenStatus::failed,
              fmt::format("'{}': cannot claim interface {} of the MR skin at {} ({}): re-plug it", uri(),
                          kInterface, node, libusb_error_name(rc))};
  }
}

// Submits every idle IN transfer; false when one cannot be (the device then counts as lost).
bool UsbTransport::submit_in() noexcept {
  for (std::size_t i = 0; i < options_.in_transfers; ++i) {
    Slot& s = slots_[i];
    if (s.busy) {
      continue;
    }
    libusb_fill_interrupt_transfer(s.transfer, handle_, endpoint_in_, s.buffer.data(),
                                   static_cast<int>(in_transfer_bytes_), &UsbTransport::on_transfer, &s, 0);
    if (const int rc = api_->submit_transfer(s.transfer); rc != LIBUSB_SUCCESS) {
      if (rc != LIBUSB_ERROR_NO_DEVICE) {
        counters_.io_errors.bump();
      }
      return false;
    }
    s.busy = true;
    ++in_flight_;
  }
  return true;
}

void LIBUSB_CALL UsbTransport::on_transfer(libusb_transfer* transfer) {
  auto* slot = static_cast<Slot*>(transfer->user_data);
  slot->owner->completed(*slot);
}

void UsbTransport::on_hotplug(void* user, libusb_device* device, bool arrived) noexcept {
  auto* self = static_cast<UsbTransport*>(user);
  if (arrived) {
    self->arrived_.store(true, std::memory_order_relaxed);
  } else if (device == self->device_) {
    self->lost_.store(true, std::memory_order_relaxed);
  }
}

void UsbTransport::note_error() noexcept {
  counters_.io_errors.bump();
  if (++consecutive_errors_ >= options_.max_consecutive_errors) {
    lost_.store(true, std::memory_order_relaxed);  // a reopen is the remaining cure
  }
}

// Runs inside handle_events() on the event thread. Resubmission waits for after_events(),
// which may clear a halt first (synchronous calls are not allowed inside a callback).
void UsbTransport::completed(Slot& slot) noexcept {
  slot.busy = false;
  --in_flight_;
  const libusb_transfer& t = *slot.transfer;
  switch (t.status) {
    case LIBUSB_TRANSFER_COMPLETED:
      consecutive_errors_ = 0;
      if (!slot.in) {
        counters_.sent.bump();
      } else if (t.actual_length > 0) {
        // The report as it came: no report-ID byte on libusb; decoding ignores the padding.
        Datagram d;
        d.length = static_cast<std::uint16_t>(std::min<int>(t.actual_length, static_cast<int>(kReportBytes)));
        std::memcpy(d.bytes.data(), t.buffer, d.length);
        deliver(d);
      } else {
        counters_.malformed.bump();  // an empty report is not a packet
      }
      break;
    case LIBUSB_TRANSFER_TIMED_OUT:
      if (!slot.in) {
        counters_.timeouts.bump();
      }
      break;
    case LIBUSB_TRANSFER_CANCELLED:
      break;
    case LIBUSB_TRANSFER_NO_DEVICE:
      lost_.store(true, std::memory_order_relaxed);
      break;
    case LIBUSB_TRANSFER_STALL:
      (slot.in ? halt_in_ : halt_out_) = true;
      note_error();
      break;
    case LIBUSB_TRANSFER_ERROR:
    case LIBUSB_TRANSFER_OVERFLOW:
      note_error();
      break;
  }
  if (!slot.in) {
    free_out_.push_back(&slot);
  }
}

// The event thread. It polls libusb's descriptors together with the send eventfd, so a
// queued datagram is submitted at once while the tick thread never touches libusb (whose
// own wake-up takes a mutex), and an idle link costs no periodic wake-ups.
void UsbTransport::run() noexcept {
  fds_.reserve(libusb_fds_.size() + 8);
  while (!stop_.load(std::memory_order_acquire)) {
    fds_.assign(libusb_fds_.begin(), libusb_fds_.end());
    fds_.push_back(pollfd{wake_fd_, POLLIN, 0});
    const bool can_send = handle_ != nullptr && !free_out_.empty() && !halt_out_;
    if (can_send) {
      fds_.push_back(pollfd{send_event_fd(), POLLIN, 0});  // left out when nothing could go out
    }
    int timeout_ms = -1;
    Duration next{};
    if (api_->get_next_timeout(next) == 1) {
      timeout_ms = static_cast<int>(std::chrono::ceil<std::chrono::milliseconds>(next).count());
    }
    if (handle_ == nullptr && next_reopen_ != SteadyClock::time_point{}) {
      const auto until =
          std::chrono::ceil<std::chrono::milliseconds>(next_reopen_ - SteadyClock::now()).count();
      const int wait = static_cast<int>(std::max<std::int64_t>(until, 0));
      timeout_ms = timeout_ms < 0 ? wait : std::min(timeout_ms, wait);
    }
    (void)::poll(fds_.data(), fds_.size(), timeout_ms);
    std::uint64_t value = 0;
    [[maybe_unused]] const ssize_t n = ::read(wake_fd_, &value, sizeof value);  // EAGAIN: not woken
    (void)api_->handle_events(Duration{0});
    after_events();
  }
  flush_outgoing();
  close_device();
}

// At shutdown, what the host queued last (the session's disable request) still goes out,
// for at most one OUT timeout.
void UsbTransport::flush_outgoing() noexcept {
  if (handle_ == nullptr) {
    return;
  }
  const auto until = SteadyClock::now() + options_.out_timeout;
  for (;;) {
    pump_outgoing();
    const bool out_busy = std::any_of(slots_.begin() + static_cast<std::ptrdiff_t>(options_.in_transfers),
                                      slots_.end(), [](const Slot& s) { return s.busy; });
    // Nothing in flight after a pump: the queue is empty (or the endpoint halted).
    if (handle_ == nullptr || !out_busy || SteadyClock::now() >= until) {
      return;
    }
    (void)api_->handle_events(std::chrono::milliseconds(1));
  }
}

void UsbTransport::after_events() noexcept {
  if (lost_.exchange(false, std::memory_order_relaxed) && handle_ != nullptr) {
    lose_device();
  }
  if (arrived_.exchange(false, std::memory_order_relaxed) && handle_ == nullptr) {
    schedule_reopen(true);
  }
  if (handle_ == nullptr) {
    if (next_reopen_ != SteadyClock::time_point{} && SteadyClock::now() >= next_reopen_) {
      try_reopen();
    }
    return;
  }
  clear_halts();
  if (!submit_in()) {
    lose_device();
    return;
  }
  pump_outgoing();
}

void UsbTransport::clear_halts() noexcept {
  for (const bool in : {true, false}) {
    bool& halt = in ? halt_in_ : halt_out_;
    if (!halt) {
      continue;
    }
    halt = false;  // a failed clear stalls again and counts toward max_consecutive_errors
    const int rc = api_->clear_halt(handle_, in ? endpoint_in_ : endpoint_out_);
    if (rc == LIBUSB_ERROR_NO_DEVICE) {
      lost_.store(true, std::memory_order_relaxed);
    } else if (rc != LIBUSB_SUCCESS) {
      counters_.io_errors.bump();
    }
  }
}

// OUT reports are the packets, zero padded to 64 bytes (a larger report of a high-speed unit goes
// as long as its packets), without a report-ID byte.
void UsbTransport::pump_outgoing() noexcept {
  Datagram d;
  while (!free_out_.empty() && !halt_out_ && !lost_.load(std::memory_order_relaxed) && take_outgoing(d)) {
    Slot& s = *free_out_.back();
    free_out_.pop_back();
    const std::size_t n = std::max<std::size_t>(d.length, proto::kHidReportBytes);
    std::memcpy(s.buffer.data(), d.bytes.data(), d.length);
    std::fill(s.buffer.begin() + d.length, s.buffer.begin() + static_cast<std::ptrdiff_t>(n), 0);
    libusb_fill_interrupt_transfer(
        s.transfer, handle_, endpoint_out_, s.buffer.data(), static_cast<int>(n), &UsbTransport::on_transfer,
        &s,
        static_cast<unsigned>(std::chrono::ceil<std::chrono::milliseconds>(options_.out_timeout).count()));
    const int rc = api_->submit_transfer(s.transfer);
    if (rc == LIBUSB_SUCCESS) {
      s.busy = true;
      ++in_flight_;
      continue;
    }
    free_out_.push_back(&s);
    if (rc == LIBUSB_ERROR_NO_DEVICE) {
      lost_.store(true, std::memory_order_relaxed);
    } else {
      note_error();
    }
  }
  if (lost_.load(std::memory_order_relaxed)) {
    lose_device();
  }
}

void UsbTransport::lose_device() noexcept {
  close_device();
  lost_.store(false, std::memory_order_relaxed);
  // Commands queued for the unit that left must not reach the next one.
  discard_outgoing();
  set_state(TransportState::disconnected);
  schedule_reopen(true);
}

// Without hotplug, polling goes on for ever (backoff capped); with it, for reopen_window
// after each loss or arrival, then the next arrival restarts it.
void UsbTransport::schedule_reopen(bool restart_window) noexcept {
  const auto now = SteadyClock::now();
  if (restart_window) {
    backoff_ = options_.reopen_backoff_min;
    reopen_until_ = now + options_.reopen_window;
    next_reopen_ = now;
    return;
  }
  if (hotplug_ && now >= reopen_until_) {
    next_reopen_ = {};
    return;
  }
  next_reopen_ = now + backoff_;
  backoff_ = std::min(backoff_ * 2, options_.reopen_backoff_max);
}

void UsbTransport::try_reopen() noexcept {
  OpenOutcome o;
  try {
    o = try_open();
  } catch (...) {
    o.status = OpenStatus::failed;  // out of memory building a message: try again later
  }
  if (o.status == OpenStatus::ok) {
    if (submit_in()) {
      discard_outgoing();
      next_reopen_ = {};
      set_state(TransportState::open);
      return;
    }
    close_device();
  }
  schedule_reopen(false);
}

// Cancels what is in flight, waits for the completions, then releases the interface,
// re-attaches the kernel driver and closes. Idempotent.
void UsbTransport::close_device() noexcept {
  if (handle_ == nullptr) {
    return;
  }
  for (Slot& s : slots_) {
    if (s.busy) {
      (void)api_->cancel_transfer(s.transfer);  // NOT_FOUND: already completing
    }
  }
  // libusb completes every cancelled transfer; the bound only guards against a broken stack.
  for (int i = 0; i < 100 && in_flight_ > 0; ++i) {
    (void)api_->handle_events(std::chrono::milliseconds(50));
  }
  stuck_ = stuck_ || in_flight_ > 0;
  (void)api_->release_interface(handle_, kInterface);
  if (detached_) {
    (void)api_->attach_kernel_driver(handle_, kInterface);  // fails harmlessly when the unit left
    detached_ = false;
  }
  api_->close(handle_);
  handle_ = nullptr;
  device_ = nullptr;
  try {
    api_->get_pollfds(libusb_fds_);
  } catch (...) {
    libusb_fds_.clear();  // keep polling the wake-up and libusb's timeouts only
  }
}

}  // namespace

UsbUri parse_usb_uri(std::string_view uri) {
  if (!uri.starts_with(kUsbScheme)) {
    throw InvalidArgument(fmt::format("'{}' is not a usb:// URI ({})", uri, kUsbUriForm));
  }
  UsbUri out;
  std::string_view rest = uri.substr(kUsbScheme.size());
  std::string_view query;
  if (const auto q = rest.find('?'); q != std::string_view::npos) {
    query = rest.substr(q + 1);
    rest = rest.substr(0, q);
  }
  if (!rest.empty()) {
    const auto colon = rest.find(':');
    if (colon == std::string_view::npos) {
      throw InvalidArgument(fmt::format("'{}': '{}' is not VID:PID ({})", uri, rest, kUsbUriForm));
    }
    out.vendor_id = parse_hex_id(uri, rest.substr(0, colon), "vendor id");
    out.product_id = parse_hex_id(uri, rest.substr(colon + 1), "product id");
  }
  while (!query.empty()) {
    const auto amp = query.find('&');
    const std::string_view item = query.substr(0, amp);
    query = amp == std::string_view::npos ? std::string_view{} : query.substr(amp + 1);
    const auto eq = item.find('=');
    const std::string_view key = item.substr(0, eq);
    const std::string_view value = eq == std::string_view::npos ? std::string_view{} : item.substr(eq + 1);
    if (key != "serial") {
      throw InvalidArgument(
          fmt::format("'{}': unknown parameter '{}' (only serial; {})", uri, key, kUsbUriForm));
    }
    const auto serial = proto::parse_usb_serial(value);
    if (!serial) {
      throw InvalidArgument(fmt::format(
          "'{}': serial '{}' is not 8 hex digits (as mrskinctl list shows it; {})", uri, value, kUsbUriForm));
    }
    out.serial = proto::format_usb_serial(*serial);
  }
  return out;
}

std::shared_ptr<LibusbApi> make_libusb_api() { return std::make_shared<RealLibusb>(); }

std::unique_ptr<Transport> open_usb_transport(std::string_view uri, std::shared_ptr<LibusbApi> api,
                                              const UsbTransportOptions& options) {
  if (!api) {
    throw InvalidArgument(fmt::format("'{}': no libusb given (pass make_libusb_api())", uri));
  }
  return std::make_unique<UsbTransport>(uri, std::move(api), options);
}

std::unique_ptr<Transport> open_usb_transport(std::string_view uri, const UsbTransportOptions& options) {
  return open_usb_transport(uri, make_libusb_api(), options);
}

std::vector<DeviceListing> list_usb_devices(LibusbApi& api) {
  std::vector<DeviceListing> out;
  try {
    if (const int rc = api.init(); rc != LIBUSB_SUCCESS) {
      DeviceListing l;
      l.bus = "usb";
      l.problem = fmt::format("USB is not available (libusb_init: {})", libusb_error_name(rc));
      l.fix = no_usb_fix();
      out.push_back(std::move(l));
      return out;
    }
    {
      const DeviceList list(api);
      for (libusb_device* device : list.devices()) {
        UsbDeviceIds d;
        if (api.get_device_ids(device, d) != LIBUSB_SUCCESS || d.vendor_id != proto::kUsbVendorId ||
            d.product_id != proto::kUsbProductId) {
          continue;
        }
        DeviceListing l;
        l.bus = "usb";
        l.path = port_path(api, device);
        l.uri = fmt::format("usb://{:04x}:{:04x}", d.vendor_id, d.product_id);
        const std::string node = device_node(api.get_bus_number(device), api.get_device_address(device));
        libusb_device_handle* handle = nullptr;
        const int rc = api.open(device, &handle);
        if (rc == LIBUSB_SUCCESS) {
          l.serial = read_serial(api, handle, d.serial_index);
          api.close(handle);
          l.uri += l.serial.empty() ? "" : "?serial=" + l.serial;
        } else if (rc == LIBUSB_ERROR_ACCESS) {
          l.problem = "permission denied";
          l.fix = permission_fix(node);
        } else {
          l.problem = fmt::format("cannot open {} (libusb_open: {})", node, libusb_error_name(rc));
          l.fix = "re-plug the unit";
        }
        out.push_back(std::move(l));
      }
    }
    api.exit();
  } catch (...) {
    api.exit();  // out of memory: return what was listed
  }
  return out;
}

std::vector<DeviceListing> list_usb_devices() {
  try {
    return list_usb_devices(*make_libusb_api());
  } catch (...) {
    return {};
  }
}

}  // namespace mrskin
