#include <fmt/format.h>
#include <hidapi/hidapi.h>
#include <poll.h>
#include <pthread.h>
#include <sys/eventfd.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstring>
#include <mutex>
#include <optional>
#include <system_error>
#include <thread>
#include <utility>

#include "event_fd.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/queued_transport.hpp"
#include "mrskin/driver/transports/hid.hpp"
#include "mrskin/protocol/packet.hpp"

namespace mrskin {
namespace {

constexpr std::string_view kHidScheme = "hid://";
// hid_write() takes the report-ID byte (0x00: no report IDs), then the report: 64 bytes at full speed, or up
// to the 1024 a unit declares (UsbSlots), as long as its packets (a short transfer, which USB allows).
constexpr std::size_t kMaxWriteBytes = kMaxDatagramBytes + 1;
constexpr std::size_t write_bytes(std::size_t datagram_bytes) noexcept {
  return 1 + std::max(datagram_bytes, protocol::kHidReportBytes);
}

std::uint16_t parse_id(std::string_view what, std::string_view text, std::string_view uri) {
  unsigned value = 0;
  const char* end = text.data() + text.size();
  const auto r = std::from_chars(text.data(), end, value, 16);
  if (text.empty() || text.size() > 4 || r.ec != std::errc{} || r.ptr != end || value == 0) {
    throw InvalidArgument(
        fmt::format("'{}': the {} '{}' is not 1 to 4 hex digits (not 0000); write "
                    "hid://VID:PID, e.g. hid://1209:4d52",
                    uri, what, text));
  }
  return static_cast<std::uint16_t>(value);
}

// What to do about EACCES on a hidraw node.
std::string permission_fix() {
  return "install the udev rule and join the mrskin group: sudo cp udev/70-mrskin.rules /etc/udev/rules.d/ "
         "&& "
         "sudo udevadm control --reload && sudo udevadm trigger; sudo groupadd --system mrskin; "
         "sudo usermod -aG mrskin $USER (then log in again and replug the unit)";
}

std::string permission_message(std::string_view path) {
  return fmt::format("permission denied on {}: {}", path, permission_fix());
}

// strerror() is not thread-safe; this is.
std::string errno_text(int error) { return std::generic_category().message(error); }

bool same_serial(std::string_view listed, std::string_view wanted) noexcept {
  const auto a = protocol::parse_usb_serial(listed);
  return a.has_value() && a == protocol::parse_usb_serial(wanted);
}

// errno values meaning the node or the device behind it is gone.
bool gone(int error) noexcept {
  return error == ENODEV || error == ENXIO || error == ENOENT || error == ESHUTDOWN;
}

// hid_init() for as long as it lives.
class HidInit {
 public:
  explicit HidInit(HidApi& api) : api_(api) {
    if (!api_.init()) {
      throw Error(
          "hid_init() failed: hidapi (hidraw backend) could not start; check that /dev and /sys are "
          "mounted and libudev is installed");
    }
  }
  HidInit(const HidInit&) = delete;
  HidInit& operator=(const HidInit&) = delete;
  HidInit(HidInit&&) = delete;
  HidInit& operator=(HidInit&&) = delete;
  ~HidInit() { api_.exit(); }

