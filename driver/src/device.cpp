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
#include <string>

#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/transports/can.hpp"
#include "mrskin/driver/transports/hid.hpp"
#include "mrskin/driver/transports/usb.hpp"

namespace mrskin {
namespace {

template <class T>
T parse_number(std::string_view key, std::string_view text) {
  T value{};
  const auto* end = text.data() + text.size();
  const auto r = std::from_chars(text.data(), end, value);
  if (r.ec != std::errc{} || r.ptr != end) {
    throw InvalidArgument("mock:// parameter '" + std::string(key) + "' has bad value '" + std::string(text) +
                          "'");
  }
  return value;
}

// faults=drop:P,dup:P,corrupt:P,reorder:P,delay:S,disconnect:AT+FOR,stuck:N,noisy:N,offset:N,leak:V,
//        overheat:N,busoff:AT
MockFaults parse_faults(std::string_view list) {
  MockFaults f;
  while (!list.empty()) {
    const auto comma = list.find(',');
    const std::string_view item = list.substr(0, comma);
    list = comma == std::string_view::npos ? std::string_view{} : list.substr(comma + 1);
    const auto colon = item.find(':');
    if (colon == std::string_view::npos) {
      throw InvalidArgument("mock:// fault '" + std::string(item) + "' needs a value (name:value)");
    }
    const std::string_view name = item.substr(0, colon);
    const std::string_view value = item.substr(colon + 1);
    // An index of a sensor or valve: the unit's count is checked when the mock is built.
    auto index = [&](std::string_view text) {
      const int i = parse_number<int>(name, text);
      if (i < 0 || i > 65535) {
        throw InvalidArgument("mock:// fault '" + std::string(name) +
                              "' names a sensor or valve index (0, 1, ...)");
      }
      return i;
    };
    // Seconds: finite, 0 to an hour.
    auto seconds = [&](std::string_view text, bool zero_ok) {
      const auto t = parse_number<double>(name, text);
      if (!(std::isfinite(t) && (zero_ok ? t >= 0.0 : t > 0.0) && t <= 3600.0)) {
        throw InvalidArgument("mock:// fault '" + std::string(name) + "' takes seconds in " +
                              (zero_ok ? "[0, 3600]" : "(0, 3600]") + ", not '" + std::string(text) + "'");
      }
      return t;
    };
    auto probability = [&](double& out) {
      out = parse_number<double>(name, value);
      if (!(out >= 0.0 && out <= 1.0)) {
        throw InvalidArgument("mock:// fault '" + std::string(name) + "' is a probability in [0, 1]");
      }
    };
    if (name == "drop") {
      probability(f.drop_probability);
    } else if (name == "dup") {
      probability(f.duplicate_probability);
    } else if (name == "corrupt") {
      probability(f.corrupt_probability);
    } else if (name == "reorder") {
      probability(f.reorder_probability);
    } else if (name == "delay") {
      f.delay_s = seconds(value, true);
    } else if (name == "disconnect") {
      const auto plus = value.find('+');
      if (plus == std::string_view::npos) {
        throw InvalidArgument("mock:// fault 'disconnect' is AT+FOR, in seconds (e.g. disconnect:2+0.5)");
      }
      f.disconnect_at_s = seconds(value.substr(0, plus), true);
      f.disconnect_for_s = seconds(value.substr(plus + 1), false);
    } else if (name == "stuck") {
      f.stuck_sensor = index(value);
    } else if (name == "noisy") {
      f.noisy_sensor = index(value);
    } else if (name == "offset") {
      f.offset_sensor = index(value);
    } else if (name == "overheat") {
      const auto plus = value.find('+');
      f.overheat_valve = index(value.substr(0, plus));
      if (plus != std::string_view::npos) {
        f.overheat_for_s = seconds(value.substr(plus + 1), false);
      }
    } else if (name == "busoff") {
      f.bus_off_at_s = seconds(value, true);
    } else if (name == "leak") {
      f.leak_valve = index(value);
    } else {
      throw InvalidArgument("mock:// fault '" + std::string(name) +
                            "' is unknown: use drop, dup, corrupt, reorder, delay, disconnect, stuck, noisy, "
                            "offset, overheat, busoff or leak");
    }
  }
  return f;
}

}  // namespace

MockUri parse_mock_uri(std::string_view uri) {
  MockUri parsed;
  MockOptions& options = parsed.options;
  constexpr std::string_view scheme = "mock://";
  if (!uri.starts_with(scheme)) {
    throw InvalidArgument("'" + std::string(uri) + "' is not a mock:// URI");
  }
  uri.remove_prefix(scheme.size());
  const auto q = uri.find('?');
  parsed.profile = std::string(uri.substr(0, q));
  std::string_view query = q == std::string_view::npos ? std::string_view{} : uri.substr(q + 1);
  while (!query.empty()) {
    const auto amp = query.find('&');
    const std::string_view pair = query.substr(0, amp);
    query = amp == std::string_view::npos ? std::string_view{} : query.substr(amp + 1);
    const auto eq = pair.find('=');
    if (eq == std::string_view::npos) {
      throw InvalidArgument("mock:// parameter '" + std::string(pair) + "' needs a value (key=value)");
    }
    const std::string_view key = pair.substr(0, eq);
    const std::string_view value = pair.substr(eq + 1);
    if (key == "seed") {
      options.seed = parse_number<std::uint64_t>(key, value);
    } else if (key == "perturbation") {
      options.perturbation = parse_number<double>(key, value);
      if (options.perturbation < 0.0 || options.perturbation >= 0.9) {
        throw InvalidArgument("mock:// perturbation must be in [0, 0.9)");
      }
    } else if (key == "faults") {
      options.faults = parse_faults(value);
    } else if (key == "time_scale") {
      options.time_scale = parse_number<double>(key, value);
      if (!(options.time_scale >= 1.0 && options.time_scale <= 1000.0)) {
        throw InvalidArgument("mock:// time_scale must be in [1, 1000]");
      }
    } else if (key == "protocol_major") {
      const auto major = parse_number<unsigned>(key, value);
      if (major < 1 || major > 255) {
        throw InvalidArgument("mock:// protocol_major must be in [1, 255]");
      }
      options.protocol_major = static_cast<std::uint8_t>(major);
    } else if (key == "bipolar") {
      if (value != "0" && value != "1") {
        throw InvalidArgument("mock:// bipolar must be 0 (a unipolar coil driver: no degauss) or 1");
      }
      options.bipolar_driver = value == "1";
    } else if (key == "finger") {
      const bool name_chars = std::all_of(value.begin(), value.end(), [](char c) {
        return (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '_' || c == '-';
      });
      if (value.empty() || value.size() > 64 || !name_chars) {
        throw InvalidArgument("mock:// finger must name a scene (mrskin-bridged --help lists them), not '" +
                              std::string(value) + "'");
      }
      options.finger_scene = std::string(value);
    } else if (key == "rows" || key == "cols") {
      throw InvalidArgument("mock:// parameter '" + std::string(key) +
                            "' is gone: the grid comes from the device profile; name one "
                            "(mock://fingertip-16x16) or give a profile file (mock:///path/to/unit.toml)");
    } else {
      throw InvalidArgument("mock:// parameter '" + std::string(key) +
                            "' is unknown: use seed, perturbation, faults, time_scale, bipolar, "
                            "protocol_major or finger");
    }
  }
  return parsed;
}

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

OpenedDevice open_device(std::string_view uri, Clock& clock, const OpenOptions& options) {
  OpenedDevice opened;
  SessionOptions session_options = options.session;
  if (const char* scale = std::getenv("MRSKIN_TIME_SCALE"); scale != nullptr && *scale != '\0') {
    session_options.time_scale = parse_number<double>("MRSKIN_TIME_SCALE", scale);
  }
  if (uri.starts_with("mock://")) {
    MockUri parsed = parse_mock_uri(uri);
    const LoadedProfile profile = load_profile_with_text(parsed.profile);
    opened.lock = std::make_unique<DeviceLock>(uri);
    parsed.options.time_scale = std::max(parsed.options.time_scale, session_options.time_scale);
    opened.mock = MockDevice::make(parsed.options, profile);
    if (!options.synchronous_mock) {
      opened.mock->start(clock);
    }
    opened.session = std::make_unique<DeviceSession>(opened.mock->connect(options.synchronous_mock, &clock),
                                                     clock, session_options);
    return opened;
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
  throw InvalidArgument(
      "'" + std::string(uri) +
      "' is not a device URI: use mock://[PROFILE][?seed=N], hid://VID:PID[?serial=S], "
      "usb://VID:PID[?serial=S] or can://IFACE?node=N[&fd=1] (mrskinctl list shows the units found)");
}

}  // namespace mrskin
