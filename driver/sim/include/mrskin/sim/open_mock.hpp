// Opening the simulated unit by URI (mock://, see mrskin/driver/device.hpp for the syntax).
// Call register_mock_scheme() once at start-up: loading this library registers the scheme too,
// but a linker with --as-needed (Debian's default) drops a library none of whose symbols the
// program uses, and then mock:// is unknown.
#pragma once

#include <memory>
#include <string>
#include <string_view>

#include "mrskin/driver/device.hpp"
#include "mrskin/sim/export.hpp"
#include "mrskin/sim/mock_device.hpp"

namespace mrskin::sim {

struct MockUri {
  std::string profile;  // name or path as written ("" for the default)
  MockOptions options;
  // Without bus= (or with bus=profile): open_device models the bus the profile's [interface] names.
  bool profile_bus = true;
};
// Parses a mock:// URI; throws InvalidArgument naming the bad parameter. The profile is not
// loaded here (model::load_profile_with_text does that).
MRSKIN_SIM_API MockUri parse_mock_uri(std::string_view uri);

// Makes open_device() open mock:// URIs. Idempotent; setup only.
MRSKIN_SIM_API void register_mock_scheme();

// The mock behind a device opened with mock://; null for any other device.
MRSKIN_SIM_API std::shared_ptr<MockDevice> mock_of(const OpenedDevice& device) noexcept;

}  // namespace mrskin::sim
