// Names of wire codes in the session's messages and logs. Private to the driver.
#pragma once

#include <cstdint>

#include "mrskin/protocol/messages.hpp"

namespace mrskin::session_names {

inline const char* quantity_name(std::uint8_t q) noexcept {
  switch (static_cast<protocol::SensorQuantity>(q)) {
    case protocol::SensorQuantity::displacement_m:
      return "displacement";
    case protocol::SensorQuantity::force_N:
      return "force";
    case protocol::SensorQuantity::pressure_Pa:
      return "pressure";
  }
  return "unknown";
}

inline const char* quantity_unit(std::uint8_t q) noexcept {
  switch (static_cast<protocol::SensorQuantity>(q)) {
    case protocol::SensorQuantity::displacement_m:
      return "m";
    case protocol::SensorQuantity::force_N:
      return "N";
    case protocol::SensorQuantity::pressure_Pa:
      return "Pa";
  }
  return "?";
}

inline const char* request_name(std::uint8_t r) noexcept {
  switch (static_cast<protocol::StateRequestCode>(r)) {
    case protocol::StateRequestCode::disable:
      return "disable";
    case protocol::StateRequestCode::enable:
      return "enable";
    case protocol::StateRequestCode::pause:
      return "pause";
    case protocol::StateRequestCode::estop:
      return "e-stop";
    case protocol::StateRequestCode::degauss:
      return "degauss";
  }
  return "unknown";
}

inline const char* config_key_name(std::uint16_t key) noexcept {
  switch (static_cast<protocol::ConfigKey>(key)) {
    case protocol::ConfigKey::profile:
      return "profile";
    case protocol::ConfigKey::calibration:
      return "calibration";
  }
  return "unknown key";
}

inline const char* config_status_name(std::uint8_t s) noexcept {
  switch (static_cast<protocol::ConfigStatus>(s)) {
    case protocol::ConfigStatus::ok:
      return "ok";
    case protocol::ConfigStatus::bad_key:
      return "bad key";
    case protocol::ConfigStatus::bad_range:
      return "bad range";
    case protocol::ConfigStatus::rejected:
      return "rejected";
    case protocol::ConfigStatus::busy:
      return "busy";
  }
  return "unknown status";
}

}  // namespace mrskin::session_names
