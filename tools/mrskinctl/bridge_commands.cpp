// Placeholder until this command lands (#11).
#include "command.hpp"

namespace mrskin::ctl {

void add_bridge_commands(CLI::App& app, const GlobalOptions& /*global*/, int& exit_code) {
  add_unavailable_command(app, "enable", "enable a running bridge", exit_code);
  add_unavailable_command(app, "disable", "disable a running bridge", exit_code);
  add_unavailable_command(app, "estop", "emergency stop through a running bridge", exit_code);
  add_unavailable_command(app, "fault", "a running bridge's fault cause and ring log", exit_code);
}

}  // namespace mrskin::ctl
