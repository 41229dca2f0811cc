#include "mrskin/protocol/messages.hpp"

#include <type_traits>

#include "validate.hpp"
#include "visit.hpp"

namespace mrskin::protocol {

MessageType type_of(const Message& m) noexcept {
  static constexpr MessageType kTypes[] = {
      MessageType::identify_request, MessageType::identity,    MessageType::valve_currents,
      MessageType::cell_targets,     MessageType::telemetry,   MessageType::time_sync,
      MessageType::status,           MessageType::heartbeat,   MessageType::state_request,
      MessageType::config_read,      MessageType::config_data, MessageType::config_write,
      MessageType::config_ack,       MessageType::usb_slots,   MessageType::sensor_deadband};
  static_assert(std::size(kTypes) == std::variant_size_v<Message>);
  return kTypes[m.index()];
}

namespace detail {
namespace {

Error check(const IdentifyRequest& /*m*/) noexcept { return Error::ok; }
Error check(const Identity& m) noexcept {
  if (m.current_max_counts > kCurrentCountMax || m.sensor_quantity > 2 || m.current_lsb_nA == 0 ||
      m.sensor_lsb_nano == 0) {
    return Error::out_of_range;
  }
  return Error::ok;
}
Error check(const ValveCurrents& m) noexcept {
  if (m.count == 0 || m.count > kMaxValveCurrents || m.first + m.count > 0xFFFF) {
    return Error::out_of_range;
  }
  for (std::size_t i = 0; i < m.count; ++i) {
    if (m.counts[i] > kCurrentCountMax) {
      return Error::out_of_range;
    }
  }
  return Error::ok;
}
Error check(const CellTargets& m) noexcept {
  if (m.count == 0 || m.count > kMaxCellTargets || m.first + m.count > 0xFFFF) {
    return Error::out_of_range;
  }
  for (std::size_t i = 0; i < m.count; ++i) {
    const CellTarget& t = m.targets[i];
    if (t.stiffness > kStiffnessCountMax || t.offset > kOffsetCountMax || t.ceiling > kCeilingCountMax ||
        t.validity > kValidityCountMax) {
      return Error::out_of_range;
    }
  }
  return Error::ok;
}
Error check(const Telemetry& m) noexcept {
  if (m.count == 0 || m.count > kMaxTelemetryValues || m.first + m.count > 0xFFFF) {
    return Error::out_of_range;
  }
  for (std::size_t i = 0; i < m.count; ++i) {
    if (m.counts[i] < kSensorCountMin || m.counts[i] > kSensorCountMax) {
      return Error::out_of_range;
    }
  }
  return Error::ok;
}
Error check(const TimeSync& /*m*/) noexcept { return Error::ok; }
Error check(const Status& m) noexcept {
  return (m.state > 3 || m.fault > 7) ? Error::out_of_range : Error::ok;
}
Error check(const Heartbeat& /*m*/) noexcept { return Error::ok; }
Error check(const StateRequest& m) noexcept { return m.request > 4 ? Error::out_of_range : Error::ok; }
Error check(const ConfigRead& m) noexcept {
  return (m.length == 0 || m.length > kMaxConfigBytes) ? Error::out_of_range : Error::ok;
}
Error check(const ConfigChunk& m) noexcept {
  if (m.length > kMaxConfigBytes || m.offset + m.length > m.total) {
    return Error::out_of_range;
  }
  return Error::ok;
}
Error check(const ConfigAck& m) noexcept { return m.status > 4 ? Error::out_of_range : Error::ok; }
Error check(const UsbSlots& m) noexcept {
  const bool interval_ok =
      m.interval_us == 125 || m.interval_us == 250 || m.interval_us == 500 || m.interval_us == 1000;
  if (m.report_bytes < kUsbSlotsMinReportBytes || m.report_bytes > kUsbSlotsMaxReportBytes ||
      m.reports_per_interval == 0 || m.reports_per_interval > kUsbSlotsMaxReportsPerInterval ||
      !interval_ok) {
    return Error::out_of_range;
  }
  return Error::ok;
}

Error check(const SensorDeadband& m) noexcept {
  return m.counts > kSensorDeadbandMaxCounts ? Error::out_of_range : Error::ok;
}

}  // namespace

Error validate(const Message& message) noexcept {
  return visit_nothrow<Error>([](const auto& m) noexcept { return check(m); }, message);
}

}  // namespace detail
}  // namespace mrskin::protocol
