// Library and protocol versions, for the host to log and compare.
#pragma once

#include <string_view>

namespace mrskin {

// "MAJOR.MINOR.PATCH" of the installed mrskin libraries.
std::string_view library_version() noexcept;
// Major and minor version of the wire protocol this library speaks.
int protocol_version_major() noexcept;
int protocol_version_minor() noexcept;

}  // namespace mrskin
