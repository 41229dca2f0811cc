// `mrskinctl model ...`: evaluates the device model's laws for a profile and prints JSON
// whose keys carry their SI unit (q_m3_s, dp_pa, tau_y_pa, h_a_m, b_t, force_n...).
#pragma once

#include <cstdio>

#include "command_line.hpp"

namespace mrskin::ctl {

using tools::CliCommand;
using tools::CliOption;

// Registers "model" and its subcommands (valve, fluid, coil, membrane, cell, profile) on `app`.
// The command runs from its CLI11 callback during parsing; `exit_code` receives 0 on success,
// 2 for a bad or out-of-range argument or profile, 1 when a law reports a failure. JSON goes to
// `out`, errors (one line, "error: ...") to `err`.
CliCommand add_model_command(CliCommand app, int& exit_code, std::FILE* out = stdout,
                             std::FILE* err = stderr);

}  // namespace mrskin::ctl
