// The framing of a device lease on mrskin-bridged's control socket (docs/daemon.md, "lease"): each
// datagram, both ways, is its length (u16, little-endian) then its bytes. The daemon names it in
// the lease's answer and the client (mrskinctl --bridge) refuses any other, so that a daemon and a
// client of different releases never misframe each other's datagrams.
#pragma once

#include <cstddef>
#include <string_view>

namespace mrskin::tools {

inline constexpr std::string_view kLeaseFraming = "u16le length, then the datagram, both ways";
inline constexpr std::size_t kLeaseLengthBytes = 2;

}  // namespace mrskin::tools
