// Library and protocol versions, for the host to log and compare.
#pragma once

#include <string_view>

#include "mrskin/driver/export.hpp"

namespace mrskin {

// "MAJOR.MINOR.PATCH" of the installed mrskin libraries.
MRSKIN_DRIVER_API std::string_view library_version() noexcept;
// Major and minor version of the wire protocol this library speaks.
MRSKIN_DRIVER_API int protocol_version_major() noexcept;
MRSKIN_DRIVER_API int protocol_version_minor() noexcept;

}  // namespace mrskin
