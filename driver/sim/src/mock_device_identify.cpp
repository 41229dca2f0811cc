// The unit's answer to an IdentifyRequest: its Identity and, to a 1.2 host, its UsbSlots and
// SensorDeadband (docs/protocol.md).
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <optional>

#include "mock_device_impl.hpp"
#include "mrskin/protocol/packed_report.hpp"

namespace mrskin::sim {
namespace proto = mrskin::protocol;

namespace {

constexpr std::uint8_t kFirmwareMajor = 0;
constexpr std::uint8_t kFirmwareMinor = 2;
constexpr std::uint8_t kFirmwarePatch = 0;

proto::SensorQuantity wire_quantity(model::SensorQuantity q) noexcept {
  switch (q) {
    case model::SensorQuantity::displacement:
      return proto::SensorQuantity::displacement_m;
    case model::SensorQuantity::force:
      return proto::SensorQuantity::force_N;
    case model::SensorQuantity::pressure:
      return proto::SensorQuantity::pressure_Pa;
  }
  return proto::SensorQuantity::displacement_m;
}

}  // namespace

void MockDevice::Impl::answer_identify(const proto::IdentifyRequest& request) noexcept {
  // The Identity goes first in its report: a host reads it before it knows the unit packs.
  // Packing follows from this request on, as both sides declared: a 1.2 host reads the UsbSlots
  // and the status packed behind the Identity. When every slot carries a sample, the Identity's
  // report takes the next sample's slot (that sample is skipped: emit_telemetry), and what the
  // previous session left waiting for telemetry (status, echoes) is dropped rather than sent in a
  // slot of its own (a status follows the Identity).
  const bool packs = proto::reads_packed_reports(options_.protocol_major, options_.protocol_minor) &&
                     proto::reads_packed_reports(request.host_major, request.host_minor);
  const bool tight = slots_taken_by_samples();
  if (tight) {
    report_.length = 0;
    held_status_at_ = kNoHeldStatus;
  } else {
    flush_report();
  }
  packing_ = packs;
  pending_read_count_ = 0;  // a new session asks again
  proto::Identity id;
  id.fw_major = kFirmwareMajor;
  id.fw_minor = kFirmwareMinor;
  id.fw_patch = kFirmwarePatch;
  id.rows = static_cast<std::uint8_t>(layout_.rows());
  id.cols = static_cast<std::uint8_t>(layout_.cols());
  id.fluid_cells = static_cast<std::uint16_t>(layout_.fluid_cell_count());
  id.valves = static_cast<std::uint16_t>(layout_.valve_count());
  id.sensors = static_cast<std::uint16_t>(sensor_si_.size());
  id.serial = options_.serial;
  id.proto_major = options_.protocol_major;
  id.proto_minor = options_.protocol_minor;
  id.current_lsb_nA = static_cast<std::uint32_t>(std::lround(current_lsb_A_ * 1e9));
  id.current_max_counts = static_cast<std::uint16_t>(
      std::min<long>(std::lround(max_current_A_ / current_lsb_A_), proto::kCurrentCountMax));
  id.sensor_quantity = static_cast<std::uint8_t>(wire_quantity(profile_.sensors.front().quantity));
  id.sensor_lsb_nano = static_cast<std::uint32_t>(std::lround(sensor_lsb_ * 1e9));
  id.heartbeat_timeout_ms =
      static_cast<std::uint16_t>(std::lround(options_.heartbeat_timeout_s * options_.time_scale * 1e3));
  id.telemetry_rate_hz = static_cast<std::uint16_t>(std::lround(1.0 / options_.telemetry_period_s));
  report_capacity_ = proto::kHidReportBytes;  // the Identity's report: the host assumes full speed
  send_message(id, /*hold=*/true);
  packing_ = packs;
  const std::optional<proto::UsbInterruptSlots> slots = declared_usb_slots(options_.bus);
  if (packs && slots) {
    // 1.2 on USB: the unit declares its reports, then uses them (docs/protocol.md, UsbSlots).
    send_message(proto::usb_slots_message(*slots), /*hold=*/true);
  }
  // 1.2: the deadband, declared before it applies; every block goes whole first.
  std::fill(block_sent_counts_.begin(), block_sent_counts_.end(), kNoBlockSent);
  if (packs && sensor_deadband_counts_ > 0) {
    send_message(proto::SensorDeadband{static_cast<std::uint8_t>(sensor_deadband_counts_)}, /*hold=*/true);
  }
  send_status();
  flush_report();  // tight: the next sample finds the slot taken and is skipped (emit_telemetry)
  if (packs && slots) {
    report_capacity_ = slots->report_bytes;
  }
}

}  // namespace mrskin::sim
