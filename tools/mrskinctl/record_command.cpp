// Placeholder until this command lands (#11).
#include "command.hpp"

namespace mrskin::ctl {

void add_record_commands(CLI::App& app, const GlobalOptions& /*global*/, int& exit_code) {
  add_unavailable_command(app, "record", "record telemetry and commands to a file", exit_code);
  add_unavailable_command(app, "replay", "replay a recording", exit_code);
}

}  // namespace mrskin::ctl
