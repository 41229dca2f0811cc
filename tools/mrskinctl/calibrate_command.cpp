// Placeholder until this command lands (#11).
#include "command.hpp"

namespace mrskin::ctl {

void add_calibrate_command(CLI::App& app, const GlobalOptions& /*global*/, int& exit_code) {
  add_unavailable_command(app, "calibrate", "yield sweep, degauss, tare; store on the device", exit_code);
}

}  // namespace mrskin::ctl
