// Placeholder until this command lands (#11).
#include "command.hpp"

namespace mrskin::ctl {

void add_selftest_command(CLI::App& app, const GlobalOptions& /*global*/, int& exit_code) {
  add_unavailable_command(app, "selftest", "valve sweep, sensor, latency, leak and stuck-sensor checks",
                          exit_code);
}

}  // namespace mrskin::ctl
