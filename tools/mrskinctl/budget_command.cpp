// mrskinctl budget: what a profile's cyclic traffic needs of each bus at a loop rate, with protocol
// 1.1 (one packet a report or frame) and 1.2 (packed), from the encoders (protocol/bus_budget.hpp;
// docs/protocol.md, "Bus budget"). No device is opened.
#include <fmt/format.h>

#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "command.hpp"
#include "exit_codes.hpp"
#include "json_text.hpp"
#include "mrskin/driver/layout.hpp"
#include "mrskin/driver/model/profile.hpp"
#include "mrskin/protocol/bus_budget.hpp"

namespace mrskin::ctl {
namespace {

namespace proto = mrskin::protocol;

struct BudgetOptions {
  std::string profile = "mr-skin-5x5";
  double rate_hz = 1000.0;
  double telemetry_rate_hz = 1000.0;
};

struct Row {
  proto::BusKind bus;
  bool packed;
  proto::BusBudget budget;
  double highest_hz;
};

std::string verdict_of(const proto::BusBudget& b) {
  if (!b.encodable) {
    return "REFUSED: not addressable";
  }
  if (!b.fits()) {
    return b.one_bus || b.load() > 1.0 ? "REFUSED: over the bus" : "REFUSED: more reports than slots";
  }
  return b.fits(0.8) ? "ok" : "warn: above 80 %";
}

std::string direction_text(const proto::BusBudget& b, const proto::DirectionLoad& d) {
  if (!b.encodable) {
    return "-";
  }
  if (b.one_bus) {
    return fmt::format("{:.1f} % ({:.0f} frames/s)", 100.0 * d.load, d.units_per_s);
  }
  return fmt::format("{:.1f} % ({:.3f} reports/slot)", 100.0 * d.load, d.slot_fraction);
}

int run_budget(const BudgetOptions& o, const GlobalOptions& global) {
  const model::DeviceProfile p = model::load_profile(o.profile);
  const GridLayout layout(p.rows, p.cols);
  proto::CyclicTraffic traffic;
  traffic.valves = layout.valve_count();
  traffic.sensors = p.sensors.size();
  traffic.update_rate_hz = o.rate_hz;
  traffic.telemetry_rate_hz = o.telemetry_rate_hz;
  std::vector<Row> rows;
  for (std::size_t k = 0; k < proto::kBusKindCount; ++k) {
    for (const bool packed : {false, true}) {
      const auto bus = static_cast<proto::BusKind>(k);
      traffic.packed = packed;
      const proto::BusSpec spec = proto::default_bus_spec(bus, packed);
      rows.push_back({bus, packed, proto::compute_bus_budget(spec, traffic),
                      proto::highest_update_rate_hz(spec, traffic)});
    }
  }
  if (global.json) {
    std::string out = fmt::format(
        R"({{"profile": "{}", "rows": {}, "cols": {}, "valves": {}, "sensors": {}, "rate_hz": {}, )"
        R"("telemetry_rate_hz": {}, "buses": [)",
        json_escape(p.origin), p.rows, p.cols, traffic.valves, traffic.sensors, json_number(o.rate_hz),
        json_number(o.telemetry_rate_hz));
    for (std::size_t i = 0; i < rows.size(); ++i) {
      const Row& r = rows[i];
      out += fmt::format(
          R"({}{{"bus": "{}", "protocol": "{}", "fits": {}, "load": {}, "host_to_device": {}, )"
          R"("device_to_host": {}, "host_to_device_slots": {}, "device_to_host_slots": {}, "highest_rate_hz": {}}})",
          i == 0 ? "" : ", ", proto::to_string(r.bus), r.packed ? "1.2" : "1.1",
          r.budget.fits() ? "true" : "false", json_number(r.budget.load()),
          json_number(r.budget.host_to_device.load), json_number(r.budget.device_to_host.load),
          json_number(r.budget.host_to_device.slot_fraction),
          json_number(r.budget.device_to_host.slot_fraction), json_number(r.highest_hz));
    }
    fmt::print("{}]}}\n", out);
    return tools::kOk;
  }
  fmt::print("bus budget of {} ({}x{}: {} valves, {} sensors), loop {:.0f} Hz, telemetry {:.0f} Hz:\n",
             std::filesystem::path(p.origin).stem().string(), p.rows, p.cols, traffic.valves, traffic.sensors,
             o.rate_hz, o.telemetry_rate_hz);
  fmt::print("{:<7}{:<6}{:<32}{:<32}{:>9}  {:<38}{}\n", "bus", "proto", "host to device", "device to host",
             "load", "verdict", "highest rate");
  for (const Row& r : rows) {
    fmt::print("{:<7}{:<6}{:<32}{:<32}{:>9}  {:<38}{:.0f} Hz\n", proto::to_string(r.bus),
               r.packed ? "1.2" : "1.1", direction_text(r.budget, r.budget.host_to_device),
               direction_text(r.budget, r.budget.device_to_host),
               r.budget.encodable ? fmt::format("{:.1f} %", 100.0 * r.budget.load()) : std::string("-"),
               verdict_of(r.budget), r.highest_hz);
  }
  return tools::kOk;
}

}  // namespace

void add_budget_command(CliCommand app, const GlobalOptions& global, int& exit_code) {
  auto o = std::make_shared<BudgetOptions>();
  CliCommand sub = app.subcommand(
      "budget",
      "what a profile's cyclic traffic needs of each bus (hid-fs, hid-hs, can, canfd) at a loop rate, with "
      "protocol 1.1 and 1.2, and the highest rate each bus carries (docs/protocol.md, \"Bus budget\"). No "
      "device is opened. Exit 0, 2 bad argument or profile");
  sub.option("--profile", o->profile,
             "device profile: a .toml file, or a name looked up in $MRSKIN_PROFILE_PATH and the shipped "
             "profiles")
      .show_default();
  sub.option("--rate", o->rate_hz, "loop rate: valve currents sent per second, Hz")
      .range(1.0, 100000.0)
      .show_default();
  sub.option("--telemetry-rate", o->telemetry_rate_hz, "the unit's telemetry rate (its Identity's), Hz")
      .range(1.0, 100000.0)
      .show_default();
  sub.callback([o, &global, &exit_code] { exit_code = run_budget(*o, global); });
}

}  // namespace mrskin::ctl
