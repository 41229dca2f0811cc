// mrskinctl record / replay: telemetry and the commands sent, to an NDJSON file and back
// (format: ctl_device_record.hpp, docs/cli.md). replay --to-device re-sends the recorded
// commands at their recorded times, with the target device's limits checked again first.
#include <fmt/format.h>

#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "bridge_client.hpp"
#include "command.hpp"
#include "ctl_device_record.hpp"
#include "ctl_device_rig.hpp"
#include "exit_codes.hpp"
#include "json_text.hpp"
#include "recording.hpp"

namespace mrskin::ctl {
namespace {

struct RecordOptions {
  std::string uri = "mock://";
  bool realtime = false;
  std::string out;
  double duration_s = 1.0;
  std::string currents;
  std::string bridge;       // the daemon's socket ("": its default)
  bool use_bridge = false;  // --bridge given, with or without a value
};

struct ReplayOptions {
  std::string file;
  std::string to_device;
  bool realtime = false;
  LeaseOption lease;  // --bridge: re-send to the device of a running mrskin-bridged
};

// Writes lines; a failed write is remembered and reported once at the end.
class LineWriter {
 public:
  explicit LineWriter(const std::string& path) : file_(std::fopen(path.c_str(), "w")) {
    if (file_ == nullptr) {
      throw InvalidArgument(
          fmt::format("record: cannot write {}: {}; give a writable --out path", path, std::strerror(errno)));
    }
  }
  LineWriter(const LineWriter&) = delete;
  LineWriter& operator=(const LineWriter&) = delete;
  LineWriter(LineWriter&&) = delete;
  LineWriter& operator=(LineWriter&&) = delete;
  ~LineWriter() { (void)close(); }
  void line(const std::string& text) noexcept {
    if (file_ != nullptr && (std::fputs(text.c_str(), file_) < 0 || std::fputc('\n', file_) == EOF)) {
      failed_ = true;
    }
    ++lines_;
  }
  bool close() noexcept {
    if (file_ != nullptr) {
      // NOLINTNEXTLINE(cppcoreguidelines-owning-memory): the FILE* this class owns
      failed_ = std::fclose(file_) != 0 || failed_;
      file_ = nullptr;
    }
    return !failed_;
  }
  [[nodiscard]] std::size_t lines() const noexcept { return lines_; }

