#include "mrskin/driver/device.hpp"

#include <fcntl.h>
#include <fmt/format.h>
#include <sys/file.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <map>
#include <mutex>
#include <string>

#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/transports/can.hpp"
#include "mrskin/driver/transports/hid.hpp"
#include "mrskin/driver/transports/usb.hpp"

namespace mrskin {
namespace {

// One lock per unit, whichever bus names it: hid:// and usb:// reach the same USB unit (and
// usb:// detaches the kernel driver under hidraw), so both lock its VID:PID:serial.
std::string lock_name(std::string_view uri) {
  std::uint16_t vendor_id = 0;
  std::uint16_t product_id = 0;
  std::string serial;
  if (uri.starts_with("hid://")) {
    HidUri u = parse_hid_uri(uri);
    vendor_id = u.vendor_id;
    product_id = u.product_id;
    serial = std::move(u.serial);
  } else if (uri.starts_with("usb://")) {
    UsbUri u = parse_usb_uri(uri);
    vendor_id = u.vendor_id;
    product_id = u.product_id;
    serial = std::move(u.serial);
  } else if (uri.starts_with("can://")) {
    const CanUri u = parse_can_uri(uri);
    return fmt::format("can-{}-{}", u.interface, u.node);  // one session per node, either framing
  } else {
    return std::string(uri.substr(0, uri.find('?')));
  }
  return fmt::format("usb-{:04x}-{:04x}-{}", vendor_id, product_id, serial.empty() ? "any" : serial);
}

}  // namespace

DeviceLock::DeviceLock(std::string_view uri) {
  std::string name = lock_name(uri);
  if (uri.starts_with("mock://")) {
    name = fmt::format("{}@{}", name, ::getpid());
    per_process_ = true;
  }
  for (char& c : name) {
    if (std::isalnum(static_cast<unsigned char>(c)) == 0 && c != '@' && c != '-') {
      c = '_';
    }
  }
  const char* runtime = std::getenv("XDG_RUNTIME_DIR");
  path_ = fmt::format("{}/mrskin-{}.lock", runtime != nullptr && *runtime != '\0' ? runtime : "/tmp", name);
  fd_ =
      ::open(path_.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0600);  // NOLINT(cppcoreguidelines-pro-type-vararg)
  if (fd_ < 0) {
    throw PermissionDenied(
        fmt::format("cannot create the ownership lock {}: {}: set XDG_RUNTIME_DIR to a writable "
                    "directory",
                    path_, std::strerror(errno)));
  }
  if (::flock(fd_, LOCK_EX | LOCK_NB) != 0) {
    std::string owner = "another session";
    std::ifstream in(path_);
    long pid = 0;
    if (in >> pid && pid > 0) {
      std::ifstream comm(fmt::format("/proc/{}/comm", pid));
      std::string command;
      std::getline(comm, command);
      owner = command.empty() ? fmt::format("process {}", pid) : fmt::format("process {} ({})", pid, command);
    }
    ::close(fd_);
    fd_ = -1;
    throw DeviceBusy(fmt::format(
        "{} is owned by {}: stop it, or talk to the device through the running bridge (mrskinctl --bridge)",
        uri, owner));
  }
  const std::string pid = fmt::format("{}\n", ::getpid());
  if (::ftruncate(fd_, 0) != 0 || ::write(fd_, pid.data(), pid.size()) != static_cast<ssize_t>(pid.size())) {
    // The lock holds without the PID; only the message to a second opener gets vaguer.
  }
}

DeviceLock::~DeviceLock() {
  if (fd_ >= 0) {
    if (per_process_) {
      ::unlink(path_.c_str());  // nobody else can want a lock named after our PID
    }
    ::flock(fd_, LOCK_UN);
    ::close(fd_);
  }
}

namespace {

// A real bus: the unit's lock, then its transport (scaled like the session), then the session.
template <class TransportOptions>
OpenedDevice open_on_bus(std::string_view uri, Clock& clock, const SessionOptions& session_options,
                         std::unique_ptr<Transport> (*open_transport)(std::string_view,
                                                                      const TransportOptions&)) {
  OpenedDevice opened;
  opened.lock = std::make_unique<DeviceLock>(uri);
  TransportOptions transport_options;
  transport_options.time_scale = session_options.time_scale;
  opened.session =
      std::make_unique<DeviceSession>(open_transport(uri, transport_options), clock, session_options);
  return opened;
}

}  // namespace

namespace {

struct SchemeRegistry {
  std::mutex mutex;
  std::map<std::string, DeviceOpener, std::less<>> openers;
};

SchemeRegistry& scheme_registry() {
  static SchemeRegistry registry;
  return registry;
}

DeviceOpener registered_opener(std::string_view scheme) {
  SchemeRegistry& registry = scheme_registry();
  const std::lock_guard lock(registry.mutex);
  const auto it = registry.openers.find(scheme);
  return it == registry.openers.end() ? nullptr : it->second;
}

[[noreturn]] void throw_not_a_device_uri(std::string_view uri) {
  if (uri.starts_with("mock://")) {
    throw InvalidArgument("'" + std::string(uri) +
                          "' needs the simulation library: link mrskin::sim (the simulated unit is not "
                          "part of mrskin::driver) and call mrskin::sim::register_mock_scheme() once at "
                          "start-up");
  }
  throw InvalidArgument(
      "'" + std::string(uri) +
      "' is not a device URI: use mock://[PROFILE][?seed=N], hid://VID:PID[?serial=S], "
      "usb://VID:PID[?serial=S] or can://IFACE?node=N[&fd=1] (mrskinctl list shows the units found)");
}

double time_scale_from_environment(double fallback) {
  const char* text = std::getenv("MRSKIN_TIME_SCALE");
  if (text == nullptr || *text == '\0') {
    return fallback;
  }
  const std::string_view value(text);
  double scale = 0.0;
  const auto r = std::from_chars(value.data(), value.data() + value.size(), scale);
  if (r.ec != std::errc{} || r.ptr != value.data() + value.size()) {
    throw InvalidArgument("MRSKIN_TIME_SCALE has bad value '" + std::string(value) +
                          "': give a number (1 in real time, more for slow machines)");
  }
  return scale;
}

}  // namespace

void register_device_scheme(std::string_view scheme, DeviceOpener opener) {
  SchemeRegistry& registry = scheme_registry();
  const std::lock_guard lock(registry.mutex);
  registry.openers.insert_or_assign(std::string(scheme), opener);
}

OpenedDevice open_device(std::string_view uri, Clock& clock, const OpenOptions& options) {
  SessionOptions session_options = options.session;
  session_options.time_scale = time_scale_from_environment(session_options.time_scale);
  if (const auto colon = uri.find("://"); colon != std::string_view::npos) {
    if (const DeviceOpener opener = registered_opener(uri.substr(0, colon)); opener != nullptr) {
      return opener(uri, clock, options, session_options);
    }
  }
  if (uri.starts_with("hid://")) {
    return open_on_bus<HidTransportOptions>(uri, clock, session_options, &open_hid_transport);
  }
  if (uri.starts_with("usb://")) {
    return open_on_bus<UsbTransportOptions>(uri, clock, session_options, &open_usb_transport);
  }
  if (uri.starts_with("can://")) {
    return open_on_bus<CanTransportOptions>(uri, clock, session_options, &open_can_transport);
  }
  throw_not_a_device_uri(uri);
}

void check_device_uri(std::string_view uri) {
  if (const auto colon = uri.find("://"); colon != std::string_view::npos) {
    if (registered_opener(uri.substr(0, colon)) != nullptr) {
      return;  // a registered scheme checks its URI when it opens
    }
  }
  if (uri.starts_with("hid://")) {
    (void)parse_hid_uri(uri);
  } else if (uri.starts_with("usb://")) {
    (void)parse_usb_uri(uri);
  } else if (uri.starts_with("can://")) {
    (void)parse_can_uri(uri);
  } else {
    throw_not_a_device_uri(uri);
  }
}

}  // namespace mrskin
