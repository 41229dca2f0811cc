// mrskin-bridged's configuration: built-in defaults, then the TOML file (--config), then the
// command-line flags. docs/daemon.md lists every key.
#pragma once

#include <array>
#include <optional>
#include <string>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/bridge/sources.hpp"
#include "mrskin/driver/errors.hpp"
#include "socket_path.hpp"  // default_socket_path()

namespace mrskin::bridged {

// A bad file, key or value; the message names FILE:LINE and the key. Exit code kUsage.
class ConfigError : public InvalidArgument {
 public:
  using InvalidArgument::InvalidArgument;
};

struct Settings {
  std::string device = "mock://";
  std::string source = "scene://demo";
  double rate_hz = 1000.0;
  // rate_hz came from the file or --rate. Without it a bus that cannot carry 1000 Hz runs the
  // loop at the highest whole rate it carries (logged); with it the daemon refuses (exit 2).
  bool rate_given = false;
  double duration_s = 0.0;  // 0: until SIGINT/SIGTERM
  std::string stats_json;   // "" : none
  std::string record;       // "" : none; else the input stream is recorded here (replay:// format)
  bool quiet = false;
  std::string log_level = "info";      // tools::kLogLevels; SIGHUP applies a new one
  bridge::WorkspaceMapping mapping{};  // [mapping]; rotation given in degrees in the file
  // [stream]: which OpenIGTLink devices the stream is read from and the robot's frame in the
  // tissue frame; the source URI's keys (force_device=...) override these.
  std::string force_device = "ContactForce";
  std::string pose_device = "InstrumentTip";
  std::string map_device = "TactileArray";
  std::string pose_tool = "*";
  std::array<double, 3> robot_rpy_deg{0.0, 0.0, 0.0};
  std::array<double, 3> robot_origin_m{0.0, 0.0, 0.0};
  // [bridge]
  double feedback_gain_per_s = 30.0;
  double footprint_cells = 1.5;
  double resend_period_s = 0.05;
  bool realtime = true;
  int rt_priority = 80;
  int cpu = -1;               // the tick thread pinned to this CPU; -1: not pinned
  double stale_hold_s = 0.1;  // stream watchdog: hold the last estimate this long...
  double stale_fade_s = 0.2;  // ...then fade to released over this
  // [topics]: the skin as ROS 2 topics over DDS (bridge/ros2_topics.hpp); namespace "" : off.
  std::string topics_namespace;
  double topics_rate_hz = 100.0;
  int topics_domain = 0;
  // [control]
  std::string socket;  // "" : default_socket_path()
  int max_clients = 8;
  double idle_timeout_s = 300.0;  // a silent client without a subscription or lease is closed
  // [device]-independent: how long the link may stay down before the daemon gives up (exit 1).
  double device_lost_s = 10.0;
};

// What the command line set; each overrides the file.
struct Overrides {
  std::optional<std::string> device;
  std::optional<std::string> source;
  std::optional<double> rate_hz;
  std::optional<int> cpu;
  std::optional<double> duration_s;
  std::optional<std::string> stats_json;
  std::optional<std::string> record;
  std::optional<bool> quiet;
  std::optional<std::string> log_level;
  std::optional<std::string> socket;
  std::optional<std::string> topics_namespace;
};

// Reads FILE over the defaults. Throws ConfigError naming FILE:LINE and the key for a syntax
// error, an unknown key, a value of the wrong type or out of range.
Settings load_settings(const std::string& path);
// Checks the ranges of values that may come from flags too; throws ConfigError naming origin.
void validate(const Settings& s, const std::string& origin);
// What --check-config adds to validate(): the device and source URIs checked as opening them
// would (a mock's profile loaded, a scene's name, a replay file readable), with nothing opened.
// Throws InvalidArgument or mrskin::Error as the run would, before it touches anything.
void check_uris(const Settings& s);
void apply(const Overrides& o, Settings& s);
bridge::BridgeOptions bridge_options(const Settings& s);
// The part of the settings a running bridge takes without a new one (Bridge::retune).
bridge::BridgeTuning bridge_tuning(const Settings& s);
// The stream source's options from [stream] (before the URI's own keys).
bridge::SourceOptions source_options(const Settings& s);
// True when the [stream] keys differ (a reload then reopens the source).
bool same_source_options(const Settings& a, const Settings& b) noexcept;

}  // namespace mrskin::bridged
