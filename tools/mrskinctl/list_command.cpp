#include "list_command.hpp"

#include <fmt/format.h>

#include <chrono>
#include <exception>
#include <string>
#include <vector>

#include "exit_codes.hpp"
#include "json_text.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/driver/enumerate.hpp"

namespace mrskin::ctl {
namespace {

// Identity of a unit that nothing else reported: a short handshake without the configuration.
void probe(DeviceListing& unit) {
  MonotonicClock clock;
  OpenOptions open;
  open.session.read_configuration = false;
  open.session.handshake_timeout = std::chrono::milliseconds(300);
  try {
    const OpenedDevice dev = open_device(unit.uri, clock, open);
    const DeviceInfo& info = dev.session->info();
    unit.firmware = info.firmware;
    unit.protocol = fmt::format("{}.{}", info.protocol_major, info.protocol_minor);
    if (unit.serial.empty()) {
      unit.serial = fmt::format("{:08X}", info.serial);
    }
  } catch (const DeviceBusy& e) {
    unit.problem = "in use";
    unit.fix = e.what();
  } catch (const std::exception& e) {
    unit.problem = "does not answer";
    unit.fix = e.what();
  }
}

bool is_unit(const DeviceListing& d) { return !d.uri.empty(); }

}  // namespace

int cmd_list(const ListOptions& options) {
  std::vector<DeviceListing> all = list_hid_devices();
  for (const std::vector<DeviceListing>& more : {list_usb_devices(), list_can_devices()}) {
    all.insert(all.end(), more.begin(), more.end());
  }
  std::size_t units = 0;
  for (DeviceListing& d : all) {
    if (!is_unit(d)) {
      continue;  // a bus-level note (no CAN in the kernel, an interface down)
    }
    ++units;
    if (options.probe && d.problem.empty() && d.firmware.empty()) {
      probe(d);
    }
  }
  if (options.json) {
    std::string out = "{\"devices\": [";
    bool first = true;
    for (const DeviceListing& d : all) {
      out += fmt::format(
          R"({}{{"bus": "{}", "uri": "{}", "path": "{}", "serial": "{}", "firmware": "{}", "protocol": "{}", )"
          R"("problem": "{}", "fix": "{}"}})",
          first ? "" : ", ", json_escape(d.bus), json_escape(d.uri), json_escape(d.path),
          json_escape(d.serial), json_escape(d.firmware), json_escape(d.protocol), json_escape(d.problem),
          json_escape(d.fix));
      first = false;
    }
    fmt::print("{}], \"units\": {}}}\n", out, units);
  } else {
    if (units == 0) {
      fmt::print(
          "no MR skin found on hidraw, USB or CAN (check the cable and power; udev/70-mrskin.rules)\n");
    }
    for (const DeviceListing& d : all) {
      if (is_unit(d)) {
        fmt::print("{:<4} {:<34} {:<16} serial {:<9} firmware {:<8} protocol {}\n", d.bus, d.uri, d.path,
                   d.serial.empty() ? "?" : d.serial, d.firmware.empty() ? "?" : d.firmware,
                   d.protocol.empty() ? "?" : d.protocol);
        if (!d.problem.empty()) {
          fmt::print("     {}: {}\n", d.problem, d.fix);
        }
      } else {
        fmt::print("{:<4} {}: {}{}{}\n", d.bus, d.path.empty() ? "-" : d.path, d.problem,
                   d.fix.empty() ? "" : ": ", d.fix);
      }
    }
  }
  return units > 0 ? tools::kOk : tools::kNoDevice;
}

}  // namespace mrskin::ctl
