// mrskinctl set: per-valve currents or one cell's impedance target, limits enforced, held for a
// while with the heartbeat alive, then released (zero currents, disable) on exit and on SIGINT.
#include <fmt/format.h>

#include <optional>
#include <string>
#include <vector>

#include "command.hpp"
#include "ctl_device_rig.hpp"
#include "exit_codes.hpp"
#include "json_text.hpp"

namespace mrskin::ctl {
namespace {

struct SetOptions {
  std::string uri = "mock://";
  LeaseOption lease;  // --bridge: the device of a running mrskin-bridged
  bool realtime = false;
  std::string currents;
  std::optional<std::size_t> valve;
  std::optional<double> current_a;
  std::optional<std::size_t> cell;
  std::optional<double> stiffness_n_per_m;
  std::optional<double> offset_m;
  double ceiling_n = TargetLimits::ceiling_max_n;
  double validity_s = 0.1;
  double hold_s = 1.0;
};

std::string json_list(std::span<const double> values) {
  std::string out = "[";
  for (std::size_t i = 0; i < values.size(); ++i) {
    out += (i == 0 ? "" : ", ") + json_number(values[i]);
  }
  return out + "]";
}

int run_set(const SetOptions& o, const GlobalOptions& global) {
  const bool by_list = !o.currents.empty();
  const bool by_valve = o.valve.has_value() || o.current_a.has_value();
  const bool by_cell = o.cell.has_value() || o.stiffness_n_per_m.has_value() || o.offset_m.has_value();
  if (static_cast<int>(by_list) + static_cast<int>(by_valve) + static_cast<int>(by_cell) != 1) {
    throw InvalidArgument(
        "set: give exactly one of --currents A1,A2,..., --valve I --current-a X, or --cell I "
        "--stiffness-n-per-m K --offset-m D");
  }
  if (by_valve && (!o.valve || !o.current_a)) {
    throw InvalidArgument("set: --valve and --current-a go together");
  }
  if (by_cell && (!o.cell || !o.stiffness_n_per_m || !o.offset_m)) {
    throw InvalidArgument("set: --cell needs --stiffness-n-per-m and --offset-m");
  }
  if (!std::isfinite(o.hold_s) || o.hold_s < 0.0 || o.hold_s > 3600.0) {
    throw InvalidArgument("set: --hold must be 0..3600 s");
  }
  Rig rig(o.uri, o.realtime, o.lease.lease_socket());
  const DeviceInfo& info = rig.info();
  // Every limit is checked before anything is sent.
  std::vector<double> current_a(info.valves, 0.0);
  protocol::CellTarget target{};
  protocol::CellTargetSi target_si{};
  if (by_list) {
    current_a = parse_number_list(o.currents, "--currents");
    check_currents(current_a, info, "--currents");
  } else if (by_valve) {
    if (*o.valve >= info.valves) {
      throw InvalidArgument(fmt::format("--valve {}: the device has valves 0..{}", *o.valve,
                                        info.valves == 0 ? 0 : info.valves - 1));
    }
    current_a[*o.valve] = *o.current_a;
    check_currents(current_a, info, "--current-a");
  } else {
    target_si = {*o.stiffness_n_per_m, *o.offset_m, o.ceiling_n, o.validity_s};
    target = check_target(*o.cell, target_si, info, "--cell");
  }

  rig.enable();
  // Resend every heartbeat period: a lossy link cannot lose the setting, and a target's
  // validity is renewed while held.
  const auto send = [&] {
    if (by_cell) {
      const std::array<protocol::CellTarget, 1> one{target};
      return rig.session().send_cell_targets(static_cast<std::uint16_t>(*o.cell), one);
    }
    return rig.session().send_valve_currents(current_a);
  };
  ResultCode sent = send();
  std::vector<double> sum(info.sensors, 0.0);
  std::size_t samples = 0;
  std::uint32_t last_time_us = rig.session().sensor_device_time_us();
  int k = 0;
  const double average_from_s = rig.elapsed_s() + std::max(0.0, o.hold_s - 0.1);
  rig.run_for(o.hold_s, [&] {
    if (++k % 20 == 0 && rig.last() == ResultCode::ok) {
      sent = send();
    }
    const std::uint32_t t_us = rig.session().sensor_device_time_us();
    if (t_us != last_time_us && rig.elapsed_s() >= average_from_s) {
      last_time_us = t_us;
      const auto s = rig.session().sensors();
      for (std::size_t i = 0; i < s.size() && i < sum.size(); ++i) {
        sum[i] += s[i];
      }
      ++samples;
    }
  });
  const bool interrupted = Rig::interrupted();
  const DeviceState state = rig.session().state();
  const std::uint8_t fault = rig.session().fault_code();
  const bool derated = rig.session().derated();
  std::vector<double> mean(sum.size(), 0.0);
  for (std::size_t i = 0; i < sum.size(); ++i) {
    mean[i] = samples > 0 ? sum[i] / static_cast<double>(samples) : rig.session().sensors()[i];
  }
  const std::vector<double> commanded(rig.session().commanded_currents().begin(),
                                      rig.session().commanded_currents().end());
  rig.release();
  const bool ok = state == DeviceState::enabled && sent == ResultCode::ok && !interrupted;

  if (global.json) {
    std::string out = fmt::format(R"({{"uri": "{}", "mode": "{}", "hold_s": {}, )", json_escape(o.uri),
                                  by_cell ? "cell" : "currents", json_number(o.hold_s));
    if (by_cell) {
      out += fmt::format(
          R"("cell": {}, "target": {{"stiffness_n_per_m": {}, "offset_m": {}, "ceiling_n": {}, "validity_s": {}}}, )",
          *o.cell, json_number(target_si.stiffness_N_per_m), json_number(target_si.offset_m),
          json_number(target_si.ceiling_N), json_number(target_si.validity_s));
    }
    out += fmt::format(
        R"("commanded_currents_a": {}, "state": "{}", "fault": "{}", "derated": {}, "last_send": "{}", )"
        R"("sensor_unit": "{}", "sensor_samples": {}, "sensors_mean": {}, "interrupted": {}, "released": true}})",
        json_list(commanded), to_string(state), fault_name(fault), derated ? "true" : "false",
        to_string(sent), info.sensor_unit, samples, json_list(mean), interrupted ? "true" : "false");
    fmt::print("{}\n", out);
  } else {
    if (by_cell) {
      fmt::print(
          "set cell {}: stiffness {} N/m, offset {} m, ceiling {} N, validity {} s (renewed every 20 ms)\n",
          *o.cell, target_si.stiffness_N_per_m, target_si.offset_m, target_si.ceiling_N,
          target_si.validity_s);
    } else {
      fmt::print("set currents [A]: {:.6g}\n", fmt::join(commanded, " "));
    }
    fmt::print("held {:.3f} s{}; state {} (fault: {}){}; last send: {}\n", o.hold_s,
               interrupted ? " (interrupted)" : "", to_string(state), fault_name(fault),
               derated ? ", derated" : "", to_string(sent));
    fmt::print("sensors [{}], mean of the last {} telemetry packets:\n  {:.4g}\n", info.sensor_unit, samples,
               fmt::join(mean, " "));
    fmt::print("released: currents 0 A, disable requested\n");
  }
  return ok ? tools::kOk : tools::kFailure;
}

}  // namespace

void add_set_command(CliCommand app, const GlobalOptions& global, int& exit_code) {
  auto options = std::make_shared<SetOptions>();
  CliCommand sub = app.subcommand(
      "set",
      "send per-valve currents (A) or one cell's impedance target, limits enforced; enable, hold with the "
      "heartbeat alive, print the telemetry, then release (also on Ctrl-C). Exit 0 held, 1 the device "
      "refused or faulted, 2 a value outside the device's or the protocol's limits");
  add_device_options(sub, options->uri, options->realtime);
  sub.option("--currents", options->currents, "one current per valve, A, comma-separated");
  sub.option("--valve", options->valve, "one valve's index (with --current-a; the others get 0 A)");
  sub.option("--current-a", options->current_a, "that valve's current, A");
  sub.option("--cell", options->cell, "fluid cell index for an impedance target");
  sub.option("--stiffness-n-per-m", options->stiffness_n_per_m, "target stiffness, N/m (0..32766)");
  sub.option("--offset-m", options->offset_m, "target offset, m (0..0.00819)");
  sub.option("--ceiling-n", options->ceiling_n, "force ceiling, N (0..4.095)").show_default();
  sub.option("--validity-s", options->validity_s, "validity of each resend, s (0..0.63)").show_default();
  sub.option("--hold", options->hold_s, "seconds to hold the setting").show_default();
  add_lease_option(sub, options->lease);
  sub.callback([options, &global, &exit_code] {
    if (const std::optional<std::string> socket = options->lease.lease_socket()) {
      options->uri = "bridge:" + *socket;  // what the report names; the Rig leases the socket
    }
    exit_code = run_set(*options, global);
  });
}

}  // namespace mrskin::ctl
