// mrskinctl: diagnostic CLI for the MR skin.
#include <fmt/format.h>

#include <CLI/CLI.hpp>
#include <cstdio>
#include <string>

#include "exit_codes.hpp"
#include "model_command.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/driver/version.hpp"

namespace {

// Exit codes: tools/common/exit_codes.hpp.

std::string json_escape(const std::string& text) {
  std::string out;
  for (const char c : text) {
    switch (c) {
      case '"':
        out += "\\\"";
        break;
      case '\\':
        out += "\\\\";
        break;
      case '\n':
        out += "\\n";
        break;
      default:
        out += c;
    }
  }
  return out;
}

int cmd_info(const std::string& uri, bool json, double sample_s) {
  mrskin::MonotonicClock clock;
  const mrskin::OpenedDevice dev = mrskin::open_device(uri, clock);
  mrskin::DeviceSession& session = *dev.session;
  // Listen for a moment so the statistics mean something.
  const mrskin::TimePoint end = clock.now() + mrskin::from_seconds(sample_s);
  while (clock.now() < end) {
    (void)session.poll(clock.now());
    clock.sleep_until(clock.now() + std::chrono::milliseconds(1));
  }
  const mrskin::DeviceInfo& i = session.info();
  const mrskin::SessionCounters& c = session.counters();
  if (json) {
    fmt::print(
        "{{\"uri\": \"{}\", \"serial\": \"{:08X}\", \"firmware\": \"{}\", \"protocol\": \"{}.{}\", "
        "\"rows\": {}, \"cols\": {}, \"fluid_cells\": {}, \"valves\": {}, \"sensors\": {}, "
        "\"current_lsb_a\": {:.9g}, \"max_current_a\": {:.9g}, \"sensor_lsb_si\": {:.9g}, "
        "\"heartbeat_timeout_s\": {:.6g}, \"telemetry_rate_hz\": {:.6g}, \"state\": \"{}\", \"fault\": "
        "\"{}\", "
        "\"calibration\": \"{}\", \"stats\": {{\"sent\": {}, \"received\": {}, \"telemetry\": {}, "
        "\"crc_errors\": {}, \"decode_errors\": {}, \"sequence_gaps\": {}, \"telemetry_timeouts\": {}, "
        "\"reconnects\": {}, \"rtt_p50_s\": {:.6g}, \"rtt_p99_s\": {:.6g}}}}}\n",
        uri, i.serial, i.firmware, i.protocol_major, i.protocol_minor, i.rows, i.cols, i.fluid_cells,
        i.valves, i.sensors, i.current_lsb_A, i.max_current_A, i.sensor_lsb, i.heartbeat_timeout_s,
        i.telemetry_rate_hz, mrskin::to_string(session.state()), mrskin::fault_name(session.fault_code()),
        json_escape(i.calibration), c.sent, c.received, c.telemetry, c.crc_errors, c.decode_errors,
        c.sequence_gaps, c.telemetry_timeouts, c.reconnects, c.round_trip.percentile_ns(0.5) * 1e-9,
        c.round_trip.percentile_ns(0.99) * 1e-9);
    return 0;
  }
  fmt::print(
      "device      {}\nserial      {:08X}\nfirmware    {}\nprotocol    v{}.{} (library speaks v{}.{})\n"
      "grid        {} x {}: {} fluid cells, {} valves, {} sensors\n"
      "current     {:.3f} mA per count, max {:.4f} A\nsensor LSB  {:.3g} (SI)\nheartbeat   {:.3f} s timeout\n"
      "telemetry   {:.0f} Hz\nstate       {} (fault: {})\n",
      uri, i.serial, i.firmware, i.protocol_major, i.protocol_minor, mrskin::protocol_version_major(),
      mrskin::protocol_version_minor(), i.rows, i.cols, i.fluid_cells, i.valves, i.sensors,
      i.current_lsb_A * 1e3, i.max_current_A, i.sensor_lsb, i.heartbeat_timeout_s, i.telemetry_rate_hz,
      mrskin::to_string(session.state()), mrskin::fault_name(session.fault_code()));
  fmt::print("calibration\n");
  std::size_t start = 0;
  while (start < i.calibration.size()) {
    const std::size_t end_line = i.calibration.find('\n', start);
    fmt::print("  {}\n", i.calibration.substr(start, end_line - start));
    start = end_line == std::string::npos ? i.calibration.size() : end_line + 1;
  }
  fmt::print(
      "statistics over {:.2f} s: {} sent, {} received ({} telemetry), {} CRC errors, {} decode errors, {} "
      "sequence "
      "gaps, {} telemetry timeouts, {} reconnects, round trip p50 {:.3f} ms p99 {:.3f} ms\n",
      sample_s, c.sent, c.received, c.telemetry, c.crc_errors, c.decode_errors, c.sequence_gaps,
      c.telemetry_timeouts, c.reconnects, c.round_trip.percentile_ns(0.5) * 1e-6,
      c.round_trip.percentile_ns(0.99) * 1e-6);
  return 0;
}

}  // namespace