 private:
  HidApi& api_;
};

// The matching nodes, each path once (hidapi lists a node once per top-level usage).
std::vector<HidDeviceInfo> matching_nodes(HidApi& api, const HidUri& uri, std::vector<HidDeviceInfo>* all) {
  std::vector<HidDeviceInfo> listed = api.enumerate(uri.vendor_id, uri.product_id);
  std::vector<HidDeviceInfo> out;
  for (HidDeviceInfo& info : listed) {
    const bool ours = info.vendor_id == uri.vendor_id && info.product_id == uri.product_id;
    const bool seen =
        std::any_of(out.begin(), out.end(), [&](const HidDeviceInfo& o) { return o.path == info.path; });
    if (ours && !seen && (uri.serial.empty() || same_serial(info.serial, uri.serial))) {
      out.push_back(info);
    }
  }
  if (all != nullptr) {
    *all = std::move(listed);
  }
  return out;
}

// One attempt to open the unit: a handle for the reader and one for the writer.
struct Attempt {
  enum class Outcome : unsigned char { opened, not_found, denied, failed };
  Outcome outcome = Outcome::not_found;
  std::string path;
  int error = 0;
  std::unique_ptr<HidDevice> reader;
  std::unique_ptr<HidDevice> writer;
};

Attempt try_open(HidApi& api, const HidUri& uri, std::vector<HidDeviceInfo>* all) {
  Attempt a;
  const std::vector<HidDeviceInfo> nodes = matching_nodes(api, uri, all);
  if (nodes.empty()) {
    return a;
  }
  a.path = nodes.front().path;
  for (std::unique_ptr<HidDevice>* slot : {&a.reader, &a.writer}) {
    HidApi::Opened o = api.open_path(a.path);
    if (!o.device) {
      a.reader.reset();
      a.error = o.error;
      a.outcome = o.error == EACCES || o.error == EPERM ? Attempt::Outcome::denied
                  : gone(o.error)                       ? Attempt::Outcome::not_found
                                                        : Attempt::Outcome::failed;
      return a;
    }
    *slot = std::move(o.device);
  }
  a.outcome = Attempt::Outcome::opened;
  return a;
}

std::string not_found_message(std::string_view uri_text, const HidUri& uri,
                              const std::vector<HidDeviceInfo>& all) {
  std::string others;
  for (const HidDeviceInfo& info : all) {
    if (info.vendor_id == uri.vendor_id && info.product_id == uri.product_id) {
      others += fmt::format("{}{} (serial {})", others.empty() ? "" : ", ", info.path,
                            info.serial.empty() ? "none" : info.serial);
    }
  }
  return fmt::format(
      "no MR skin for {}: searched the hidraw nodes for {:04x}:{:04x}{}{}; check the USB cable and "
      "power, and run `mrskinctl list` to see the units reachable",
      uri_text, uri.vendor_id, uri.product_id,
      uri.serial.empty() ? "" : fmt::format(" with serial {}", uri.serial),
      others.empty() ? "" : fmt::format(" (found only {})", others));
}

int to_ms(Duration d) noexcept {
  const auto ms = std::chrono::ceil<std::chrono::milliseconds>(d).count();
  return static_cast<int>(std::clamp<std::int64_t>(ms, 1, 60'000));
}

class HidTransport final : public QueuedTransport {
 public:
  HidTransport(std::string_view uri_text, const HidTransportOptions& options, std::shared_ptr<HidApi> api)
      : QueuedTransport(std::string(uri_text), options.send_queue, options.receive_queue),
        uri_(parse_hid_uri(uri_text)),
        options_(options),
        api_(std::move(api)),
        init_(*api_),
        wake_(uri_text),
        read_timeout_ms_(to_ms(options.read_timeout)),
        backoff_min_(scaled_duration(options.reopen_backoff_min, options.time_scale)),
        backoff_max_(scaled_duration(options.reopen_backoff_max, options.time_scale)),
        permission_retry_(scaled_duration(options.permission_retry, options.time_scale)),
        backoff_(backoff_min_) {
    std::vector<HidDeviceInfo> all;
    Attempt a = try_open(*api_, uri_, &all);
    switch (a.outcome) {
      case Attempt::Outcome::opened:
        break;
      case Attempt::Outcome::not_found:
        throw DeviceNotFound(not_found_message(uri_text, uri_, all));
      case Attempt::Outcome::denied:
        throw PermissionDenied(
            fmt::format("cannot open {} for {}: {}", a.path, uri_text, permission_message(a.path)));
      case Attempt::Outcome::failed:
        throw Error(fmt::format("cannot open {} for {}: {}; run `mrskinctl list` to see what is wrong",
                                a.path, uri_text, errno_text(a.error)));
    }
    install(std::move(a));
    reader_thread_ = std::thread([this] {
      (void)::pthread_setname_np(::pthread_self(), "mrskin-hid-read");
      read_loop();
    });
    try {
      writer_thread_ = std::thread([this] {
        (void)::pthread_setname_np(::pthread_self(), "mrskin-hid-wr");
        write_loop();
      });
    } catch (...) {
      stop();
      throw;
    }
  }
  HidTransport(const HidTransport&) = delete;
  HidTransport& operator=(const HidTransport&) = delete;
  HidTransport(HidTransport&&) = delete;
  HidTransport& operator=(HidTransport&&) = delete;

  ~HidTransport() override { stop(); }

  [[nodiscard]] std::string problem() const {
    const std::lock_guard lock(problem_mutex_);
    return problem_;
  }

  // The unit's descriptors are full speed (usb.hpp): one 64-byte report a 1 ms frame each way.
  [[nodiscard]] std::optional<protocol::BusSpec> bus() const noexcept override {
    return protocol::default_bus_spec(protocol::BusKind::hid_full_speed);
  }

 private:
  [[nodiscard]] bool stopping() const noexcept { return stopping_.load(std::memory_order_acquire); }

  void stop() noexcept {
    stopping_.store(true, std::memory_order_release);
    wake_.signal();  // never cleared: every wait of both threads ends
    for (std::thread* t : {&reader_thread_, &writer_thread_}) {
      if (t->joinable()) {
        t->join();
      }
    }
  }

  // Waits up to d, or until shutdown.
  void nap(Duration d) const noexcept {
    pollfd p{wake_.fd(), POLLIN, 0};
    (void)::poll(&p, 1, to_ms(d));
  }

  void set_problem(std::string text) {
    const std::lock_guard lock(problem_mutex_);
    problem_ = std::move(text);
  }

  // Reader thread (or the constructor, before the threads start).
  void install(Attempt&& a) noexcept {
    {
      const std::lock_guard lock(write_mutex_);
      discard_outgoing();  // a send() that raced the unplug must not reach the unit now
      writer_ = std::move(a.writer);
      writer_failed_.store(false, std::memory_order_release);
    }
    reader_ = std::move(a.reader);
    path_ = std::move(a.path);
    backoff_ = backoff_min_;
    denied_since_.reset();
    set_state(TransportState::open);
  }

  // Reader thread: the unit is gone (or its handle wedged). Nothing queued for it survives.
  void lose() noexcept {
    set_state(TransportState::disconnected);
    {
      const std::lock_guard lock(write_mutex_);
      writer_.reset();
      writer_failed_.store(false, std::memory_order_release);
      discard_outgoing();  // consumer side of the queue, under the writer's lock
    }
    reader_.reset();
    next_attempt_ = clock_.now();  // at once: a wedged handle's unit is still there
  }

  // Reader thread, while disconnected: one reopen attempt when due.
  void reopen_step() {
    const TimePoint now = clock_.now();
    if (now < next_attempt_) {
      nap(std::min<Duration>(next_attempt_ - now, options_.read_timeout));
      return;
    }
    Attempt a = try_open(*api_, uri_, nullptr);
    switch (a.outcome) {
      case Attempt::Outcome::opened:
        set_problem({});
        install(std::move(a));
        return;
      case Attempt::Outcome::denied:
        if (!denied_since_) {
          denied_since_ = now;
        }
        if (now - *denied_since_ < permission_retry_) {
          next_attempt_ = now + backoff_min_;  // udev is still applying the rule
          return;
        }
        set_problem(permission_message(a.path));
        break;
      case Attempt::Outcome::not_found:
        denied_since_.reset();
        break;
      case Attempt::Outcome::failed:
        set_problem(fmt::format("cannot open {}: {}", a.path, errno_text(a.error)));
        break;
    }
    next_attempt_ = now + backoff_;
    backoff_ = std::min(backoff_ * 2, backoff_max_);
  }

  // A failed read: the unit is gone when hidapi saw the node hang up (no errno), the
  // errno says so, or the node vanished.
  [[nodiscard]] bool read_failure_means_gone(int error) const noexcept {
    return error == 0 || gone(error) || api_->access(path_) == ENOENT;
  }

  void read_loop() noexcept {
    int errors = 0;
    Datagram d;
    while (!stopping()) {
      if (!reader_) {
        try {
          reopen_step();
        } catch (...) {  // enumeration allocates: on bad_alloc, try again later
          nap(backoff_max_);
        }
        errors = 0;
        continue;
      }
      if (writer_failed_.load(std::memory_order_acquire)) {
        lose();
        continue;
      }
      const HidIoResult r = reader_->read_timeout(d.bytes, read_timeout_ms_);
      if (r.result > 0) {
        d.length = static_cast<std::uint16_t>(std::min(r.result, static_cast<int>(kMaxDatagramBytes)));
        deliver(d);
        errors = 0;
      } else if (r.result == 0) {
        errors = 0;  // nothing within the read timeout: the normal idle case
      } else if (read_failure_means_gone(r.error) || ++errors >= options_.errors_before_reopen) {
        lose();
      } else {
        counters_.io_errors.bump();
      }
    }
  }

  // Writer thread, under write_mutex_: one datagram as one hid_write() (65 bytes at full speed).
  void write_one(const Datagram& d, int& errors) noexcept {
    const std::size_t n = write_bytes(d.length);
    std::fill_n(report_.begin(), n, std::uint8_t{0});
    report_[0] = protocol::kHidReportId;
    std::copy_n(d.bytes.begin(), d.length, report_.begin() + 1);
    const HidIoResult r = writer_->write(std::span<const std::uint8_t>(report_).first(n));
    if (r.result == static_cast<int>(n)) {
      counters_.sent.bump();
      errors = 0;
      return;
    }
    if (r.result < 0 && gone(r.error)) {
      writer_failed_.store(true, std::memory_order_release);
      return;
    }
    (r.result < 0 && r.error == ETIMEDOUT ? counters_.timeouts : counters_.io_errors).bump();
    if (++errors >= options_.errors_before_reopen) {
      writer_failed_.store(true, std::memory_order_release);
    }
  }

  void write_loop() noexcept {
    std::array<pollfd, 2> fds{{{send_event_fd(), POLLIN, 0}, {wake_.fd(), POLLIN, 0}}};
    int errors = 0;
    while (!stopping()) {
      (void)::poll(fds.data(), fds.size(), -1);
      for (;;) {
        const std::lock_guard lock(write_mutex_);
        Datagram d;
        if (!take_outgoing(d)) {
          break;
        }
        if (!writer_ || writer_failed_.load(std::memory_order_acquire)) {
          discard_outgoing();  // the reader is closing the unit
          errors = 0;
          break;
        }
        write_one(d, errors);
      }
    }
  }

  HidUri uri_;
  HidTransportOptions options_;
  std::shared_ptr<HidApi> api_;
  HidInit init_;
  transports::EventFd wake_;
  int read_timeout_ms_;
  Duration backoff_min_;
  Duration backoff_max_;
  Duration permission_retry_;
  // The poll() waits run on real time, so the I/O thread dates its retries on it too.
  MonotonicClock clock_;
  std::atomic<bool> stopping_{false};

  // Reader thread only (the constructor before it starts).
  std::unique_ptr<HidDevice> reader_;
  std::string path_;
  Duration backoff_;
  TimePoint next_attempt_{};
  std::optional<TimePoint> denied_since_;

  // The writer's handle: written by the writer thread; replaced by the reader, under the lock.
  std::mutex write_mutex_;
  std::unique_ptr<HidDevice> writer_;
  std::array<std::uint8_t, kMaxWriteBytes> report_{};
  std::atomic<bool> writer_failed_{false};  // the writer's handle failed: the reader closes it

  mutable std::mutex problem_mutex_;
  std::string problem_;

  std::thread reader_thread_;
  std::thread writer_thread_;
};

// --- hidapi itself ---------------------------------------------------------------------------

// hidapi keeps its global error string without a lock and hid_init/hid_exit are process-wide:
// every enumerate, open and the init count go through this lock.
struct HidGlobal {
  std::mutex mutex;
  int users = 0;
};
HidGlobal& hid_global() noexcept {
  static HidGlobal g;
  return g;
}

class SystemHidDevice final : public HidDevice {
 public:
  explicit SystemHidDevice(hid_device* device) noexcept : device_(device) {}
  SystemHidDevice(const SystemHidDevice&) = delete;
  SystemHidDevice& operator=(const SystemHidDevice&) = delete;
  SystemHidDevice(SystemHidDevice&&) = delete;
  SystemHidDevice& operator=(SystemHidDevice&&) = delete;
  ~SystemHidDevice() override { hid_close(device_); }

  HidIoResult write(std::span<const std::uint8_t> data) noexcept override {
    errno = 0;
    const int r = hid_write(device_, data.data(), data.size());
    return {r, r < 0 ? errno : 0};
  }
  HidIoResult read_timeout(std::span<std::uint8_t> data, int timeout_ms) noexcept override {
    errno = 0;
    const int r = hid_read_timeout(device_, data.data(), data.size(), timeout_ms);
    return {r, r < 0 ? errno : 0};
  }

 private:
  hid_device* device_;
};

std::string narrow(const wchar_t* text) {
  std::string out;
  for (; text != nullptr && *text != L'\0'; ++text) {
    out += *text > 0 && *text < 0x80 ? static_cast<char>(*text) : '?';
  }
  return out;
}

class SystemHidApi final : public HidApi {
 public:
  bool init() noexcept override {
    const std::lock_guard lock(hid_global().mutex);
    if (hid_global().users == 0 && hid_init() != 0) {
      return false;
    }
    ++hid_global().users;
    return true;
  }
  void exit() noexcept override {
    const std::lock_guard lock(hid_global().mutex);
    if (--hid_global().users == 0) {
      (void)hid_exit();
    }
  }
  std::vector<HidDeviceInfo> enumerate(std::uint16_t vendor_id, std::uint16_t product_id) override {
    const std::lock_guard lock(hid_global().mutex);
    std::vector<HidDeviceInfo> out;
    hid_device_info* list = hid_enumerate(vendor_id, product_id);
    try {
      for (const hid_device_info* d = list; d != nullptr; d = d->next) {
        out.push_back(
            {d->path != nullptr ? d->path : "", d->vendor_id, d->product_id, narrow(d->serial_number)});
      }
    } catch (...) {
      hid_free_enumeration(list);
      throw;
    }
    hid_free_enumeration(list);
    return out;
  }
  Opened open_path(const std::string& path) override {
    const std::lock_guard lock(hid_global().mutex);
    errno = 0;
    hid_device* d = hid_open_path(path.c_str());
    if (d == nullptr) {
      const int error = errno;
      // errno is open()'s; should hidapi have lost it, ask the node itself.
      const int probe = error != 0 ? error : access(path);
      return {nullptr, probe != 0 ? probe : EIO};
    }
    return {std::make_unique<SystemHidDevice>(d), 0};
  }
  int access(const std::string& path) noexcept override {
    return ::access(path.c_str(), R_OK | W_OK) == 0 ? 0 : errno;
  }
};

}  // namespace

HidUri parse_hid_uri(std::string_view uri) {
  if (!uri.starts_with(kHidScheme)) {
    throw InvalidArgument(fmt::format("'{}' is not a hid:// URI (hid://VID:PID[?serial=XXXXXXXX])", uri));
  }
  HidUri parsed;
  std::string_view rest = uri.substr(kHidScheme.size());
  const auto q = rest.find('?');
  const std::string_view ids = rest.substr(0, q);
  std::string_view query = q == std::string_view::npos ? std::string_view{} : rest.substr(q + 1);
  if (!ids.empty()) {
    const auto colon = ids.find(':');
    if (colon == std::string_view::npos) {
      throw InvalidArgument(fmt::format("'{}': '{}' is not VID:PID (hex, e.g. hid://1209:4d52)", uri, ids));
    }
    parsed.vendor_id = parse_id("vendor ID", ids.substr(0, colon), uri);
    parsed.product_id = parse_id("product ID", ids.substr(colon + 1), uri);
  }
  while (!query.empty()) {
    const auto amp = query.find('&');
    const std::string_view pair = query.substr(0, amp);
    query = amp == std::string_view::npos ? std::string_view{} : query.substr(amp + 1);
    const auto eq = pair.find('=');
    const std::string_view key = pair.substr(0, eq);
    if (key != "serial") {
      throw InvalidArgument(
          fmt::format("'{}': parameter '{}' is unknown: hid:// takes only serial=XXXXXXXX", uri, key));
    }
    const std::string_view value = eq == std::string_view::npos ? std::string_view{} : pair.substr(eq + 1);
    const auto serial = protocol::parse_usb_serial(value);
    if (!serial) {
      throw InvalidArgument(fmt::format(
          "'{}': serial '{}' is not 8 hex digits (as `mrskinctl list` shows it, e.g. serial=4D520001)", uri,
          value));
    }
    parsed.serial = protocol::format_usb_serial(*serial);
  }
  return parsed;
}

std::string format_hid_uri(const HidUri& uri) {
  return fmt::format("hid://{:04x}:{:04x}{}", uri.vendor_id, uri.product_id,
                     uri.serial.empty() ? "" : "?serial=" + uri.serial);
}

std::shared_ptr<HidApi> make_system_hid_api() { return std::make_shared<SystemHidApi>(); }

std::unique_ptr<Transport> open_hid_transport(std::string_view uri, const HidTransportOptions& options) {
  return open_hid_transport(uri, options, make_system_hid_api());
}

std::unique_ptr<Transport> open_hid_transport(std::string_view uri, const HidTransportOptions& options,
                                              std::shared_ptr<HidApi> api) {
  if (!(std::isfinite(options.time_scale) && options.time_scale > 0.0) ||
      options.read_timeout <= Duration{0} || options.reopen_backoff_min <= Duration{0} ||
      options.reopen_backoff_max < options.reopen_backoff_min || options.permission_retry < Duration{0} ||
      options.errors_before_reopen < 1 || options.send_queue == 0 || options.receive_queue == 0) {
    throw InvalidArgument(fmt::format(
        "{}: HidTransportOptions need time_scale > 0, read_timeout > 0, 0 < reopen_backoff_min <= "
        "reopen_backoff_max, permission_retry >= 0, errors_before_reopen >= 1 and non-empty queues",
        uri));
  }
  if (!api) {
    throw InvalidArgument(fmt::format("{}: no HidApi given", uri));
  }
  return std::make_unique<HidTransport>(uri, options, std::move(api));
}

std::string hid_transport_problem(const Transport& transport) {
  const auto* hid = dynamic_cast<const HidTransport*>(&transport);
  return hid != nullptr ? hid->problem() : std::string{};
}

std::vector<DeviceListing> list_hid_devices(HidApi& api) {
  std::vector<DeviceListing> out;
  try {
    const HidInit init(api);
    for (const HidDeviceInfo& node : matching_nodes(api, HidUri{}, nullptr)) {
      DeviceListing l;
      l.bus = "hid";
      l.path = node.path;
      l.serial = node.serial;
      HidUri uri;
      if (const auto serial = protocol::parse_usb_serial(node.serial)) {
        uri.serial = protocol::format_usb_serial(*serial);
      }
      l.uri = format_hid_uri(uri);
      const int error = api.access(node.path);
      if (error == EACCES || error == EPERM) {
        l.problem = "permission denied";
        l.fix = permission_fix();
      } else if (error != 0) {
        l.problem = errno_text(error);
        l.fix = "replug the unit; `dmesg` shows what the kernel saw";
      }
      out.push_back(std::move(l));
    }
  } catch (const std::exception& e) {
    DeviceListing l;
    l.bus = "hid";
    l.uri = format_hid_uri(HidUri{});
    l.problem = e.what();
    l.fix = "install libhidapi-hidraw0 and libudev1 (sudo apt-get install libhidapi-hidraw0 libudev1)";
    out.push_back(std::move(l));
  }
  return out;
}

std::vector<DeviceListing> list_hid_devices() {
  const std::shared_ptr<HidApi> api = make_system_hid_api();
  return list_hid_devices(*api);
}

}  // namespace mrskin