 private:
  std::FILE* file_;
  bool failed_ = false;
  std::size_t lines_ = 0;
};

struct RecordContext {
  Rig* rig = nullptr;
  LineWriter* out = nullptr;
  std::size_t telemetry = 0;
};

void on_telemetry(void* context, const TelemetryView& view) noexcept {
  auto* c = static_cast<RecordContext*>(context);
  try {
    c->out->line(
        fmt::format(R"({{"t_s": {}, "dir": "rx", "kind": "telemetry", "device_time_s": {}, "first": {}, )"
                    R"("values": {}}})",
                    json_number(c->rig->elapsed_s()), json_number(view.device_time_us * 1e-6), view.first,
                    record_numbers(view.values)));
    ++c->telemetry;
  } catch (...) {  // formatting allocates; a full memory loses the line, never the unit
  }
}

void check_record_options(const RecordOptions& o) {
  if (o.out.empty()) {
    throw InvalidArgument("record: --out FILE is required");
  }
  if (!std::isfinite(o.duration_s) || o.duration_s <= 0.0 || o.duration_s > 3600.0) {
    throw InvalidArgument("record: --duration must be in (0, 3600] s");
  }
}

void print_record_summary(const RecordOptions& o, const GlobalOptions& global, double elapsed_s,
                          std::size_t lines, std::size_t telemetry, std::size_t commands, bool interrupted) {
  if (global.json) {
    fmt::print(
        R"({{"out": "{}", "duration_s": {}, "lines": {}, "telemetry": {}, "commands": {}, "interrupted": {}}})"
        "\n",
        json_escape(o.out), json_number(elapsed_s), lines, telemetry, commands,
        interrupted ? "true" : "false");
  } else {
    fmt::print("recorded {:.3f} s to {}: {} lines, {} telemetry packets, {} commands{}\n", elapsed_s, o.out,
               lines, telemetry, commands, interrupted ? " (interrupted)" : "");
  }
}

std::string header_line(const std::string& uri, std::size_t valves, std::size_t fluid_cells,
                        std::size_t sensors, const std::string& sensor_unit, double max_current_a,
                        std::string_view rendered = "none") {
  return fmt::format(R"({{"format": "{}", "version": {}, "uri": "{}", "valves": {}, "fluid_cells": {}, )"
                     R"("sensors": {}, "sensor_unit": "{}", "max_current_a": {}, "rendered": "{}"}})",
                     kRecordFormat, kRecordVersion, json_escape(uri), valves, fluid_cells, sensors,
                     json_escape(sensor_unit), json_number(max_current_a), rendered);
}

// Version 2's per-cell picture from one grid event (daemon.md, "Grid telemetry"): false when the
// daemon sent no envelope (an older one). rendered_n: the truth when the daemon has one.
bool cells_line(const JsonReply& event, double t_s, std::string& line) {
  const std::optional<std::vector<double>> truth = event.numbers("true_force_n");
  const std::optional<std::vector<double>> observed = event.numbers("force_n");
  const std::optional<std::vector<double>> target = event.numbers("target_n");
  const std::optional<std::vector<double>> law = event.numbers("law_n");
  std::optional<std::vector<double>> floor = event.numbers("floor_n");
  std::optional<std::vector<double>> ceiling = event.numbers("ceiling_n");
  if (!observed || !target || !law || !floor || !ceiling) {
    return false;
  }
  const bool has_truth = truth && !truth->empty() && std::isfinite(truth->front());
  std::vector<double> loaded(floor->size(), 0.0);
  for (std::size_t i = 0; i < floor->size() && i < ceiling->size(); ++i) {
    loaded[i] = std::isfinite((*floor)[i]) ? 1.0 : 0.0;
    if (loaded[i] == 0.0) {
      (*floor)[i] = 0.0;  // the file holds numbers only: "loaded" says where these mean nothing
      (*ceiling)[i] = 0.0;
    }
  }
  line = fmt::format(
      R"({{"t_s": {}, "dir": "rx", "kind": "cells", "rendered_n": {}, "target_n": {}, "law_n": {}, )"
      R"("floor_n": {}, "ceiling_n": {}, "loaded": {}}})",
      json_number(t_s), record_numbers(has_truth ? *truth : *observed), record_numbers(*target),
      record_numbers(*law), record_numbers(*floor), record_numbers(*ceiling), record_numbers(loaded));
  return true;
}

// Through a running mrskin-bridged (which owns the device): its grid telemetry every 10 ms, as
// the same NDJSON: the sensors as rx telemetry, the bridge's commanded currents as tx currents
// when they change, status changes; an ENABLED unit starts with a tx enable, so the file
// replays onto a free device (replay --to-device) as the bridge drove it, at 10 ms resolution.
int run_record_bridge(const RecordOptions& o, const GlobalOptions& global) {
  check_record_options(o);
  const std::string path = bridge_socket(o.bridge);
  (void)connect_bridge(path);  // no daemon: exit 3 before the file is created
  LineWriter out(o.out);
  const auto t0 = std::chrono::steady_clock::now();
  const auto elapsed_s = [&] {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  };
  bool header = false;
  bool pictured = false;  // the header said cells lines follow
  std::string state;
  std::string fault;
  std::vector<double> last_currents;
  std::size_t telemetry = 0;
  std::size_t commands = 0;
  const StopSignals signals;
  const int code = stream_bridge_grid(path, 10.0, o.duration_s, "record", [&](const JsonReply& event) {
    if (event.text("event") != "telemetry") {
      return;
    }
    std::optional<std::vector<double>> sensors = event.numbers("sensor");
    std::optional<std::vector<double>> currents = event.numbers("current_a");
    const std::optional<std::vector<double>> cells = event.numbers("force_n");
    if (!sensors || !currents || !cells || sensors->empty()) {
      return;  // no grid yet, or a daemon without the raw sensors (older)
    }
    const double t_s = elapsed_s();
    const std::string now_state = event.text("state").value_or("?");
    const std::string now_fault = event.text("fault").value_or("?");
    std::string picture;
    const bool has_picture = cells_line(event, t_s, picture);
    if (!header) {
      const std::optional<std::vector<double>> truth = event.numbers("true_force_n");
      const bool has_truth = truth && !truth->empty() && std::isfinite(truth->front());
      out.line(header_line("bridge:" + path, currents->size(), cells->size(), sensors->size(),
                           event.text("sensor_unit").value_or("m"),
                           event.number("max_current_a").value_or(0.0),
                           !has_picture ? "none"
                           : has_truth  ? "truth"
                                        : "observer"));
      header = true;
      pictured = has_picture;
    }
    if (now_state != state || now_fault != fault) {
      state = now_state;
      fault = now_fault;
      out.line(fmt::format(R"({{"t_s": {}, "dir": "rx", "kind": "status", "state": "{}", "fault": "{}"}})",
                           json_number(t_s), json_escape(state), json_escape(fault)));
      if (commands == 0 && state == "ENABLED") {
        out.line(fmt::format(R"({{"t_s": {}, "dir": "tx", "kind": "state", "request": "enable"}})",
                             json_number(t_s)));
        ++commands;
      }
    }
    if (*currents != last_currents) {
      out.line(fmt::format(R"({{"t_s": {}, "dir": "tx", "kind": "currents", "values": {}}})",
                           json_number(t_s), record_numbers(*currents)));
      last_currents = *std::move(currents);
      ++commands;
    }
    out.line(fmt::format(R"({{"t_s": {}, "dir": "rx", "kind": "telemetry", "device_time_s": {}, "first": 0, )"
                         R"("values": {}}})",
                         json_number(t_s), json_number(event.number("grid_t_s").value_or(0.0)),
                         record_numbers(*sensors)));
    ++telemetry;
    if (pictured && has_picture) {
      out.line(picture);
    }
  });
  const std::size_t lines = out.lines();
  if (!out.close()) {
    throw Error(fmt::format("record: writing {} failed (disk full?); the file is incomplete", o.out));
  }
  if (code != tools::kOk) {
    return code;
  }
  if (!header) {
    throw Error(
        fmt::format("record: mrskin-bridged on {} sent no grid with raw sensors in {} s (an older daemon?)",
                    path, o.duration_s));
  }
  print_record_summary(o, global, elapsed_s(), lines, telemetry, commands, stop_requested());
  return tools::kOk;
}

int run_record(const RecordOptions& o, const GlobalOptions& global) {
  if (o.use_bridge) {
    return run_record_bridge(o, global);
  }
  check_record_options(o);
  Rig rig(o.uri, o.realtime);
  const DeviceInfo& info = rig.info();
  std::vector<double> current_a;
  if (!o.currents.empty()) {
    current_a = parse_number_list(o.currents, "--currents");
    check_currents(current_a, info, "--currents");
  }
  LineWriter out(o.out);
  out.line(
      header_line(o.uri, info.valves, info.fluid_cells, info.sensors, info.sensor_unit, info.max_current_A));
  RecordContext context{&rig, &out, 0};
  rig.session().set_telemetry_callback(&on_telemetry, &context);
  std::size_t commands = 0;
  const auto status_line = [&] {
    out.line(fmt::format(R"({{"t_s": {}, "dir": "rx", "kind": "status", "state": "{}", "fault": "{}"}})",
                         json_number(rig.elapsed_s()), to_string(rig.session().state()),
                         fault_name(rig.session().fault_code())));
  };
  const auto send_currents = [&] {
    out.line(fmt::format(R"({{"t_s": {}, "dir": "tx", "kind": "currents", "values": {}}})",
                         json_number(rig.elapsed_s()), record_numbers(current_a)));
    (void)rig.session().send_valve_currents(current_a);
    ++commands;
  };
  status_line();
  DeviceState state = rig.session().state();
  std::uint8_t fault = rig.session().fault_code();
  if (!current_a.empty()) {
    out.line(fmt::format(R"({{"t_s": {}, "dir": "tx", "kind": "state", "request": "enable"}})",
                         json_number(rig.elapsed_s())));
    ++commands;
    rig.enable();
    send_currents();
  }
  int k = 0;
  rig.run_for(o.duration_s, [&] {
    if (rig.session().state() != state || rig.session().fault_code() != fault) {
      state = rig.session().state();
      fault = rig.session().fault_code();
      status_line();
    }
    if (!current_a.empty() && ++k % 20 == 0 && rig.last() == ResultCode::ok) {
      send_currents();  // resent every heartbeat period, like set
    }
  });
  if (!current_a.empty()) {
    out.line(fmt::format(R"({{"t_s": {}, "dir": "tx", "kind": "state", "request": "disable"}})",
                         json_number(rig.elapsed_s())));
    ++commands;
    rig.release();
  }
  rig.session().set_telemetry_callback(nullptr, nullptr);
  const std::size_t lines = out.lines();
  if (!out.close()) {
    throw Error(fmt::format("record: writing {} failed (disk full?); the file is incomplete", o.out));
  }
  print_record_summary(o, global, rig.elapsed_s(), lines, context.telemetry, commands, Rig::interrupted());
  return tools::kOk;
}

// --- replay ----------------------------------------------------------------------------

std::string event_json(const RecordedEvent& e) {
  std::string out = fmt::format(R"({{"line": {}, "t_s": {}, "dir": "{}", "kind": "{}")", e.line,
                                json_number(e.t_s), e.tx ? "tx" : "rx", e.kind);
  if (!e.request.empty()) {
    out += fmt::format(R"(, "request": "{}")", e.request);
  }
  if (!e.state.empty()) {
    out += fmt::format(R"(, "state": "{}", "fault": "{}")", json_escape(e.state), json_escape(e.fault));
  }
  if (e.kind == "telemetry") {
    out += fmt::format(R"(, "device_time_s": {})", json_number(e.device_time_s));
  }
  if (e.kind == "telemetry" || e.kind == "targets") {
    out += fmt::format(R"(, "first": {})", e.first);
  }
  if (!e.values.empty()) {
    out += ", \"values\": " + record_numbers(e.values);
  }
  if (e.kind == "cells") {
    const CellsSample& c = e.cells;
    out += fmt::format(
        R"(, "rendered_n": {}, "target_n": {}, "law_n": {}, "floor_n": {}, "ceiling_n": {}, "loaded": {})",
        record_numbers(c.rendered_n), record_numbers(c.target_n), record_numbers(c.law_n),
        record_numbers(c.floor_n), record_numbers(c.ceiling_n), record_numbers(c.loaded));
  }
  return out + "}";
}

std::string event_text(const RecordedEvent& e, const Recording& r) {
  std::string out = fmt::format("{:10.6f} s {} {:<9}", e.t_s, e.tx ? "tx" : "rx", e.kind);
  if (e.kind == "state") {
    out += " " + e.request;
  } else if (e.kind == "status") {
    out += fmt::format(" {} (fault: {})", e.state, e.fault);
  } else if (e.kind == "currents") {
    out += fmt::format(" valves 0..{} [A]: {:.6g}", e.values.size() - 1, fmt::join(e.values, " "));
  } else if (e.kind == "targets") {
    out += fmt::format(" cell {}: {:.6g} N/m, {:.6g} m, {:.6g} N, {:.6g} s", e.first, e.values[0],
                       e.values[1], e.values[2], e.values[3]);
  } else if (e.kind == "telemetry") {
    out += fmt::format(" device {:.6f} s sensors {}..{} [{}]: {:.4g}", e.device_time_s, e.first,
                       e.first + e.values.size() - 1, r.sensor_unit, fmt::join(e.values, " "));
  } else if (e.kind == "cells") {
    out += fmt::format(" rendered ({}) [N]: {:.4g}; target [N]: {:.4g}", r.rendered,
                       fmt::join(e.cells.rendered_n, " "), fmt::join(e.cells.target_n, " "));
  }
  return out;
}

int run_replay(const ReplayOptions& o, const GlobalOptions& global) {
  const Recording r = read_recording(o.file);
  std::size_t commands = 0;
  std::size_t telemetry = 0;
  for (const RecordedEvent& e : r.events) {
    commands += e.tx ? 1U : 0U;
    telemetry += e.kind == "telemetry" ? 1U : 0U;
  }
  if (o.to_device.empty()) {
    if (global.json) {
      std::string out = fmt::format(
          R"({{"file": "{}", "uri": "{}", "valves": {}, "fluid_cells": {}, "sensors": {}, "sensor_unit": "{}", )"
          R"("max_current_a": {}, "commands": {}, "telemetry": {}, "events": [)",
          json_escape(o.file), json_escape(r.uri), r.valves, r.fluid_cells, r.sensors,
          json_escape(r.sensor_unit), json_number(r.max_current_a), commands, telemetry);
      for (std::size_t i = 0; i < r.events.size(); ++i) {
        out += (i == 0 ? "" : ", ") + event_json(r.events[i]);
      }
      fmt::print("{}]}}\n", out);
    } else {
      fmt::print("recording of {}: {} valves, {} sensors in {}; {} events ({} commands, {} telemetry)\n",
                 r.uri, r.valves, r.sensors, r.sensor_unit, r.events.size(), commands, telemetry);
      for (const RecordedEvent& e : r.events) {
        fmt::print("{}\n", event_text(e, r));
      }
    }
    return tools::kOk;
  }

  Rig rig(o.to_device, o.realtime, o.lease.lease_socket());
  const DeviceInfo& info = rig.info();
  // The target device's limits, checked for every command before the first is sent.
  std::vector<protocol::CellTarget> targets(r.events.size());
  for (std::size_t i = 0; i < r.events.size(); ++i) {
    const RecordedEvent& e = r.events[i];
    const std::string where = fmt::format("{}:{}", o.file, e.line);
    if (e.kind == "currents") {
      check_currents(e.values, info, where);
    } else if (e.kind == "targets") {
      targets[i] = check_target(e.first, {e.values[0], e.values[1], e.values[2], e.values[3]}, info, where);
    }
  }
  std::size_t sent = 0;
  std::size_t refused = 0;
  for (std::size_t i = 0; i < r.events.size() && !Rig::interrupted(); ++i) {
    const RecordedEvent& e = r.events[i];
    if (!e.tx) {
      continue;
    }
    while (rig.elapsed_s() < e.t_s && !Rig::interrupted()) {
      rig.tick();
    }
    ResultCode rc = ResultCode::ok;
    if (e.kind == "state") {
      if (e.request == "enable") {
        rig.enable();
      } else if (e.request == "disable") {
        rig.release();
      } else if (e.request == "pause") {
        rc = rig.session().request_pause();
      } else {
        rc = rig.session().request_estop();
      }
    } else if (e.kind == "currents") {
      rc = rig.session().send_valve_currents(e.values);
    } else {
      const std::array<protocol::CellTarget, 1> one{targets[i]};
      rc = rig.session().send_cell_targets(static_cast<std::uint16_t>(e.first), one);
    }
    ++sent;
    refused += rc == ResultCode::ok ? 0U : 1U;
  }
  rig.run_for(0.02);
  const DeviceState state = rig.session().state();
  const std::uint8_t fault = rig.session().fault_code();
  const std::uint64_t received = rig.session().counters().telemetry;
  rig.release();
  if (global.json) {
    fmt::print(R"({{"file": "{}", "to_device": "{}", "commands_sent": {}, "commands_refused": {}, )"
               R"("telemetry_received": {}, "state": "{}", "fault": "{}", "interrupted": {}}})"
               "\n",
               json_escape(o.file), json_escape(o.to_device), sent, refused, received, to_string(state),
               fault_name(fault), Rig::interrupted() ? "true" : "false");
  } else {
    fmt::print(
        "replayed {} commands from {} to {} over {:.3f} s ({} refused by the session); {} telemetry "
        "packets received; state {} (fault: {}); released\n",
        sent, o.file, o.to_device, rig.elapsed_s(), refused, received, to_string(state), fault_name(fault));
  }
  return refused == 0 && !Rig::interrupted() ? tools::kOk : tools::kFailure;
}

}  // namespace

void add_record_commands(CliCommand app, const GlobalOptions& global, int& exit_code) {
  auto record = std::make_shared<RecordOptions>();
  CliCommand rec = app.subcommand(
      "record",
      "record telemetry, status changes and the commands sent to an NDJSON file (docs/cli.md); with "
      "--currents, "
      "enable and hold those currents while recording, then release. Exit 0 recorded, 2 bad arguments");
  add_device_options(rec, record->uri, record->realtime);
  rec.option("--out", record->out, "file to write").required();
  rec.option("--duration", record->duration_s, "seconds to record").show_default();
  CliOption currents =
      rec.option("--currents", record->currents, "hold these per-valve currents (A) while recording");
  CliOption bridge = rec.option("--bridge", record->bridge,
                                "record through a running mrskin-bridged on this control socket (it owns "
                                "the device): its raw sensors and commanded currents every 10 ms; "
                                "without a value, its default socket (" +
                                    bridged::default_socket_path() + " here)")
                         .value_optional()
                         .excludes(currents);
  if (const CliOption device = rec.find("--device"); device.exists()) {
    bridge.excludes(device);
  }
  rec.callback([record, bridge, &global, &exit_code] {
    record->use_bridge = bridge.given();
    exit_code = run_record(*record, global);
  });

  auto replay = std::make_shared<ReplayOptions>();
  CliCommand rep = app.subcommand("replay",
                                  "print a recording (or --json), or with --to-device re-send its commands "
                                  "with their timing, the device's "
                                  "limits checked again first. Exit 0 done, 1 the session refused a command, "
                                  "2 malformed file (the line is "
                                  "named) or a command outside the device's limits");
  rep.option("file", replay->file, "recording written by mrskinctl record").required();
  rep.option("--to-device", replay->to_device, "device URI to re-send the recorded commands to");
  rep.flag("--realtime", replay->realtime, "run a mock:// unit in real time instead of simulated time");
  add_lease_option(rep, replay->lease);
  rep.callback([replay, &global, &exit_code] {
    if (const std::optional<std::string> socket = replay->lease.lease_socket()) {
      replay->to_device = "bridge:" + *socket;  // re-sent through the daemon's device lease
    }
    exit_code = run_replay(*replay, global);
  });
}

}  // namespace mrskin::ctl
