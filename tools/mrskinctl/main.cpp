// mrskinctl: diagnostic CLI for the MR skin.
#include <fmt/format.h>

#include <cmath>
#include <cstdio>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "command.hpp"
#include "exit_codes.hpp"
#include "json_text.hpp"
#include "list_command.hpp"
#include "logging.hpp"
#include "model_command.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/driver/version.hpp"
#include "mrskin/protocol/messages.hpp"
#include "mrskin/sim/open_mock.hpp"

namespace {

// Exit codes: tools/common/exit_codes.hpp.
using mrskin::ctl::json_escape;
using mrskin::ctl::json_number;

std::string json_numbers(const std::vector<double>& values) {
  std::string out = "[";
  for (std::size_t i = 0; i < values.size(); ++i) {
    out += (i == 0 ? "" : ", ") + json_number(values[i]);
  }
  return out + "]";
}

std::string json_log(const std::vector<mrskin::LogEntry>& entries) {
  std::string out = "[";
  for (std::size_t k = 0; k < entries.size(); ++k) {
    const mrskin::LogEntry& e = entries[k];
    out +=
        fmt::format(R"({}{{"host_time_s": {}, "dir": "{}", "kind": "{}", "seq": {})", k == 0 ? "" : ", ",
                    json_number(mrskin::to_seconds(e.host_time)), e.sent ? "tx" : "rx", e.kind, e.sequence);
    if (!e.error.empty()) {
      out += fmt::format(R"(, "error": "{}")", json_escape(e.error));
    }
    if (e.has_device_time) {
      out +=
          fmt::format(", \"device_time_s\": {}", json_number(static_cast<double>(e.device_time_us) * 1e-6));
    }
    if (!e.values.empty()) {
      out += fmt::format(R"(, "first": {}, "unit": "{}", "values": {})", e.first, e.unit,
                         json_numbers(e.values));
    }
    if (!e.targets.empty()) {
      out += fmt::format(R"(, "first": {}, "targets": [)", e.first);
      for (std::size_t i = 0; i < e.targets.size(); ++i) {
        const auto& t = e.targets[i];
        out +=
            fmt::format(R"({}{{"stiffness_n_per_m": {}, "offset_m": {}, "ceiling_n": {}, "validity_s": {}}})",
                        i == 0 ? "" : ", ", json_number(t.stiffness_N_per_m), json_number(t.offset_m),
                        json_number(t.ceiling_N), json_number(t.validity_s));
      }
      out += "]";
    }
    if (!e.state.empty()) {
      out += fmt::format(R"(, "state": "{}")", e.state);
    }
    if (!e.fault.empty()) {
      out += fmt::format(R"(, "fault": "{}")", e.fault);
    }
    if (!e.detail.empty()) {
      out += fmt::format(R"(, "detail": "{}")", json_escape(e.detail));
    }
    out += "}";
  }
  return out + "]";
}

// "13 at fluid cells" / "12 under valves, 1 at fluid cells".
std::string sensor_places(const mrskin::model::DeviceProfile* profile) {
  if (profile == nullptr) {
    return "layout unknown (no profile read)";
  }
  std::size_t at_cells = 0;
  std::size_t at_valves = 0;
  std::size_t in_reservoir = 0;
  for (const auto& s : profile->sensors) {
    at_cells += s.place == mrskin::model::PlaceKind::fluid_cell ? 1U : 0U;
    at_valves += s.place == mrskin::model::PlaceKind::valve ? 1U : 0U;
    in_reservoir += s.place == mrskin::model::PlaceKind::reservoir ? 1U : 0U;
  }
  std::string out;
  for (const auto& [n, where] : {std::pair{at_cells, "at fluid cells"}, std::pair{at_valves, "under valves"},
                                 std::pair{in_reservoir, "in the reservoir"}}) {
    if (n > 0) {
      out += fmt::format("{}{} {}", out.empty() ? "" : ", ", n, where);
    }
  }
  return out;
}

struct InfoOptions {
  std::string uri;
  bool json = false;
  double sample_s = 0.2;
  bool log = false;
};

int cmd_info(const InfoOptions& o) {
  mrskin::MonotonicClock clock;
  const mrskin::OpenedDevice dev = mrskin::open_device(o.uri, clock);
  mrskin::DeviceSession& session = *dev.session;
  // Listen for a moment so the statistics mean something.
  const mrskin::TimePoint end = clock.now() + mrskin::from_seconds(o.sample_s);
  while (clock.now() < end) {
    (void)session.poll(clock.now());
    clock.sleep_until(clock.now() + std::chrono::milliseconds(1));
  }
  const mrskin::DeviceInfo& i = session.info();
  const mrskin::SessionCounters& c = session.counters();
  const mrskin::model::DeviceProfile* profile = session.profile();
  const double sensor_min = mrskin::protocol::kSensorCountMin * i.sensor_lsb;
  const double sensor_max = mrskin::protocol::kSensorCountMax * i.sensor_lsb;
  const double rtt_p50_s = c.round_trip.percentile_ns(0.5) * 1e-9;
  const double rtt_p99_s = c.round_trip.percentile_ns(0.99) * 1e-9;
  const double rtt_max_s = static_cast<double>(c.round_trip.max_ns()) * 1e-9;
  const bool faulted = c.faults > 0;
  if (o.json) {
    std::string out = fmt::format(
        "{{\"uri\": \"{}\", \"serial\": \"{:08X}\", \"firmware\": \"{}\", \"protocol\": \"{}.{}\", "
        "\"library_protocol\": \"{}.{}\", \"profile\": {{\"name\": \"{}\", \"description\": \"{}\"}}, "
        "\"rows\": {}, \"cols\": {}, \"fluid_cells\": {}, \"valves\": {}, \"sensors\": {}, "
        "\"sensor_quantity\": \"{}\", \"sensor_unit\": \"{}\", \"sensor_places\": \"{}\", ",
        json_escape(o.uri), i.serial, i.firmware, i.protocol_major, i.protocol_minor,
        mrskin::protocol_version_major(), mrskin::protocol_version_minor(),
        json_escape(profile != nullptr ? profile->name : ""),
        json_escape(profile != nullptr ? profile->description : ""), i.rows, i.cols, i.fluid_cells, i.valves,
        i.sensors, i.sensor_quantity, i.sensor_unit, sensor_places(profile));
    out += fmt::format(
        "\"current_lsb_a\": {}, \"max_current_a\": {}, \"sensor_lsb_si\": {}, \"sensor_min_si\": {}, "
        "\"sensor_max_si\": {}, \"sensor_deadband_counts\": {}, \"heartbeat_timeout_s\": {}, "
        "\"telemetry_rate_hz\": {}, \"state\": \"{}\", "
        "\"fault\": \"{}\", \"valves_released\": {}, \"derated\": {}, \"calibration\": \"{}\", ",
        json_number(i.current_lsb_A), json_number(i.max_current_A), json_number(i.sensor_lsb),
        json_number(sensor_min), json_number(sensor_max), i.sensor_deadband_counts,
        json_number(i.heartbeat_timeout_s), json_number(i.telemetry_rate_hz),
        mrskin::to_string(session.state()), mrskin::fault_name(session.fault_code()),
        session.valves_released(), session.derated(), json_escape(i.calibration));
    out += fmt::format(
        "\"stats\": {{\"sample_s\": {}, \"sent\": {}, \"received\": {}, \"telemetry\": {}, \"crc_errors\": "
        "{}, "
        "\"decode_errors\": {}, \"sequence_gaps\": {}, \"duplicates\": {}, \"heartbeats\": {}, "
        "\"send_would_block\": {}, \"invalid_commands\": {}, \"telemetry_timeouts\": {}, \"disconnects\": "
        "{}, "
        "\"reconnects\": {}, \"faults\": {}, \"reseeds\": {}, \"rtt_count\": {}, \"rtt_p50_s\": {}, "
        "\"rtt_p99_s\": {}, \"rtt_max_s\": {}}}",
        json_number(o.sample_s), c.sent, c.received, c.telemetry, c.crc_errors, c.decode_errors,
        c.sequence_gaps, c.duplicates, c.heartbeats, c.send_would_block, c.invalid_commands,
        c.telemetry_timeouts, c.disconnects, c.reconnects, c.faults, c.reseeds, c.round_trip.count(),
        json_number(rtt_p50_s), json_number(rtt_p99_s), json_number(rtt_max_s));
    if (o.log) {
      out += fmt::format(R"(, "log": {{"kind": "{}", "fault": "{}", "records": {}}})",
                         faulted ? "fault" : "ring",
                         faulted ? mrskin::fault_name(session.last_fault_code()) : "",
                         json_log(session.decode_log(faulted ? session.fault_log() : session.ring_log())));
    }
    fmt::print("{}}}\n", out);
    return mrskin::tools::kOk;
  }
  fmt::print(
      "device       {}\nserial       {:08X}\nfirmware     {}\nprotocol     v{}.{} (library speaks v{}.{})\n"
      "profile      {}{}\n"
      "grid         {} x {}: {} fluid cells, {} valves\n"
      "sensors      {} {} sensors in {} ({})\n",
      o.uri, i.serial, i.firmware, i.protocol_major, i.protocol_minor, mrskin::protocol_version_major(),
      mrskin::protocol_version_minor(), profile != nullptr ? profile->name : "(not read)",
      profile != nullptr && !profile->description.empty() ? " - " + profile->description : "", i.rows, i.cols,
      i.fluid_cells, i.valves, i.sensors, i.sensor_quantity, i.sensor_unit, sensor_places(profile));
  fmt::print(
      "limits       current 0..{:.4f} A in steps of {:.1f} uA; sensors {:.4g}..{:.4g} {} in steps of {:.4g} "
      "{}{}\n"
      "             heartbeat timeout {:.3f} s; telemetry {:.0f} Hz\n"
      "state        {} (fault: {}){}{}\n",
      i.max_current_A, i.current_lsb_A * 1e6, sensor_min, sensor_max, i.sensor_unit, i.sensor_lsb,
      i.sensor_unit,
      i.sensor_deadband_counts > 0
          ? fmt::format("; deadband {} counts (readings up to that stale)", i.sensor_deadband_counts)
          : std::string(),
      i.heartbeat_timeout_s, i.telemetry_rate_hz, mrskin::to_string(session.state()),
      mrskin::fault_name(session.fault_code()), session.valves_released() ? ", valves released" : "",
      session.derated() ? ", derated" : "");
  fmt::print("calibration\n");
  std::size_t start = 0;
  while (start < i.calibration.size()) {
    const std::size_t end_line = i.calibration.find('\n', start);
    fmt::print("  {}\n", i.calibration.substr(start, end_line - start));
    start = end_line == std::string::npos ? i.calibration.size() : end_line + 1;
  }
  fmt::print(
      "statistics over {:.2f} s\n"
      "  packets    {} sent ({} heartbeats, {} refused by a full queue), {} received ({} telemetry)\n"
      "  errors     {} CRC, {} decode in all, {} sequence gaps, {} duplicates, {} invalid commands\n"
      "  link       {} telemetry timeouts, {} disconnects, {} reconnects, {} faults, {} re-seeds\n"
      "  round trip {} samples, p50 {:.3f} ms, p99 {:.3f} ms, max {:.3f} ms\n",
      o.sample_s, c.sent, c.heartbeats, c.send_would_block, c.received, c.telemetry, c.crc_errors,
      c.decode_errors, c.sequence_gaps, c.duplicates, c.invalid_commands, c.telemetry_timeouts, c.disconnects,
      c.reconnects, c.faults, c.reseeds, c.round_trip.count(), rtt_p50_s * 1e3, rtt_p99_s * 1e3,
      rtt_max_s * 1e3);
  if (o.log) {
    if (faulted) {
      fmt::print("{}", session.fault_report());
    } else {
      const auto records = session.ring_log();
      fmt::print("ring log: no fault during the sample; the last {} packets, oldest first:\n{}",
                 records.size(), session.format_log(records));
    }
  }
  return mrskin::tools::kOk;
}

}  // namespace

