// The logging conventions of every mrskin tool (docs/daemon.md, "Logging"): spdlog to stderr as
// "TOOL: LEVEL: message"; when stderr is the systemd journal ($JOURNAL_STREAM names stderr's
// device and inode), each line starts with its syslog priority instead ("<3>error: ..."), which
// journald strips and files the line under (sd-daemon(3)). --log-level on every tool.
#pragma once

#include <string>
#include <string_view>

#include "command_line.hpp"

namespace mrskin::tools {

// The levels --log-level and the daemon's log_level take, in spdlog's names.
inline constexpr const char* kLogLevels = "trace, debug, info, warn, error, critical or off";

// Sets the default logger (stderr, the conventions above) at level info. Call first in main.
void init_logging(std::string_view tool);
// True when stderr is connected to the journal (set by systemd for a service's stderr).
[[nodiscard]] bool stderr_is_journal() noexcept;
// Adds --log-level to app (checked against kLogLevels) writing into level.
CliOption add_log_level_option(CliCommand app, std::string& level);
// True if name is one of kLogLevels.
[[nodiscard]] bool is_log_level(std::string_view name) noexcept;
// Sets the default logger's level; name must be one of kLogLevels ("" leaves it).
void set_log_level(std::string_view name);

}  // namespace mrskin::tools
