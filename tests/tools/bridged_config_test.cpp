// mrskin-bridged's configuration: the TOML file, its errors (FILE:LINE and the key), flag
// overrides, and the control-socket request parser.
#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <sched.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <numbers>
#include <string>
#include <thread>

#include "config.hpp"
#include "control_server.hpp"
#include "mrskin/driver/errors.hpp"
#include "session_gate.hpp"

namespace {

using mrskin::bridged::ConfigError;
using mrskin::bridged::load_settings;
using mrskin::bridged::Settings;

class ConfigFile : public ::testing::Test {
 protected:
  std::string write(const std::string& text) {
    std::ofstream(path_) << text;
    return path_;
  }
  void TearDown() override { std::filesystem::remove(path_); }
  std::string path_ = (std::filesystem::temp_directory_path() /
                       ("mrskin-bridged-config-" + std::to_string(::getpid()) + ".toml"))
                          .string();
};

std::string error_of(const std::string& path) {
  try {
    (void)load_settings(path);
  } catch (const ConfigError& e) {
    return e.what();
  }
  return "";
}

TEST_F(ConfigFile, ReadsEveryKey) {
  const Settings s = load_settings(write(R"(device = "mock://?seed=3"
source = "scene://tumour"
rate_hz = 500
duration_s = 2.5
stats_json = "/tmp/x.json"
record = "/tmp/in.stream"
quiet = true
device_lost_s = 3
[mapping]
origin_x_m = 0.01
origin_y_m = -0.02
cells_per_m = 50
rotation_deg = 90
mirror_x = true
mirror_y = false
[stream]
force_device = "FTSensor"
pose_device = "*"
map_device = "Tactile"
pose_tool = "Stylus"
robot_rpy_deg = [0, 0, 90]
robot_origin_m = [0.01, 0, 0.005]
[bridge]
feedback_gain_per_s = 20.0
footprint_cells = 2
resend_period_s = 0.1
realtime = false
rt_priority = 50
stale_hold_s = 0.2
stale_fade_s = 0.4
[control]
socket = "/tmp/x/bridged.sock"
max_clients = 4
)"));
  EXPECT_EQ(s.device, "mock://?seed=3");
  EXPECT_EQ(s.source, "scene://tumour");
  EXPECT_DOUBLE_EQ(s.rate_hz, 500.0);
  EXPECT_DOUBLE_EQ(s.duration_s, 2.5);
  EXPECT_EQ(s.stats_json, "/tmp/x.json");
  EXPECT_EQ(s.record, "/tmp/in.stream");
  EXPECT_TRUE(s.quiet);
  EXPECT_DOUBLE_EQ(s.device_lost_s, 3.0);
  EXPECT_DOUBLE_EQ(s.mapping.origin_x_m, 0.01);
  EXPECT_DOUBLE_EQ(s.mapping.origin_y_m, -0.02);
  EXPECT_DOUBLE_EQ(s.mapping.cells_per_m, 50.0);
  EXPECT_NEAR(s.mapping.rotation_rad, std::numbers::pi / 2, 1e-12);
  EXPECT_TRUE(s.mapping.mirror_x);
  EXPECT_FALSE(s.mapping.mirror_y);
  EXPECT_DOUBLE_EQ(s.feedback_gain_per_s, 20.0);
  EXPECT_DOUBLE_EQ(s.footprint_cells, 2.0);
  EXPECT_DOUBLE_EQ(s.resend_period_s, 0.1);
  EXPECT_FALSE(s.realtime);
  EXPECT_EQ(s.rt_priority, 50);
  EXPECT_EQ(s.socket, "/tmp/x/bridged.sock");
  EXPECT_EQ(s.max_clients, 4);
  const mrskin::bridge::BridgeOptions o = mrskin::bridged::bridge_options(s);
  EXPECT_DOUBLE_EQ(o.rate_hz, 500.0);
  EXPECT_DOUBLE_EQ(o.feedback_gain_per_s, 20.0);
  EXPECT_DOUBLE_EQ(o.estimator.hold_s, 0.2);
  EXPECT_DOUBLE_EQ(o.estimator.fade_s, 0.4);
  EXPECT_DOUBLE_EQ(o.mapping.cells_per_m, 50.0);
  const mrskin::bridge::SourceOptions so = mrskin::bridged::source_options(s);
  EXPECT_EQ(so.igtl_force_device, "FTSensor");
  EXPECT_EQ(so.igtl_pose_device, "*");
  EXPECT_EQ(so.igtl_map_device, "Tactile");
  EXPECT_EQ(so.igtl_pose_tool, "Stylus");
  EXPECT_NEAR(so.robot_to_tissue[3], 1.0, 1e-12);  // yaw 90: the robot's x is the tissue's y
  EXPECT_NEAR(so.robot_to_tissue[1], -1.0, 1e-12);
  EXPECT_DOUBLE_EQ(so.robot_origin_m[0], 0.01);
  EXPECT_DOUBLE_EQ(so.robot_origin_m[2], 0.005);
}

TEST_F(ConfigFile, AnEmptyFileKeepsTheDefaults) {
  const Settings s = load_settings(write(""));
  EXPECT_EQ(s.device, "mock://");
  EXPECT_EQ(s.source, "scene://demo");
  EXPECT_DOUBLE_EQ(s.rate_hz, 1000.0);
}

TEST(ExampleConfig, LoadsWithTheDefaults) {
  const Settings s = load_settings(MRSKIN_BRIDGED_EXAMPLE);
  const Settings d;
  EXPECT_EQ(s.device, d.device);
  EXPECT_EQ(s.source, d.source);
  EXPECT_DOUBLE_EQ(s.rate_hz, d.rate_hz);
  EXPECT_DOUBLE_EQ(s.feedback_gain_per_s, d.feedback_gain_per_s);
  EXPECT_DOUBLE_EQ(s.mapping.cells_per_m, d.mapping.cells_per_m);
  EXPECT_EQ(s.max_clients, d.max_clients);
}

TEST_F(ConfigFile, AnUnknownKeyNamesFileLineAndKey) {
  const std::string e = error_of(write("rate_hz = 1000\n[bridge]\nfeedback_gain = 3\n"));
  EXPECT_NE(e.find(path_ + ":3:"), std::string::npos) << e;
  EXPECT_NE(e.find("bridge.feedback_gain"), std::string::npos) << e;
  EXPECT_NE(e.find("unknown key"), std::string::npos) << e;
  const std::string top = error_of(write("\nsecene = \"demo\"\n"));
  EXPECT_NE(top.find(path_ + ":2: secene"), std::string::npos) << top;
}

TEST_F(ConfigFile, ABadValueNamesFileLineAndKey) {
  std::string e = error_of(write("device = \"mock://\"\nrate_hz = \"fast\"\n"));
  EXPECT_NE(e.find(path_ + ":2: rate_hz"), std::string::npos) << e;
  e = error_of(write("rate_hz = 50000\n"));
  EXPECT_NE(e.find(path_ + ":1: rate_hz"), std::string::npos) << e;
  EXPECT_NE(e.find("out of range"), std::string::npos) << e;
  e = error_of(write("[mapping]\ncells_per_m = -1\n"));
  EXPECT_NE(e.find(path_ + ":2: mapping.cells_per_m"), std::string::npos) << e;
  e = error_of(write("[bridge]\nrealtime = 1\n"));
  EXPECT_NE(e.find(path_ + ":2: bridge.realtime"), std::string::npos) << e;
  e = error_of(write("mapping = 3\n"));
  EXPECT_NE(e.find(path_ + ":1: mapping"), std::string::npos) << e;
  e = error_of(write("[stream]\nforce_device = \"\"\n"));
  EXPECT_NE(e.find(path_ + ":2: stream.force_device"), std::string::npos) << e;
  e = error_of(write("[stream]\nrobot_rpy_deg = [0, 0]\n"));
  EXPECT_NE(e.find(path_ + ":2: stream.robot_rpy_deg"), std::string::npos) << e;
  e = error_of(write("[stream]\nrobot_rpy_deg = [0, 0, 400]\n"));
  EXPECT_NE(e.find("stream.robot_rpy_deg"), std::string::npos) << e;
  e = error_of(write("duration_s = 1e10\n"));
  EXPECT_NE(e.find(path_ + ":1: duration_s"), std::string::npos) << e;
  e = error_of(write("[bridge]\nstale_hold_s = 1e300\n"));
  EXPECT_NE(e.find(path_ + ":2: bridge.stale_hold_s"), std::string::npos) << e;
  e = error_of(write("rate_hz = = 3\n"));
  EXPECT_NE(e.find(path_ + ":1:"), std::string::npos) << e;
}

// [topics]: the skin as ROS 2 topics; every key bounded, a namespace ROS 2 accepts.
TEST_F(ConfigFile, TopicsAreReadAndBounded) {
  const Settings s =
      load_settings(write("[topics]\nnamespace = \"/mrskin/left\"\nrate_hz = 50\ndomain = 7\n"));
  EXPECT_EQ(s.topics_namespace, "/mrskin/left");
  EXPECT_DOUBLE_EQ(s.topics_rate_hz, 50.0);
  EXPECT_EQ(s.topics_domain, 7);
  EXPECT_NO_THROW(mrskin::bridged::validate(s, "file"));
  std::string e = error_of(write("[topics]\nrate_hz = 1000\n"));
  EXPECT_NE(e.find(path_ + ":2: topics.rate_hz"), std::string::npos) << e;
  e = error_of(write("[topics]\ndomain = 233\n"));
  EXPECT_NE(e.find(path_ + ":2: topics.domain"), std::string::npos) << e;
  e = error_of(write("[topics]\nnamspace = \"/x\"\n"));
  EXPECT_NE(e.find("unknown key"), std::string::npos) << e;
  Settings bad = s;
  bad.topics_namespace = "/skin//left";  // --topics /skin//left
  EXPECT_THROW(mrskin::bridged::validate(bad, "flags"), ConfigError);
}

// [bridge] cpu / --cpu: the tick thread's CPU, one the process may run on, or -1.
TEST_F(ConfigFile, TheLoopCpuIsOneTheProcessMayRunOn) {
  cpu_set_t set;
  CPU_ZERO(&set);
  ASSERT_EQ(sched_getaffinity(0, sizeof(set), &set), 0);
  int allowed = 0;
  while (!CPU_ISSET(static_cast<std::size_t>(allowed), &set)) {
    ++allowed;
  }
  Settings s = load_settings(write("[bridge]\ncpu = " + std::to_string(allowed) + "\n"));
  EXPECT_EQ(s.cpu, allowed);
  EXPECT_EQ(mrskin::bridged::bridge_tuning(s).loop_cpu, allowed);
  EXPECT_EQ(Settings{}.cpu, -1);
  std::string e = error_of(write("[bridge]\ncpu = 4096\n"));
  EXPECT_NE(e.find(path_ + ":2: bridge.cpu"), std::string::npos) << e;
  EXPECT_NE(e.find("a CPU this process may run on ("), std::string::npos) << e;
  e = error_of(write("[bridge]\ncpu = -2\n"));
  EXPECT_NE(e.find(path_ + ":2: bridge.cpu"), std::string::npos) << e;
  mrskin::bridged::Overrides o;
  o.cpu = 100000;  // --cpu 100000
  mrskin::bridged::apply(o, s);
  try {
    mrskin::bridged::validate(s, "flags");
    ADD_FAILURE() << "--cpu 100000 was taken";
  } catch (const ConfigError& err) {
    EXPECT_NE(std::string(err.what()).find("flags: cpu: 100000 is not a CPU"), std::string::npos)
        << err.what();
  }
}

// --check-config refuses what the run would refuse, as the run would (InvalidArgument: exit 2; an
// unreadable file: mrskin::Error, exit 1), and opens nothing: the UDP port the source names stays
// ours while it is checked.
TEST(CheckConfig, RefusesWhatTheRunWouldAndOpensNothing) {
  Settings s;
  EXPECT_NO_THROW(mrskin::bridged::check_uris(s));  // mock://, scene://demo
  const auto refused = [](Settings bad) -> std::string {
    try {
      mrskin::bridged::check_uris(bad);
    } catch (const mrskin::InvalidArgument& e) {
      return std::string("usage: ") + e.what();
    } catch (const mrskin::Error& e) {
      return std::string("error: ") + e.what();
    }
    return "taken";
  };
  Settings bad = s;
  bad.source = "scene://nope";
  EXPECT_NE(refused(bad).find("usage: unknown scene 'nope'"), std::string::npos) << refused(bad);
  bad.source = "udp://127.0.0.1:0?queue=abc";
  EXPECT_NE(refused(bad).find("usage: source 'udp://127.0.0.1:0?queue=abc': bad queue"), std::string::npos)
      << refused(bad);
  bad.source = "replay:///nonexistent/take.csv";
  EXPECT_NE(refused(bad).find("error: replay:///nonexistent/take.csv: cannot read"), std::string::npos)
      << refused(bad);
  bad = s;
  bad.device = "nope://";
  EXPECT_NE(refused(bad).find("usage: 'nope://' is not a device URI"), std::string::npos) << refused(bad);
  bad.device = "hid://zz";
  EXPECT_NE(refused(bad).find("usage: 'hid://zz'"), std::string::npos) << refused(bad);
  bad.device = "mock://no-such-skin";
  EXPECT_NE(refused(bad).find("no-such-skin"), std::string::npos) << refused(bad);

  const int fd = ::socket(AF_INET, SOCK_DGRAM, 0);
  ASSERT_GE(fd, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  ASSERT_EQ(::bind(fd, reinterpret_cast<const sockaddr*>(&a), sizeof(a)), 0);
  socklen_t len = sizeof(a);
  ASSERT_EQ(::getsockname(fd, reinterpret_cast<sockaddr*>(&a), &len), 0);
  Settings udp = s;
  udp.source = "udp://127.0.0.1:" + std::to_string(ntohs(a.sin_port));
  EXPECT_EQ(refused(udp), "taken");  // binding it would have failed: the port is ours
  ::close(fd);
}

TEST_F(ConfigFile, AMissingFileIsAUsageError) {
  const std::string e = error_of("/nonexistent/mrskin.toml");
  EXPECT_NE(e.find("/nonexistent/mrskin.toml"), std::string::npos) << e;
}

TEST_F(ConfigFile, FlagsOverrideTheFile) {
  Settings s = load_settings(write("rate_hz = 500\ndevice = \"mock://?seed=1\"\nquiet = true\n"));
  mrskin::bridged::Overrides o;
  o.rate_hz = 250.0;
  o.source = "scene://sweep";
  o.quiet = false;
  mrskin::bridged::apply(o, s);
  EXPECT_DOUBLE_EQ(s.rate_hz, 250.0);
  EXPECT_EQ(s.source, "scene://sweep");
  EXPECT_EQ(s.device, "mock://?seed=1");  // not overridden
  EXPECT_FALSE(s.quiet);
  s.rate_hz = 0.5;
  EXPECT_THROW(mrskin::bridged::validate(s, "flags"), ConfigError);
}

TEST(DefaultSocket, FollowsTheRuntimeDirectory) {
  ::setenv("RUNTIME_DIRECTORY", "/run/mrskin:/run/other", 1);
  EXPECT_EQ(mrskin::bridged::default_socket_path(), "/run/mrskin/bridged.sock");
  ::unsetenv("RUNTIME_DIRECTORY");
  ::setenv("XDG_RUNTIME_DIR", "/run/user/1000", 1);
  EXPECT_EQ(mrskin::bridged::default_socket_path(), "/run/user/1000/mrskin/bridged.sock");
  ::unsetenv("XDG_RUNTIME_DIR");
  EXPECT_EQ(mrskin::bridged::default_socket_path(),
            "/tmp/mrskin-" + std::to_string(::getuid()) + "/bridged.sock");
}

TEST(ControlRequest, ParsesJsonAndBareWords) {
  mrskin::bridged::ControlRequest r;
  std::string error;
  ASSERT_TRUE(mrskin::bridged::parse_request(R"({"cmd":"telemetry","period_ms":50})", r, error)) << error;
  EXPECT_EQ(r.cmd, "telemetry");
  EXPECT_DOUBLE_EQ(r.period_ms, 50.0);
  ASSERT_TRUE(mrskin::bridged::parse_request(R"( { "cmd" : "status" } )", r, error)) << error;
  EXPECT_EQ(r.cmd, "status");
  ASSERT_TRUE(mrskin::bridged::parse_request("estop", r, error)) << error;
  EXPECT_EQ(r.cmd, "estop");
  for (const char* bad : {"{", R"({"cmd":)", R"({"cmd":"status")", R"({"cmd":"a"} x)", R"({"x":1})", "{}",
                          R"({"cmd":"a","period_ms":nan})", R"({"cmd":[1]})", "st@tus", R"("cmd")"}) {
    EXPECT_FALSE(mrskin::bridged::parse_request(bad, r, error)) << bad;
    EXPECT_FALSE(error.empty()) << bad;
  }
}

// Requests are read with nlohmann-json: escapes decoded, any JSON number for period_ms; a bad
// line gets an error that says what is wrong (nlohmann-json's words for malformed JSON).
TEST(ControlRequest, ReadsJsonAndNamesWhatIsWrong) {
  mrskin::bridged::ControlRequest r;
  std::string error;
  ASSERT_TRUE(mrskin::bridged::parse_request(R"({"cmd":"st\u0061tus"})", r, error)) << error;
  EXPECT_EQ(r.cmd, "status");
  ASSERT_TRUE(
      mrskin::bridged::parse_request(R"({"grid":false,"period_ms":2.5e1,"cmd":"telemetry"})", r, error))
      << error;
  EXPECT_EQ(r.cmd, "telemetry");
  EXPECT_DOUBLE_EQ(r.period_ms, 25.0);
  EXPECT_FALSE(r.grid);
  const struct {
    const char* line;
    const char* error;
  } cases[] = {
      {R"({"cmd": )",
       "malformed JSON: syntax error while parsing value - unexpected end of input; expected '[', '{', or a "
       "literal (column 9)"},
      {R"({"cmd":"status"} x)",
       "malformed JSON: syntax error while parsing value - invalid literal; last read: "
       "'\"status\"} x'; expected end of input (column 18)"},
      {R"({"cmd":"telemetry","period_ms":NaN})",
       "malformed JSON: syntax error while parsing value - invalid literal"},
      {R"({"cmd":"telemetry","period_ms":1e999})", "malformed JSON: number overflow parsing '1e999'"},
      {R"({"cmd":"status",})", "malformed JSON: syntax error while parsing object key - unexpected '}'"},
      {R"({"cmd":7})", R"("cmd" must be a string)"},
      {R"({"cmd":null})", R"("cmd" must be a string)"},
      {R"({"cmd":"telemetry","period_ms":"50"})", R"("period_ms" must be a number)"},
      {R"({"cmd":"telemetry","period_ms":null})", R"("period_ms" must be a number)"},
      {R"({"cmd":"telemetry","grid":1})", R"("grid" must be true or false)"},
      {R"({"cmd":"status","x":[1,{"a":2}]})", R"(unknown field "x")"},
      {R"({"cmd":""})", R"(missing "cmd")"},
      {"{}", R"(missing "cmd")"},
      {"St@tus", R"(malformed request: expected a JSON object such as {"cmd":"status"} or a command word)"},
      {" \t", "empty request"},
  };
  for (const auto& c : cases) {
    EXPECT_FALSE(mrskin::bridged::parse_request(c.line, r, error)) << c.line;
    EXPECT_TRUE(error.starts_with(c.error)) << c.line << "\n" << error;
  }
}

}  // namespace

// The session's hand-off between the tick and the control thread: while a reader holds the gate
// the tick skips, and a reader cannot get in while the tick is inside.
TEST(SessionGate, TheTickAndAReaderNeverHoldTheSessionTogether) {
  using mrskin::bridged::SessionGate;
  using namespace std::chrono_literals;
  SessionGate gate;
  ASSERT_TRUE(gate.try_tick());
  EXPECT_FALSE(gate.try_read(5ms));  // the tick is in: the reader gives up at its deadline
  gate.end_tick();
  ASSERT_TRUE(gate.try_read(5ms));
  EXPECT_FALSE(gate.try_tick());  // a reader is in: the tick skips
  EXPECT_FALSE(gate.try_tick());
  EXPECT_EQ(gate.gated_ticks(), 2U);
  gate.end_read();
  EXPECT_TRUE(gate.try_tick());
  gate.end_tick();

  // Two threads, bounded: the tick and a reader count how often each is inside; never both.
  std::atomic<int> inside{0};
  std::atomic<bool> overlap{false};
  std::atomic<bool> stop{false};
  std::thread tick([&] {
    for (int k = 0; k < 20000 && !stop.load(); ++k) {
      if (gate.try_tick()) {
        if (inside.fetch_add(1) != 0) {
          overlap.store(true);
        }
        inside.fetch_sub(1);
        gate.end_tick();
      }
    }
  });
  int reads = 0;
  for (int k = 0; k < 200; ++k) {
    if (gate.try_read(50ms)) {
      if (inside.fetch_add(1) != 0) {
        overlap.store(true);
      }
      inside.fetch_sub(1);
      gate.end_read();
      ++reads;
    }
  }
  stop.store(true);
  tick.join();
  EXPECT_FALSE(overlap.load());
  EXPECT_GT(reads, 0);
}
