#include "mrskin/driver/device.hpp"

#include <charconv>
#include <string>

#include "mrskin/driver/errors.hpp"

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

}  // namespace

MockOptions parse_mock_uri(std::string_view uri, int& rows, int& cols) {
  MockOptions options;
  rows = 5;
  cols = 5;
  constexpr std::string_view scheme = "mock://";
  uri.remove_prefix(scheme.size());
  const auto q = uri.find('?');
  const std::string_view profile = uri.substr(0, q);
  if (!profile.empty() && profile != "default") {
    throw InvalidArgument(
        "mock:// profile '" + std::string(profile) +
        "' is unknown: device profiles arrive with the device model; use mock:// for the 5 x 5");
  }
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
    } else if (key == "rows") {
      rows = parse_number<int>(key, value);
    } else if (key == "cols") {
      cols = parse_number<int>(key, value);
    } else {
      throw InvalidArgument("mock:// parameter '" + std::string(key) +
                            "' is unknown: use seed, perturbation, rows or cols");
    }
  }
  return options;
}

OpenedDevice open_device(std::string_view uri, Clock& clock, const OpenOptions& options) {
  OpenedDevice opened;
  if (uri.starts_with("mock://")) {
    int rows = 5;
    int cols = 5;
    const MockOptions mock_options = parse_mock_uri(uri, rows, cols);
    opened.mock = MockDevice::make_placeholder(mock_options, rows, cols);
    if (!options.synchronous_mock) {
      opened.mock->start(clock);
    }
    opened.session = std::make_unique<DeviceSession>(opened.mock->connect(options.synchronous_mock), clock,
                                                     options.session);
    return opened;
  }
  for (const std::string_view scheme : {"hid://", "usb://", "can://"}) {
    if (uri.starts_with(scheme)) {
      throw InvalidArgument("'" + std::string(uri) + "': the " + std::string(scheme.substr(0, 3)) +
                            " transport is not in this build yet; use mock://");
    }
  }
  throw InvalidArgument("'" + std::string(uri) + "' is not a device URI: use mock://[?seed=N]");
}

}  // namespace mrskin
