// Typed exceptions thrown at setup only (open, configure). Every message says what to
// do about it. The real-time path never throws: it returns ResultCode.
#pragma once

#include <stdexcept>
#include <string>

#include "mrskin/driver/export.hpp"

namespace mrskin {

class MRSKIN_DRIVER_API Error : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};
// A URI, option or profile value that cannot be used.
class MRSKIN_DRIVER_API InvalidArgument : public Error {
 public:
  using Error::Error;
};
// A profile name that is in none of the profile directories; the message lists the search path
// and the names available there.
class MRSKIN_DRIVER_API ProfileNotFound : public InvalidArgument {
 public:
  using InvalidArgument::InvalidArgument;
};
// A loop rate whose traffic the unit's bus cannot carry (DeviceSession's bus budget); the message
// names the highest rate this bus carries and the buses that carry the one asked for.
class MRSKIN_DRIVER_API BusOverloaded : public InvalidArgument {
 public:
  using InvalidArgument::InvalidArgument;
};
// No device answers at the given address.
class MRSKIN_DRIVER_API DeviceNotFound : public Error {
 public:
  using Error::Error;
};
// The OS refused access (udev rule, group, capability).
class MRSKIN_DRIVER_API PermissionDenied : public Error {
 public:
  using Error::Error;
};
// The device speaks another protocol version; the message names both.
class MRSKIN_DRIVER_API ProtocolMismatch : public Error {
 public:
  using Error::Error;
};
// Another process (or another session in this one) owns the device.
class MRSKIN_DRIVER_API DeviceBusy : public Error {
 public:
  using Error::Error;
};
// The device did not answer in time during setup.
class MRSKIN_DRIVER_API Timeout : public Error {
 public:
  using Error::Error;
};

// Return codes of calls allowed on the real-time path.
enum class ResultCode : unsigned char {
  ok = 0,
  would_block,    // queue full or nothing to read; try next tick
  not_open,       // no device session
  invalid_value,  // NaN, Inf or out of range: nothing was sent
  device_fault,   // device reports FAULT; enable() clears it
  disconnected,   // transport lost
  stale,          // input older than its validity
};

constexpr const char* to_string(ResultCode c) noexcept {
  switch (c) {
    case ResultCode::ok:
      return "ok";
    case ResultCode::would_block:
      return "would block";
    case ResultCode::not_open:
      return "not open";
    case ResultCode::invalid_value:
      return "invalid value";
    case ResultCode::device_fault:
      return "device fault";
    case ResultCode::disconnected:
      return "disconnected";
    case ResultCode::stale:
      return "stale";
  }
  return "unknown";
}

}  // namespace mrskin
