// Placeholder until this command lands (#11).
#include "command.hpp"

namespace mrskin::ctl {

void add_set_command(CLI::App& app, const GlobalOptions& /*global*/, int& exit_code) {
  add_unavailable_command(app, "set", "send per-valve currents or per-cell targets", exit_code);
}

}  // namespace mrskin::ctl
