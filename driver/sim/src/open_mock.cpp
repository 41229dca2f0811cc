#include "mrskin/sim/open_mock.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <optional>
#include <string>

#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/model/profile.hpp"

namespace mrskin::sim {
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

MockBusKind parse_bus_kind(std::string_view value) {
  for (const MockBusKind kind :
       {MockBusKind::none, MockBusKind::hid_fs, MockBusKind::hid_hs, MockBusKind::can, MockBusKind::canfd}) {
    if (value == to_string(kind)) {
      return kind;
    }
  }
  throw InvalidArgument(fmt::format(
      "mock:// bus '{}' is unknown: use none, hid-fs, hid-hs, can, canfd or profile (the default: "
      "the bus the profile's [interface] names)",
      value));
}

MockBusKind mock_bus_kind_of(std::optional<protocol::BusKind> bus) noexcept {
  if (!bus) {
    return MockBusKind::none;
  }
  switch (*bus) {
    case protocol::BusKind::hid_high_speed:
      return MockBusKind::hid_hs;
    case protocol::BusKind::can_classic:
      return MockBusKind::can;
    case protocol::BusKind::can_fd:
      return MockBusKind::canfd;
    case protocol::BusKind::hid_full_speed:
      break;
  }
  return MockBusKind::hid_fs;
}

// bitrate=B for can, B or B/D for canfd (nominal/data), bits per second.
void parse_bitrate(std::string_view value, MockBusOptions& bus) {
  if (bus.kind != MockBusKind::can && bus.kind != MockBusKind::canfd) {
    throw InvalidArgument(
        "mock:// bitrate applies to bus=can (bitrate=B) and bus=canfd (bitrate=B/D), not bus=" +
        std::string(to_string(bus.kind)));
  }
  const auto slash = value.find('/');
  if (slash != std::string_view::npos && bus.kind == MockBusKind::can) {
    throw InvalidArgument(
        "mock:// bitrate for bus=can is one rate in bit/s (e.g. bitrate=500000); B/D is for canfd");
  }
  const auto rate = [](std::string_view text, double max_bit_per_s) {
    const auto r = parse_number<double>("bitrate", text);
    if (!(r >= 10e3 && r <= max_bit_per_s)) {
      throw InvalidArgument(
          fmt::format("mock:// bitrate '{}' is outside 10000 to {:.0f} bit/s", text, max_bit_per_s));
    }
    return r;
  };
  bus.nominal_bitrate_bit_per_s = rate(value.substr(0, slash), 1e6);
  if (slash != std::string_view::npos) {
    bus.data_bitrate_bit_per_s = rate(value.substr(slash + 1), 12e6);
    if (bus.data_bitrate_bit_per_s < bus.nominal_bitrate_bit_per_s) {
      throw InvalidArgument("mock:// bitrate B/D: the data rate D is at least the nominal rate B");
    }
  }
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
  std::string_view bitrate;  // read once the bus is known, wherever it comes in the query
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
    } else if (key == "physics_dt") {
      options.physics_dt_s = parse_number<double>(key, value);
      if (!(options.physics_dt_s >= 1e-5 && options.physics_dt_s <= options.telemetry_period_s)) {
        throw InvalidArgument(fmt::format(
            "mock:// physics_dt must be in [1e-5, {}] s (the plant's substep, at most the telemetry period)",
            options.telemetry_period_s));
      }
    } else if (key == "protocol_major") {
      const auto major = parse_number<unsigned>(key, value);
      if (major < 1 || major > 255) {
        throw InvalidArgument("mock:// protocol_major must be in [1, 255]");
      }
      options.protocol_major = static_cast<std::uint8_t>(major);
    } else if (key == "protocol_minor") {
      const auto minor = parse_number<unsigned>(key, value);
      if (minor > protocol::kVersionMinor) {
        throw InvalidArgument(
            fmt::format("mock:// protocol_minor must be in [0, {}]", protocol::kVersionMinor));
      }
      options.protocol_minor = static_cast<std::uint8_t>(minor);
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
    } else if (key == "bus") {
      parsed.profile_bus = value == "profile";
      options.bus.kind = parsed.profile_bus ? MockBusKind::none : parse_bus_kind(value);
    } else if (key == "report_bytes") {
      const auto bytes = parse_number<double>("report_bytes", value);
      if (!(bytes >= 64 && bytes <= 1024) || bytes != std::floor(bytes)) {
        throw InvalidArgument(fmt::format(
            "mock:// report_bytes '{}' is not a whole number of bytes from 64 to 1024 (the reports a "
            "high-speed unit declares)",
            value));
      }
      options.bus.usb_report_bytes = static_cast<std::size_t>(bytes);
    } else if (key == "deadband") {
      const auto counts = parse_number<double>("deadband", value);
      if (!(counts >= 0 && counts <= 100) || counts != std::floor(counts)) {
        throw InvalidArgument(fmt::format(
            "mock:// deadband '{}' is not a whole number of sensor counts from 0 (off) to 100", value));
      }
      options.sensor_deadband_counts = static_cast<int>(counts);
    } else if (key == "bitrate") {
      bitrate = value;
      if (value.empty()) {
        throw InvalidArgument("mock:// bitrate needs a value: B for can, B or B/D for canfd, in bit/s");
      }
    } else if (key == "rows" || key == "cols") {
      throw InvalidArgument("mock:// parameter '" + std::string(key) +
                            "' is gone: the grid comes from the device profile; name one "
                            "(mock://fingertip-16x16) or give a profile file (mock:///path/to/unit.toml)");
    } else {
      throw InvalidArgument("mock:// parameter '" + std::string(key) +
                            "' is unknown: use seed, perturbation, faults, time_scale, bipolar, "
                            "protocol_major, protocol_minor, finger, bus, bitrate, report_bytes or deadband");
    }
  }
  if (!bitrate.empty()) {
    parse_bitrate(bitrate, options.bus);
  }
  return parsed;
}