namespace {

int guarded_main(int argc, char** argv) {
  mrskin::tools::init_logging("mrskinctl");
  mrskin::sim::register_mock_scheme();  // mock:// (the simulated unit, mrskin::sim)
  mrskin::tools::CliApp cli{"mrskinctl: inspect, test and calibrate MR skin devices"};
  mrskin::tools::CliCommand root = cli.root();
  root.version_flag("--version", std::string(mrskin::library_version()) + " (protocol v" +
                                     std::to_string(mrskin::protocol_version_major()) + "." +
                                     std::to_string(mrskin::protocol_version_minor()) + ")");
  root.require_subcommand(1);
  root.fallthrough();  // global flags such as --json may follow the subcommand
  mrskin::ctl::GlobalOptions global;
  root.flag("--json", global.json, "machine-readable output");
  std::string log_level;
  mrskin::tools::add_log_level_option(root, log_level);
  std::string device = "mock://";

  mrskin::tools::CliCommand info = root.subcommand(
      "info",
      "open a device, run the handshake and print its identity, profile, layout, limits, calibration and "
      "statistics");
  info.option("--device", device, "device URI (mock://[PROFILE][?seed=N&faults=...])").show_default();
  InfoOptions info_options;
  info.option("--sample", info_options.sample_s, "seconds to listen for statistics")
      .range(0.0, 60.0)
      .show_default();
  info.flag("--log", info_options.log,
            "also print the decoded ring log: the fault report if a fault arrived during the sample, else "
            "the last packets");

  mrskin::tools::CliCommand list = root.subcommand(
      "list",
      "list the MR skins reachable over hidraw, USB and the CAN interfaces that exist: URI, path, serial, "
      "firmware and protocol version, and for each unit the OS refuses, the problem and its fix. Exit "
      "status 0 when a unit was found, 3 when none was");
  mrskin::ctl::ListOptions list_options;
  bool no_probe = false;
  list.flag("--no-probe", no_probe, "do not open the units for their firmware and protocol version");

  int command_exit = 0;
  mrskin::ctl::add_monitor_command(root, global, command_exit);
  mrskin::ctl::add_set_command(root, global, command_exit);
  mrskin::ctl::add_selftest_command(root, global, command_exit);
  mrskin::ctl::add_calibrate_command(root, global, command_exit);
  mrskin::ctl::add_record_commands(root, global, command_exit);
  mrskin::ctl::add_plot_command(root, global, command_exit);
  mrskin::ctl::add_budget_command(root, global, command_exit);
  mrskin::ctl::add_bridge_commands(root, global, command_exit);
  int model_exit = 0;
  const mrskin::tools::CliCommand model = mrskin::ctl::add_model_command(root, model_exit);
  if (const mrskin::tools::CliParse parsed = cli.parse(argc, argv); !parsed.run) {
    // --help and --version exit 0; every bad argument is a usage error (2), whatever CLI11's own
    // code for it.
    return parsed.exit_code == 0 ? mrskin::tools::kOk : mrskin::tools::kUsage;
  }
  mrskin::tools::set_log_level(log_level);
  if (model.parsed()) {
    return model_exit;
  }
  if (!list.parsed() && !info.parsed()) {
    return command_exit;
  }
  if (list.parsed()) {
    list_options.probe = !no_probe;
    list_options.json = global.json;
    return mrskin::ctl::cmd_list(list_options);
  }
  if (info.parsed()) {
    info_options.uri = device;
    info_options.json = global.json;
    return cmd_info(info_options);
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
