// The unit's one USB descriptor set, shared by hid:// (hidraw) and usb:// (libusb): a
// full-speed device with one vendor-defined HID interface, 64-byte input and output reports
// without report IDs, on interrupt endpoints polled every 1 ms. The iSerialNumber string is
// the unit's serial number as 8 upper-case hex digits (format_usb_serial).
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>

#include "mrskin/protocol/export.hpp"
#include "mrskin/protocol/messages.hpp"

namespace mrskin::protocol {

inline constexpr std::uint16_t kUsbVendorId = 0x1209;   // pid.codes
inline constexpr std::uint16_t kUsbProductId = 0x4d52;  // "MR", development ID
inline constexpr std::uint8_t kUsbInterface = 0;        // the HID interface
inline constexpr std::uint8_t kUsbEndpointIn = 0x81;    // interrupt IN, device -> host
inline constexpr std::uint8_t kUsbEndpointOut = 0x01;   // interrupt OUT, host -> device
inline constexpr std::uint16_t kUsbMaxPacketBytes = 64;
inline constexpr std::uint8_t kUsbIntervalFrames = 1;  // bInterval: 1 ms at full speed
// Both reports are kHidReportBytes (packet.hpp) long, without a report ID.

// An interrupt endpoint's reserved bandwidth: at most reports_per_interval reports of at most
// report_bytes each per service interval. Full speed: one 64-byte report per 1 ms frame (this
// unit). High speed (USB 2.0 high-bandwidth interrupt endpoints): up to 3 reports of up to
// 1024 bytes per 125 us microframe; the device declares what it uses.
struct UsbInterruptSlots {
  double interval_s = 1e-3;
  std::size_t reports_per_interval = 1;
  std::size_t report_bytes = 64;
};
inline constexpr double kUsbFullSpeedFrame_s = 1e-3;
inline constexpr double kUsbHighSpeedMicroframe_s = 125e-6;
inline constexpr std::size_t kUsbHighSpeedMaxReportsPerMicroframe = 3;
inline constexpr std::size_t kUsbHighSpeedMaxReportBytes = 1024;
inline constexpr UsbInterruptSlots kUsbFullSpeedSlots{kUsbFullSpeedFrame_s, 1, kUsbMaxPacketBytes};
// What a high-speed unit may declare at most (1.2's UsbSlots message, messages.hpp).
inline constexpr UsbInterruptSlots kUsbHighSpeedMaxSlots{
    kUsbHighSpeedMicroframe_s, kUsbHighSpeedMaxReportsPerMicroframe, kUsbHighSpeedMaxReportBytes};
static_assert(kUsbSlotsMaxReportBytes == kUsbHighSpeedMaxReportBytes &&
              kUsbSlotsMaxReportsPerInterval == kUsbHighSpeedMaxReportsPerMicroframe);

// The slots a UsbSlots message declares (a valid one: encode_packet and decode_packet check it).
constexpr UsbInterruptSlots usb_interrupt_slots(const UsbSlots& declared) noexcept {
  return {static_cast<double>(declared.interval_us) * 1e-6, declared.reports_per_interval,
          declared.report_bytes};
}
// The UsbSlots message that declares slots (interval rounded to whole microseconds).
MRSKIN_PROTOCOL_API UsbSlots usb_slots_message(const UsbInterruptSlots& slots) noexcept;
// Reports the slots carry per second, and bytes (reports full to report_bytes) per second.
constexpr double usb_reports_per_s(const UsbInterruptSlots& slots) noexcept {
  return static_cast<double>(slots.reports_per_interval) / slots.interval_s;
}
constexpr double usb_report_bytes_per_s(const UsbInterruptSlots& slots) noexcept {
  return usb_reports_per_s(slots) * static_cast<double>(slots.report_bytes);
}

// HID report descriptor: vendor page 0xFF00, one 64-byte input and one 64-byte output report.
inline constexpr std::array<std::uint8_t, 27> kHidReportDescriptor = {
    0x06, 0x00, 0xFF,  // Usage Page (Vendor Defined 0xFF00)
    0x09, 0x01,        // Usage (0x01)
    0xA1, 0x01,        // Collection (Application)
    0x15, 0x00,        //   Logical Minimum (0)
    0x26, 0xFF, 0x00,  //   Logical Maximum (255)
    0x75, 0x08,        //   Report Size (8)
    0x95, 0x40,        //   Report Count (64)
    0x09, 0x02,        //   Usage (0x02)
    0x81, 0x02,        //   Input (Data, Variable, Absolute)
    0x95, 0x40,        //   Report Count (64)
    0x09, 0x03,        //   Usage (0x03)
    0x91, 0x02,        //   Output (Data, Variable, Absolute)
    0xC0,              // End Collection
};

// "0000BEEF" for serial 0xBEEF.
MRSKIN_PROTOCOL_API std::string format_usb_serial(std::uint32_t serial);
// Inverse of format_usb_serial; nullopt unless exactly 8 hex digits (either case).
MRSKIN_PROTOCOL_API std::optional<std::uint32_t> parse_usb_serial(std::string_view text) noexcept;

}  // namespace mrskin::protocol
