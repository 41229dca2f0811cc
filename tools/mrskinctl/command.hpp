// What every mrskinctl subcommand gets: the global options and where to put its exit code.
// Each add_*_command() registers its subcommand(s) on the app; the work runs in the
// command's callback after parsing. Setup errors are thrown (main maps them to exit codes,
// tools/common/exit_codes.hpp); a command's own outcome goes into exit_code.
#pragma once

#include <cstdio>
#include <string>

#include "command_line.hpp"

namespace mrskin::ctl {

using tools::CliCommand;
using tools::CliOption;

struct GlobalOptions {
  bool json = false;  // --json, before or after the subcommand
};

// Registers a placeholder subcommand for something not in this build: exit 69.
inline CliCommand add_unavailable_command(CliCommand app, const char* name, const char* help,
                                          int& exit_code) {
  CliCommand sub = app.subcommand(name, std::string(help) + " [not in this build]");
  sub.allow_extras();
  sub.callback([&exit_code, name] {
    std::fputs("mrskinctl ", stderr);
    std::fputs(name, stderr);
    std::fputs(": not available in this build\n", stderr);
    exit_code = 69;
  });
  return sub;
}

void add_monitor_command(CliCommand app, const GlobalOptions& global, int& exit_code);
// enable, disable, estop and fault on a running mrskin-bridged.
void add_bridge_commands(CliCommand app, const GlobalOptions& global, int& exit_code);
void add_set_command(CliCommand app, const GlobalOptions& global, int& exit_code);
void add_selftest_command(CliCommand app, const GlobalOptions& global, int& exit_code);
void add_calibrate_command(CliCommand app, const GlobalOptions& global, int& exit_code);
// record and replay.
void add_record_commands(CliCommand app, const GlobalOptions& global, int& exit_code);
void add_plot_command(CliCommand app, const GlobalOptions& global, int& exit_code);
void add_budget_command(CliCommand app, const GlobalOptions& global, int& exit_code);

}  // namespace mrskin::ctl