namespace {

int guarded_main(int argc, char** argv) {
  CLI::App app{"mrskinctl: inspect, test and calibrate MR skin devices"};
  app.set_version_flag("--version", std::string(mrskin::library_version()) + " (protocol v" +
                                        std::to_string(mrskin::protocol_version_major()) + "." +
                                        std::to_string(mrskin::protocol_version_minor()) + ")");
  app.require_subcommand(1);
  app.fallthrough();  // global flags such as --json may follow the subcommand
  bool json = false;
  app.add_flag("--json", json, "machine-readable output");
  std::string device = "mock://";

  auto* info = app.add_subcommand("info", "open a device, run the handshake and print its identity");
  info->add_option("--device", device, "device URI")->capture_default_str();
  double sample_s = 0.2;
  info->add_option("--sample", sample_s, "seconds to listen for statistics")
      ->check(CLI::Range(0.0, 60.0))
      ->capture_default_str();

  struct Planned {
    const char* name;
    const char* help;
    const char* issue;
  };
  static constexpr Planned kPlanned[] = {
      {"list", "list attached devices on every bus", "Driver II (#7)"},
      {"monitor", "show the grid live: force, displacement, current, temperature",
       "mrskinctl complete (#11)"},
      {"set", "send per-valve currents or per-cell targets", "mrskinctl complete (#11)"},
      {"selftest", "valve sweep, sensor noise, latency histogram, leak and stuck-sensor checks",
       "mrskinctl complete (#11)"},
      {"calibrate", "yield-force sweep, degauss, tare; store on the device", "mrskinctl complete (#11)"},
      {"record", "record telemetry and commands to a file", "mrskinctl complete (#11)"},
      {"replay", "replay a recording", "mrskinctl complete (#11)"},
      {"enable", "enable a running bridge's device", "Bridge II (#10)"},
      {"disable", "disable a running bridge's device", "Bridge II (#10)"},
      {"estop", "emergency stop through a running bridge", "Bridge II (#10)"},
      {"fault", "show a running bridge's fault cause and ring log", "Bridge II (#10)"},
  };
  const Planned* chosen = nullptr;
  for (const Planned& p : kPlanned) {
    auto* sub = app.add_subcommand(p.name, std::string(p.help) + " [not in this build]");
    sub->allow_extras();
    sub->callback([&chosen, &p] { chosen = &p; });
  }
  int model_exit = 0;
  CLI::App* model = mrskin::ctl::add_model_command(app, model_exit);
  CLI11_PARSE(app, argc, argv);
  if (model->parsed()) {
    return model_exit;
  }
  if (chosen != nullptr) {
    fmt::print(stderr, "mrskinctl {}: not available in this build (planned in {})\n", chosen->name,
               chosen->issue);
    return mrskin::tools::kUnavailable;
  }
  if (info->parsed()) {
    return cmd_info(device, json, sample_s);
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return guarded_main(argc, argv);
  } catch (...) {
    return mrskin::tools::exit_code_for_current_exception();
  }
}
