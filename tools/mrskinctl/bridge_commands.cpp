// enable, disable, estop and fault on a running mrskin-bridged, through its control socket
// (docs/daemon.md). The daemon acts on a request at its next tick; --wait polls `status` until
// the bridge shows it.
#include <fmt/format.h>

#include <chrono>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "bridge_client.hpp"
#include "command.hpp"
#include "exit_codes.hpp"
#include "json_reply.hpp"
#include "line_client.hpp"

namespace mrskin::ctl {
namespace {

using namespace std::chrono_literals;

struct BridgeOptions {
  std::string socket;  // "" : the daemon's default
  double timeout_s = 5.0;
  bool wait = false;
};

std::chrono::milliseconds timeout_ms(const BridgeOptions& o) {
  return std::chrono::milliseconds(static_cast<std::int64_t>(o.timeout_s * 1e3));
}

// One request, its response line; throws when the daemon does not answer.
std::string ask(LineClient& c, const std::string& path, const std::string& cmd, const BridgeOptions& o) {
  std::optional<std::string> line = c.request(fmt::format(R"({{"cmd":"{}"}})", cmd), timeout_ms(o));
  if (!line) {
    throw Error(fmt::format("mrskin-bridged on {} did not answer `{}` within {} s (closed or busy)", path,
                            cmd, o.timeout_s));
  }
  return *std::move(line);
}

std::string field(const JsonReply& reply, std::string_view key) { return reply.text(key).value_or("?"); }

// Whether a status line shows the request done.
bool confirmed(const std::string& cmd, const JsonReply& status) {
  const std::string halted = field(status, "halted");
  if (cmd == "enable") {
    return halted == "false" && field(status, "state") == "ENABLED";
  }
  return halted == "true" && field(status, "operator") == cmd;
}

int run_request(const std::string& cmd, const BridgeOptions& o, const GlobalOptions& global) {
  const std::string path = bridge_socket(o.socket);
  LineClient c = connect_bridge(path);
  const std::string response = ask(c, path, cmd, o);
  const JsonReply reply(response);
  if (global.json) {
    fmt::print("{}\n", response);
  }
  if (reply.text("ok") != "true") {
    fmt::print(stderr, "mrskinctl {}: mrskin-bridged on {} refused: {}\n", cmd, path, field(reply, "error"));
    return tools::kFailure;
  }
  if (!o.wait) {
    if (!global.json) {
      fmt::print("{} requested on {}: {}\n", cmd, path, field(reply, "note"));
    }
    return tools::kOk;
  }
  const auto end = std::chrono::steady_clock::now() + timeout_ms(o);
  std::string line = ask(c, path, "status", o);
  JsonReply status(line);
  while (!confirmed(cmd, status)) {
    if (std::chrono::steady_clock::now() >= end) {
      fmt::print(stderr,
                 "mrskinctl {}: requested, but the bridge did not show it within {} s: state {}, halted {}, "
                 "fault {}\n",
                 cmd, o.timeout_s, field(status, "state"), field(status, "halted"), field(status, "fault"));
      return tools::kFailure;
    }
    std::this_thread::sleep_for(20ms);
    line = ask(c, path, "status", o);
    status = JsonReply(line);
  }
  if (global.json) {
    fmt::print("{}\n", line);
  } else {
    fmt::print("{} done on {}: state {}, fault {}, {}\n", cmd, path, field(status, "state"),
               field(status, "fault"), field(status, "halted") == "true" ? "halted" : "running");
  }
  return tools::kOk;
}

int run_fault(const BridgeOptions& o, const GlobalOptions& global) {
  const std::string path = bridge_socket(o.socket);
  LineClient c = connect_bridge(path);
  const std::string line = ask(c, path, "fault", o);
  const JsonReply response(line);
  const bool ok = response.text("ok") == "true" && !response.text("error").has_value();
  if (global.json) {
    fmt::print("{}\n", line);
  }
  if (!ok) {
    fmt::print(stderr, "mrskinctl fault: mrskin-bridged on {} answered with an error: {}\n", path,
               field(response, "error"));
    return tools::kFailure;
  }
  if (global.json) {
    return tools::kOk;
  }
  const std::string faults = field(response, "faults");
  fmt::print("state {}, fault: {} ({} fault{} since the daemon started", field(response, "state"),
             field(response, "fault"), faults, faults == "1" ? "" : "s");
  if (faults == "0") {
    fmt::print(")\nno fault yet: no ring log frozen\n");
    return tools::kOk;
  }
  const double at_s = response.number("last_fault_time_s").value_or(0.0);
  fmt::print("; last: {} at {:.3f} s)\n", field(response, "last_fault"), at_s);
  const std::vector<std::string> records = response.strings_in_array("log", "text");
  fmt::print("ring log frozen at the last fault, {} records, oldest first:\n", records.size());
  for (const std::string& record : records) {
    fmt::print("  {}\n", record);
  }
  return tools::kOk;
}

CliCommand add_one(CliCommand app, const char* name, const char* help, BridgeOptions& o) {
  CliCommand sub = app.subcommand(name, help);
  sub.option(
      "--bridge", o.socket,
      "the daemon's control socket (default: mrskin-bridged's, " + bridged::default_socket_path() + " here)");
  sub.option("--timeout", o.timeout_s, "seconds to wait for the daemon's answer (and for --wait)")
      .range(0.05, 600.0)
      .show_default();
  sub.footer(
      "Exit codes: 0 done; 1 the daemon refused or did not confirm (--wait); 2 bad arguments; 3 no "
      "mrskin-bridged answers on the socket.");
  return sub;
}

}  // namespace

void add_bridge_commands(CliCommand app, const GlobalOptions& global, int& exit_code) {
  const struct {
    const char* name;
    const char* help;
  } requests[] = {
      {"enable", "enable a running bridge: leave a disable, an e-stop or a latched fault"},
      {"disable", "disable a running bridge: every valve released, the device disabled"},
      {"estop",
       "emergency stop through a running bridge: zero currents within one tick, the device e-stopped"},
  };
  for (const auto& r : requests) {
    // Shared with the callback, which CLI11 keeps: the options outlive parsing.
    auto o = std::make_shared<BridgeOptions>();
    CliCommand sub = add_one(app, r.name, r.help, *o);
    sub.flag("--wait", o->wait,
             "poll the daemon's status until the bridge shows the request done (up to --timeout)");
    sub.callback(
        [name = std::string(r.name), o, &global, &exit_code] { exit_code = run_request(name, *o, global); });
  }
  auto fault_o = std::make_shared<BridgeOptions>();
  CliCommand fault =
      add_one(app, "fault",
              "a running bridge's device state, fault cause and the ring log frozen at the last "
              "fault, decoded",
              *fault_o);
  fault.callback([fault_o, &global, &exit_code] { exit_code = run_fault(*fault_o, global); });
}

}  // namespace mrskin::ctl
