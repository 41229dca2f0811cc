// Placeholder until this command lands (#11).
#include "command.hpp"

namespace mrskin::ctl {

void add_monitor_command(CLI::App& app, const GlobalOptions& /*global*/, int& exit_code) {
  add_unavailable_command(app, "monitor", "show the grid live", exit_code);
}

}  // namespace mrskin::ctl