namespace {

OpenedDevice open_mock(std::string_view uri, Clock& clock, const OpenOptions& options,
                       const SessionOptions& session_options) {
  MockUri parsed = parse_mock_uri(uri);
  const model::LoadedProfile profile = model::load_profile_with_text(parsed.profile);
  if (parsed.profile_bus) {
    parsed.options.bus.kind = mock_bus_kind_of(profile.profile.bus);
  }
  if (parsed.options.bus.usb_report_bytes != 0 && parsed.options.bus.kind != MockBusKind::hid_hs) {
    throw InvalidArgument(
        fmt::format("mock:// report_bytes applies to a high-speed unit (bus=hid-hs), not bus={}",
                    to_string(parsed.options.bus.kind)));
  }
  OpenedDevice opened;
  opened.lock = std::make_unique<DeviceLock>(uri);
  parsed.options.time_scale = std::max(parsed.options.time_scale, session_options.time_scale);
  std::shared_ptr<MockDevice> mock = MockDevice::make(parsed.options, profile);
  if (!options.synchronous_mock) {
    mock->start(clock);
  }
  opened.session = std::make_unique<DeviceSession>(mock->connect(options.synchronous_mock, &clock), clock,
                                                   session_options);
  opened.simulation = std::move(mock);
  return opened;
}

// Loading this library makes mock:// available to every open_device() of the process.
[[maybe_unused]] const bool kRegisteredAtLoad = [] {
  register_device_scheme("mock", &open_mock);
  return true;
}();

}  // namespace

void register_mock_scheme() { register_device_scheme("mock", &open_mock); }

std::shared_ptr<MockDevice> mock_of(const OpenedDevice& device) noexcept {
  return std::dynamic_pointer_cast<MockDevice>(device.simulation);
}

}  // namespace mrskin::sim
