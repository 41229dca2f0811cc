// The mrskin-bridged binary on mock://, driven over its control socket: permissions, status,
// e-stop -> fault -> enable, the e-stop's released valves, malformed requests, telemetry, SIGHUP
// reload on the open device, SIGTERM and SIGINT with the statistics flushed, UDP, replay and
// OpenIGTLink sources, and every exit code the daemon can be driven to here. Waits are bounded
// polls.
#include <arpa/inet.h>
#include <fcntl.h>
#include <gtest/gtest.h>
#include <igtlClientSocket.h>
#include <igtlSensorMessage.h>
#include <igtlTrackingDataMessage.h>
#include <igtlUnit.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "child_process.hpp"
#include "exit_codes.hpp"
#include "json_reply.hpp"
#include "line_client.hpp"
#include "mrskin/bridge/sources.hpp"

namespace {

namespace fs = std::filesystem;
using mrskin::ctl::json_field;
using mrskin::ctl::LineClient;
using namespace std::chrono_literals;

using mrskin::test::eventually;
using mrskin::test::kMaxSkippedFraction;
using mrskin::test::slurp;

// A free loopback port of this type (SOCK_DGRAM, SOCK_STREAM): the daemon binds it next.
std::uint16_t free_port(int type) {
  const int fd = ::socket(AF_INET, type, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  socklen_t len = sizeof(a);
  // NOLINTNEXTLINE(cppcoreguidelines-pro-type-reinterpret-cast): the socket API's own cast
  const bool ok = ::bind(fd, reinterpret_cast<const sockaddr*>(&a), sizeof(a)) == 0 &&
                  // NOLINTNEXTLINE(cppcoreguidelines-pro-type-reinterpret-cast): the socket API's own cast
                  ::getsockname(fd, reinterpret_cast<sockaddr*>(&a), &len) == 0;
  ::close(fd);
  return ok ? ntohs(a.sin_port) : 0;
}

// The numbers in text, separated by blanks or commas.
std::vector<double> numbers(std::string text) {
  std::replace(text.begin(), text.end(), ',', ' ');
  std::istringstream in(text);
  std::vector<double> out;
  for (double x = 0; in >> x;) {
    out.push_back(x);
  }
  return out;
}

// A member of the "link_errors" object of a status line or the statistics file.
std::optional<std::string> link_error(const std::string& json, const char* key) {
  return json_field(json_field(json, "link_errors").value_or("{}"), key);
}

// The flat records of the "log" array of a `fault` response (their text holds no braces).
std::vector<std::string> log_records(const std::string& fault) {
  std::vector<std::string> out;
  for (std::size_t at = fault.find(R"("log":[{)"); at != std::string::npos;) {
    const std::size_t begin = fault.find('{', at);
    const std::size_t end = fault.find('}', begin);
    if (end == std::string::npos) {
      break;
    }
    out.push_back(fault.substr(begin, end - begin + 1));
    at = fault.compare(end + 1, 2, ",{") == 0 ? end + 1 : std::string::npos;
  }
  return out;
}

// The daemon binary with stdout and stderr in one file, dir/NAME.out.
class Daemon : public mrskin::test::ChildProcess {
 public:
  Daemon(const fs::path& dir, const std::string& name, std::vector<std::string> args)
      : ChildProcess(dir / (name + ".out"), dir / (name + ".out"), with_exe(std::move(args))) {}
  [[nodiscard]] std::string output() const { return out(); }

 private:
  static std::vector<std::string> with_exe(std::vector<std::string> args) {
    args.insert(args.begin(), MRSKIN_BRIDGED_EXE);
    return args;
  }
};

class BridgedDaemon : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string tmpl = (fs::temp_directory_path() / "mrskin-bridged-test-XXXXXX").string();
    ASSERT_NE(::mkdtemp(tmpl.data()), nullptr);
    dir_ = tmpl;
    socket_ = (dir_ / "run" / "bridged.sock").string();
    stats_ = (dir_ / "stats.json").string();
  }
  void TearDown() override { fs::remove_all(dir_); }
  std::string config_text(const std::string& body) const {
    return "device = \"mock://\"\nsource = \"scene://demo\"\nstats_json = \"" + stats_ + "\"\n" + body +
           "\n[control]\nsocket = \"" + socket_ + "\"\n";
  }
  // Runs the daemon on a configuration body and flags until it stops by itself; returns its
  // output after checking its exit code and that the output says `says`.
  std::string expect_exit(const std::string& body, std::vector<std::string> flags, int code, const char* says,
                          std::chrono::seconds within = std::chrono::seconds(30)) const {
    std::vector<std::string> args{"--config", config(body).string(), "--quiet"};
    args.insert(args.end(), flags.begin(), flags.end());
    Daemon d(dir_, "d", std::move(args));
    EXPECT_EQ(d.wait(within), code) << d.output();
    EXPECT_NE(d.output().find(says), std::string::npos) << d.output();
    return d.output();
  }
  fs::path config(const std::string& body) const {
    fs::path p = dir_ / "bridged.toml";
    std::ofstream(p) << config_text(body);
    return p;
  }
  LineClient connect() const {
    LineClient c;
    EXPECT_TRUE(eventually([&] { return c.connect(socket_); })) << "no daemon on " << socket_;
    return c;
  }
  static std::string status(LineClient& c) { return c.request(R"({"cmd":"status"})").value_or(""); }
  // SIGHUP, then the status once it counts one reload more (bounded).
  static std::string reload(Daemon& d, LineClient& c) {
    const std::string before = json_field(status(c), "reloads").value_or("0");
    d.signal(SIGHUP);
    std::string s;
    (void)eventually([&] {
      s = status(c);
      return json_field(s, "reloads").value_or(before) != before;
    });
    return s;
  }
  // Sends estop and waits (bounded) for FAULT and halted; returns the last status.
  static std::string estop(LineClient& c) {
    EXPECT_EQ(json_field(c.request(R"({"cmd":"estop"})").value_or(""), "ok"), "true");
    std::string s;
    EXPECT_TRUE(eventually([&] {
      s = status(c);
      return json_field(s, "halted") == "true" && json_field(s, "state") == "FAULT";
    })) << s;
    EXPECT_EQ(json_field(s, "fault"), "emergency stop") << s;
    return s;
  }

  fs::path dir_;
  std::string socket_;
  std::string stats_;
};

// The stream watchdog: a recorded stream of 0.3 s ends; the status shows the bridge holding
// the last estimate, then fading, then the released safe state.
TEST_F(BridgedDaemon, AStreamThatStopsFadesToReleased) {
  const fs::path recording = dir_ / "short.stream";
  {
    std::ofstream out(recording);
    out << "# mrskin-stream 1\n";
    for (int k = 0; k < 300; ++k) {
      const double depth_m = 4e-3 * k / 300.0;
      out << k * 1000000LL << " " << k * 1000000LL << " " << 300.0 * depth_m << " " << depth_m
          << " 0 0 0.003\n";
    }
  }
  const std::string body = "[bridge]\nrealtime = false";
  std::string text = config_text(body);
  text.replace(text.find("scene://demo"), 12, "replay://" + recording.string());
  const fs::path cfg = dir_ / "replay.toml";
  std::ofstream(cfg) << text;
  Daemon d(dir_, "replay", {"--config", cfg.string()});
  LineClient c = connect();
  ASSERT_TRUE(c.connected()) << d.output();
  std::string s;
  EXPECT_TRUE(eventually([&] {
    s = status(c);
    return json_field(s, "stream") == "stale, released";
  })) << s
      << "\n"
      << d.output();
  d.signal(SIGTERM);
  EXPECT_EQ(d.wait(60s), mrskin::tools::kOk) << d.output();
  const std::string stats = slurp(stats_);
  EXPECT_EQ(std::stoull(json_field(stats, "stream_stalls").value_or("0")), 1U) << stats;  // as it went stale
}

TEST_F(BridgedDaemon, ControlSocketEstopFaultEnableThenSigtermFlushesStatistics) {
  Daemon d(dir_, "d", {"--config", config("[bridge]\nrealtime = false").string()});
  LineClient c = connect();
  ASSERT_TRUE(c.connected()) << d.output();

  struct stat st {};
  ASSERT_EQ(::stat(socket_.c_str(), &st), 0);
  EXPECT_TRUE(S_ISSOCK(st.st_mode));
  EXPECT_EQ(st.st_mode & 0777U, 0600U);
  ASSERT_EQ(::stat((dir_ / "run").c_str(), &st), 0);
  EXPECT_EQ(st.st_mode & 0777U, 0700U);

  std::string s;
  ASSERT_TRUE(eventually([&] {
    s = status(c);
    return json_field(s, "state") == "ENABLED" && std::stoull(json_field(s, "ticks").value_or("0")) > 0;
  })) << s;
  EXPECT_EQ(json_field(s, "ok"), "true");
  EXPECT_EQ(json_field(s, "halted"), "false");
  EXPECT_EQ(json_field(s, "device"), "mock://");
  EXPECT_EQ(json_field(s, "rate_hz"), "1000");
  EXPECT_TRUE(json_field(s, "stream").has_value());
  EXPECT_TRUE(json_field(s, "uptime_s").has_value());

  // Malformed and unknown requests get an error line; the connection stays usable.
  std::string r = c.request(R"({"cmd": )").value_or("");
  EXPECT_EQ(json_field(r, "ok"), "false") << r;
  EXPECT_EQ(
      json_field(r, "error"),  // as docs/daemon.md shows it
      "malformed JSON: syntax error while parsing value - unexpected end of input; expected '[', '{', or "
      "a literal (column 9)")
      << r;
  r = c.request(R"({"cmd":"selfdestruct"})").value_or("");
  EXPECT_EQ(json_field(r, "ok"), "false") << r;
  r = c.request("help").value_or("");
  EXPECT_EQ(json_field(r, "ok"), "true") << r;

  // Before any fault: the current state and an empty log.
  r = c.request(R"({"cmd":"fault"})").value_or("");
  EXPECT_EQ(json_field(r, "faults"), "0") << r;
  EXPECT_NE(r.find(R"("log":[])"), std::string::npos) << r;

  s = estop(c);
  EXPECT_EQ(json_field(s, "operator"), "estop") << s;

  r = c.request(R"({"cmd":"fault"})").value_or("");
  EXPECT_EQ(json_field(r, "ok"), "true") << r;
  EXPECT_EQ(json_field(r, "last_fault"), "emergency stop") << r;
  EXPECT_NE(r.find(R"("log":[{)"), std::string::npos) << r;
  EXPECT_NE(r.find("state request"), std::string::npos) << r;  // the e-stop request is in the log

  r = c.request(R"({"cmd":"enable"})").value_or("");
  EXPECT_EQ(json_field(r, "ok"), "true") << r;
  ASSERT_TRUE(eventually([&] {
    s = status(c);
    return json_field(s, "halted") == "false" && json_field(s, "state") == "ENABLED";
  })) << s;

  // Telemetry: lines until stop.
  ASSERT_TRUE(c.send_line(R"({"cmd":"telemetry","period_ms":20})"));
  r = c.read_line(5s).value_or("");
  EXPECT_EQ(json_field(r, "cmd"), "telemetry") << r;
  int events = 0;
  for (int i = 0; i < 3; ++i) {
    r = c.read_line(5s).value_or("");
    events += json_field(r, "event") == "telemetry" ? 1 : 0;
  }
  EXPECT_EQ(events, 3);
  ASSERT_TRUE(c.send_line("stop"));
  bool stopped = false;
  for (int i = 0; i < 100 && !stopped; ++i) {
    r = c.read_line(5s).value_or("");
    stopped = json_field(r, "cmd") == "stop";
  }
  EXPECT_TRUE(stopped);

  d.signal(SIGTERM);
  EXPECT_EQ(d.wait(30s), mrskin::tools::kOk) << d.output();
  const std::string stats = slurp(stats_);
  ASSERT_FALSE(stats.empty()) << d.output();
  const std::optional<std::string> ticks = json_field(stats, "ticks");
  ASSERT_TRUE(ticks.has_value()) << stats;
  EXPECT_GT(std::stoull(*ticks), 0U);
  // CPU per thread, by the names the threads give themselves.
  const std::string threads = json_field(stats, "threads").value_or("");
  EXPECT_NE(threads.find("\"mrskin-loop\""), std::string::npos) << threads;
  EXPECT_NE(threads.find("\"mrskin-mock\""), std::string::npos) << threads;
  EXPECT_NE(d.output().find("cpu        per thread"), std::string::npos) << d.output();
  EXPECT_FALSE(fs::exists(socket_)) << "the socket is removed at exit";
  EXPECT_NE(d.output().find("summary:"), std::string::npos) << d.output();
}

TEST_F(BridgedDaemon, SighupReloadsOnTheOpenDeviceAndSigintFlushesStatistics) {
  const fs::path cfg = config("rate_hz = 1000\n[bridge]\nrealtime = false\nfeedback_gain_per_s = 40");
  Daemon d(dir_, "d", {"--config", cfg.string()});
  LineClient c = connect();
  ASSERT_TRUE(c.connected()) << d.output();
  std::string s;
  ASSERT_TRUE(eventually([&] {
    s = status(c);
    return std::stoull(json_field(s, "link_sent").value_or("0")) > 200;
  })) << s;
  const std::uint64_t sent_before = std::stoull(json_field(s, "link_sent").value_or("0"));

  // A new rate (a new bridge and loop) and a new device URI (refused: kept, logged).
  std::ofstream(cfg) << "device = \"mock://?seed=9\"\n"
                     << config_text("rate_hz = 500\n[bridge]\nrealtime = false\nfeedback_gain_per_s = 20")
                            .substr(std::string("device = \"mock://\"\n").size());
  s = reload(d, c);
  ASSERT_EQ(json_field(s, "reloads"), "1") << s << d.output();
  EXPECT_EQ(json_field(s, "rate_hz"), "500") << s;
  EXPECT_EQ(json_field(s, "device"), "mock://") << s;
  // The same session: its packet counter carried on (a reopened device would start over).
  EXPECT_GE(std::stoull(json_field(s, "link_sent").value_or("0")), sent_before) << s;
  ASSERT_TRUE(eventually([&] {
    s = status(c);
    return json_field(s, "state") == "ENABLED";
  })) << s;
  EXPECT_EQ(json_field(s, "faults"), "0") << "the swap outlasted the device's heartbeat watchdog: " << s;
  EXPECT_TRUE(eventually([&] { return d.output().find("needs a restart") != std::string::npos; }))
      << d.output();
  // Rate and gain only: the bridge was retuned, not rebuilt (bumpless, reload_test.cpp).
  EXPECT_TRUE(eventually([&] {
    return d.output().find(
               "reload: bridge retuned in place, every state kept (rate 500 Hz, feedback gain 20") !=
           std::string::npos;
  })) << d.output();

  // A broken file on SIGHUP: logged, the daemon runs on.
  std::ofstream(cfg) << "rate_hz = \"fast\"\n";
  d.signal(SIGHUP);
  EXPECT_TRUE(eventually([&] { return d.output().find("not reloaded") != std::string::npos; })) << d.output();
  EXPECT_EQ(json_field(status(c), "rate_hz"), "500");

  // SIGINT stops it like SIGTERM: exit 0, the statistics written at exit.
  ASSERT_FALSE(fs::exists(stats_));
  d.signal(SIGINT);
  EXPECT_EQ(d.wait(30s), mrskin::tools::kOk) << d.output();
  EXPECT_NE(d.output().find("stopped by signal 2 (SIGINT)"), std::string::npos) << d.output();
  const std::string stats = slurp(stats_);
  ASSERT_TRUE(json_field(stats, "ticks").has_value()) << stats << d.output();
  EXPECT_GT(std::stoull(*json_field(stats, "ticks")), 0U) << stats;
  EXPECT_FALSE(fs::exists(socket_)) << "the socket is removed at exit";
}

// Emergency stop: every valve released in the tick that acts on it. In the ring log frozen at the
// e-stop, the packet sent just before the e-stop request commands zero current on every valve;
// then the status (the bridge's peak current, valves_released) and the grid telemetry (the
// currents the session last commanded) show nothing flowing. An operator's e-stop still in force
// at exit is no failure: SIGTERM gives exit 0.
TEST_F(BridgedDaemon, EstopReleasesEveryValveAndIsNoFailureAtExit) {
  Daemon d(dir_, "d", {"--config", config("[bridge]\nrealtime = false").string(), "--quiet"});
  LineClient c = connect();
  ASSERT_TRUE(c.connected()) << d.output();
  std::string s;
  ASSERT_TRUE(eventually([&] {
    s = status(c);
    return std::stod(json_field(s, "peak_current_a").value_or("0")) > 0.0;  // the demo scene presses
  })) << s;
  s = estop(c);
  EXPECT_EQ(json_field(s, "peak_current_a"), "0") << s;
  EXPECT_EQ(json_field(s, "valves_released"), "true") << s;

  const std::string f = c.request(R"({"cmd":"fault"})").value_or("");
  const std::vector<std::string> log = log_records(f);
  const auto estop = std::find_if(log.rbegin(), log.rend(), [](const std::string& r) {
    return json_field(r, "kind") == "state request" && json_field(r, "state") == "e-stop";
  });
  ASSERT_NE(estop, log.rend()) << f;
  const auto before = std::find_if(std::next(estop), log.rend(),
                                   [](const std::string& r) { return json_field(r, "dir") == "tx"; });
  ASSERT_NE(before, log.rend()) << f;
  EXPECT_EQ(json_field(*before, "kind"), "currents") << *before;
  EXPECT_EQ(std::stoull(json_field(*before, "seq").value_or("0")) + 1,
            std::stoull(json_field(*estop, "seq").value_or("0")))
      << *before << "\n"
      << *estop;
  const std::string text = json_field(*before, "text").value_or("");
  const std::size_t amps = text.find("[A]:");
  ASSERT_NE(amps, std::string::npos) << text;
  const std::vector<double> sent = numbers(text.substr(amps + 4));
  EXPECT_EQ(sent.size(), 12U) << text;
  EXPECT_TRUE(std::all_of(sent.begin(), sent.end(), [](double a) { return a == 0.0; })) << text;

  LineClient t = connect();
  ASSERT_TRUE(t.send_line(R"({"cmd":"telemetry","period_ms":20,"grid":true})"));
  std::string line;
  ASSERT_TRUE(eventually([&] {
    line = t.read_line(5s).value_or("");
    return json_field(line, "grid_t_s").value_or("null") != "null";
  })) << line;
  const std::size_t at = line.find(R"("current_a":[)");
  ASSERT_NE(at, std::string::npos) << line;
  const std::vector<double> commanded = numbers(line.substr(at + 13, line.find(']', at) - at - 13));
  EXPECT_EQ(commanded.size(), 12U) << line;
  EXPECT_TRUE(std::all_of(commanded.begin(), commanded.end(), [](double a) { return a == 0.0; })) << line;
  EXPECT_EQ(json_field(line, "valves_released"), "true") << line;

  d.signal(SIGTERM);
  EXPECT_EQ(d.wait(30s), mrskin::tools::kOk) << d.output();
}

// An OpenIGTLink robot connects to the daemon's igtl-listen:// source with the library's
// ClientSocket and sends SENSOR messages (ContactForce, N): they are taken and counted.
TEST_F(BridgedDaemon, OpenIgtlinkSensorMessagesAreAccepted) {
  const std::uint16_t port = free_port(SOCK_STREAM);
  ASSERT_NE(port, 0);
  Daemon d(dir_, "igtl",
           {"--config", config("[bridge]\nrealtime = false").string(), "--source",
            "igtl-listen://127.0.0.1:" + std::to_string(port), "--quiet"});
  LineClient c = connect();
  ASSERT_TRUE(c.connected()) << d.output();
  igtl::ClientSocket::Pointer robot;
  ASSERT_TRUE(eventually([&] {
    robot = igtl::ClientSocket::New();
    return robot->ConnectToServer("127.0.0.1", port) == 0;
  })) << d.output();
  for (std::uint32_t k = 1; k <= 5; ++k) {
    auto m = igtl::SensorMessage::New();
    m->SetDeviceName("ContactForce");
    m->SetLength(1);
    auto unit = igtl::Unit::New();
    unit->Init();
    unit->SetPrefix(igtl::Unit::SI_PREFIX_NONE);
    unit->Append(igtl::Unit::SI_DERIVED_NEWTON, 1);
    m->SetUnit(unit);
    m->SetValue(0U, 0.1 * k);
    auto ts = igtl::TimeStamp::New();
    ts->SetTime(1000U, k * 1'000'000U);  // 1 ms apart
    m->SetTimeStamp(ts);
    m->Pack();
    ASSERT_EQ(robot->Send(m->GetPackPointer(), static_cast<int>(m->GetPackSize())), 1);
  }
  std::string s;
  EXPECT_TRUE(eventually([&] {
    s = status(c);
    return json_field(s, "stream").has_value() && json_field(s, "stream") != "no sample yet";
  })) << s;
  robot->CloseSocket();
  d.signal(SIGTERM);
  ASSERT_EQ(d.wait(60s), mrskin::tools::kOk) << d.output();
  const std::string stats = slurp(stats_);
  ASSERT_TRUE(json_field(stats, "samples_accepted").has_value()) << stats << d.output();
  EXPECT_GT(std::stoull(*json_field(stats, "samples_accepted")), 0U) << stats;
}

// A robot as senders in the field send it, with Debian's OpenIGTLink library and none of our
// encoders: its own device names (set in the configuration and the URI), its tool's pose as
// TDATA, and the force as a 3-component vector in millinewtons, while the mock's finger follows
// the demo scene's press (mock://?finger=demo). The tissue it palpates is the demo's
// (Kelvin-Voigt, 300 N/m, 0.5 N s/m, the same depth profile), so the run is scored like a scene
// run. A few messages the daemon must refuse come first: their reasons are in the statistics
// and in the log.
TEST_F(BridgedDaemon, AFieldRobotOverOpenIgtlinkIsRenderedWithinTheClosedLoopFigures) {
  const std::uint16_t port = free_port(SOCK_STREAM);
  ASSERT_NE(port, 0);
  const std::string stream_table = "[stream]\nforce_device = \"FTSensor\"\n[bridge]\nrealtime = false\n";
  Daemon d(dir_, "field",
           {"--config", config(stream_table).string(), "--device", "mock://?finger=demo", "--source",
            "igtl-listen://127.0.0.1:" + std::to_string(port) + "?pose_device=Tracker&pose_tool=Stylus",
            "--quiet"});
  igtl::ClientSocket::Pointer robot;
  ASSERT_TRUE(eventually([&] {
    robot = igtl::ClientSocket::New();
    return robot->ConnectToServer("127.0.0.1", port) == 0;
  })) << d.output();
  const auto stamped = [](igtl::MessageBase* m, std::uint32_t k) {
    auto ts = igtl::TimeStamp::New();
    ts->SetTime(1000U + k / 1000U, (k % 1000U) * 1'000'000U);
    m->SetTimeStamp(ts);
    m->Pack();
  };
  const auto sensor = [&](const char* device, double fx, double fy, double fz, bool newton, std::uint32_t k) {
    auto m = igtl::SensorMessage::New();
    m->SetDeviceName(device);
    m->SetLength(3);
    auto unit = igtl::Unit::New();
    unit->Init();
    if (newton) {
      unit->SetPrefix(igtl::Unit::SI_PREFIX_MILLI);
      unit->Append(igtl::Unit::SI_DERIVED_NEWTON, 1);
    }
    m->SetUnit(unit);
    m->SetValue(0U, fx);
    m->SetValue(1U, fy);
    m->SetValue(2U, fz);
    stamped(m.GetPointer(), k);
    return robot->Send(m->GetPackPointer(), static_cast<int>(m->GetPackSize())) == 1;
  };
  const auto tool_at = [&](double depth_m, std::uint32_t k) {
    auto m = igtl::TrackingDataMessage::New();
    m->SetDeviceName("Tracker");
    auto tool = igtl::TrackingDataElement::New();
    tool->SetName("Stylus");
    tool->SetPosition(0.0F, 0.0F, static_cast<float>(-1e3 * depth_m));  // mm, z out of the tissue
    m->AddTrackingDataElement(tool);
    stamped(m.GetPointer(), k);
    return robot->Send(m->GetPackPointer(), static_cast<int>(m->GetPackSize())) == 1;
  };
  // Refused: the default device name, a force without a unit. Until a sample comes, the status
  // says why none does.
  LineClient c = connect();
  ASSERT_TRUE(c.connected()) << d.output();
  ASSERT_TRUE(sensor("ContactForce", 0.0, 0.0, 100.0, true, 1));
  std::string s;
  EXPECT_TRUE(eventually([&] {
    s = status(c);
    return json_field(s, "stream_warning").value_or("").find("set force_device=ContactForce") !=
           std::string::npos;
  })) << s;
  EXPECT_EQ(json_field(s, "stream"), "no sample yet") << s;
  ASSERT_TRUE(sensor("FTSensor", 0.0, 0.0, 100.0, false, 1));
  // 11 s at 1 kHz: the demo's depth (0 -> 4 mm in 1 s, hold 1 s, out in 1 s, rest 0.5 s).
  constexpr std::uint32_t kTicks = 11'000;
  auto next = std::chrono::steady_clock::now();
  for (std::uint32_t k = 2; k < kTicks; ++k) {
    const double t = std::fmod(1e-3 * k, 3.5);
    const double depth_m = t < 1.0 ? 4e-3 * t : t < 2.0 ? 4e-3 : t < 3.0 ? 4e-3 * (3.0 - t) : 0.0;
    const double rate_m_per_s = t < 1.0 ? 4e-3 : t >= 2.0 && t < 3.0 ? -4e-3 : 0.0;
    const double force_mN = depth_m > 0.0 ? 1e3 * (300.0 * depth_m + 0.5 * rate_m_per_s) : 0.0;
    // A shear the normal component must leave out; the tissue pushes the tool out along +z.
    ASSERT_TRUE(tool_at(depth_m, k) && sensor("FTSensor", 40.0, -25.0, std::max(force_mN, 0.0), true, k))
        << d.output();
    next += std::chrono::milliseconds(1);
    std::this_thread::sleep_until(next);
  }
  robot->CloseSocket();
  d.signal(SIGTERM);
  ASSERT_EQ(d.wait(60s), mrskin::tools::kOk) << d.output();
  const std::string stats = slurp(stats_);
  const std::string log = d.output();
  const auto number = [&](const char* key) { return std::stod(json_field(stats, key).value_or("nan")); };
  // Every sample reaches the bridge; the scored ones depend on the tick keeping up, which a
  // sanitizer build on a shared machine need not (the figures below are the release build's).
  EXPECT_GE(number("samples_accepted"), 0.9 * (kTicks - 2)) << stats;
  EXPECT_GT(number("force_samples"), 0.0) << stats;
  EXPECT_NE(stats.find(R"("device": 1,)"), std::string::npos) << stats;
  EXPECT_NE(stats.find(R"("unit": 1,)"), std::string::npos) << stats;
  EXPECT_NE(log.find("SENSOR from device 'ContactForce' ignored"), std::string::npos) << log;
  EXPECT_NE(log.find("its unit is not a force"), std::string::npos) << log;
  EXPECT_NE(log.find("a robot connected from 127.0.0.1:"), std::string::npos) << log;
  // What the robot sent: 1.2 N at the deepest hold.
  const std::size_t received = stats.find(R"("slave_force_n")");
  ASSERT_NE(received, std::string::npos) << stats;
  const std::vector<double> max_N = numbers(stats.substr(stats.find(R"("max": )", received) + 7, 12));
  ASSERT_FALSE(max_N.empty()) << stats;
  EXPECT_NEAR(max_N.front(), 1.202, 0.01) << stats;
  std::printf("field robot: %s force samples, rms %s N, p95 %s (true state: %s), ticks %s\n",
              json_field(stats, "force_samples").value_or("?").c_str(),
              json_field(stats, "force_rms_error_n").value_or("?").c_str(),
              json_field(stats, "relative_error_p95").value_or("?").c_str(),
              stats.substr(stats.find(R"("true_state")"), 96).c_str(),
              json_field(stats, "ticks").value_or("?").c_str());
#if defined(NDEBUG) && !defined(MRSKIN_SANITIZED)
  // The closed-loop figures (docs/bridge.md), in a real-time run on this shared machine, when the
  // loop kept its periods (a starved loop's skipped time decides them, not the bridge; the
  // simulated-clock tests hold the figures deterministically: bridge_closed_loop_test).
  if (number("skipped_periods") <= kMaxSkippedFraction * number("ticks")) {
    EXPECT_GE(number("force_samples"), 5000.0) << stats;
    EXPECT_LE(number("force_rms_error_n"), 0.04) << stats;
    EXPECT_LE(number("relative_error_p95"), 0.07) << stats;
  } else {
    std::printf(
        "field robot: the loop skipped %s periods in %s ticks: the real-time figures are not judged\n",
        json_field(stats, "skipped_periods").value_or("?").c_str(),
        json_field(stats, "ticks").value_or("?").c_str());
  }
#endif
}

// Exit 1: a device fault nobody asked for (the mock's bus-off at 3 s) latched at exit; the
// statistics are written all the same. At 1 s it landed inside a slow open under TSan on a loaded
// machine, and the start-up's enable cleared it (the run of 9c0a1b8).
TEST_F(BridgedDaemon, AFaultLatchedAtExitIsExit1) {
  Daemon d(dir_, "d",
           {"--config", config("[bridge]\nrealtime = false").string(), "--device", "mock://?faults=busoff:3",
            "--quiet"});
  LineClient c = connect();
  ASSERT_TRUE(c.connected()) << d.output();
  std::string s;
  ASSERT_TRUE(eventually([&] {
    s = status(c);
    return json_field(s, "state") == "FAULT" && json_field(s, "fault") == "bus off";
  })) << s;
  d.signal(SIGTERM);
  EXPECT_EQ(d.wait(30s), mrskin::tools::kFailure) << d.output();
  EXPECT_NE(d.output().find("in FAULT at exit"), std::string::npos) << d.output();
  // Logged as it happened, under --quiet too (issue 25).
  EXPECT_NE(d.output().find("device FAULT: bus off"), std::string::npos) << d.output();
  const std::string stats = slurp(stats_);
  EXPECT_EQ(std::stoull(json_field(stats, "device_faults").value_or("0")), 1U) << stats;
}

// Link faults are counted by kind in the status and logged at most once a second, under --quiet
// too; a disconnect is logged going and coming back (issue 25). At the real time scale: the
// harness's MRSKIN_TIME_SCALE=10 also stretches the mock's fault clock.
// The disconnect starts at 2 s: one during the opening reads fails the open instead ("stopped
// returning its profile"), which the configuration reads in 14-byte chunks (then the default)
// reached at 0.5 s on a ThreadSanitizer build.
TEST_F(BridgedDaemon, LinkFaultsAreCountedAndLogged) {
  ::setenv("MRSKIN_TIME_SCALE", "1", 1);
  Daemon d(dir_, "d",
           {"--config", config("[bridge]\nrealtime = false").string(), "--device",
            "mock://?faults=drop:0.05,dup:0.01,corrupt:0.01,disconnect:2+0.5", "--quiet"});
  ::unsetenv("MRSKIN_TIME_SCALE");
  LineClient c = connect();
  ASSERT_TRUE(c.connected()) << d.output();
  std::string s;
  EXPECT_TRUE(eventually([&] {
    s = status(c);
    const auto n = [&](const char* key) { return std::stod(link_error(s, key).value_or("0")); };
    return n("sequence_gaps") > 0 && n("duplicates") > 0 && n("crc") > 0 && n("reconnects") > 0;
  })) << s;
  std::this_thread::sleep_for(1500ms);  // a status period: the log catches up
  d.signal(SIGTERM);
  // At time scale 1 a sanitizer build on a loaded machine may also lose the heartbeat (FAULT,
  // exit 1); what this test checks is the log.
  const int code = d.wait(30s);
  EXPECT_TRUE(code == mrskin::tools::kOk || code == mrskin::tools::kFailure) << code << d.output();
  const std::string log = d.output();
  EXPECT_NE(log.find("sequence gaps (telemetry lost or reordered)"), std::string::npos) << log;
  EXPECT_NE(log.find("failed the CRC"), std::string::npos) << log;
  EXPECT_NE(log.find("duplicate packets"), std::string::npos) << log;
  EXPECT_NE(log.find("link: the device disconnected"), std::string::npos) << log;
  EXPECT_NE(log.find("link: the device reconnected"), std::string::npos) << log;
  // And in the statistics file (docs/statistics.md).
  const std::string stats = slurp(stats_);
  const auto n = [&](const char* key) { return std::stoull(link_error(stats, key).value_or("0")); };
  EXPECT_GT(n("sequence_gaps"), 0U) << stats;
  EXPECT_GT(n("duplicates"), 0U) << stats;
  EXPECT_GT(n("undecodable"), 0U) << stats;
  EXPECT_GT(n("reconnects"), 0U) << stats;
  EXPECT_GT(n("disconnects"), 0U) << stats;
}

// A new source on SIGHUP builds a new bridge (not bumpless, and the log says so) on the same
// open device; an operator's e-stop carries over to it.
TEST_F(BridgedDaemon, SighupWithANewSourceBuildsANewBridgeAndKeepsTheEstop) {
  const fs::path cfg = config("[bridge]\nrealtime = false");
  Daemon d(dir_, "d", {"--config", cfg.string()});
  LineClient c = connect();
  ASSERT_TRUE(c.connected()) << d.output();
  std::string s = estop(c);
  std::string text = config_text("[bridge]\nrealtime = false");
  text.replace(text.find("scene://demo"), std::string("scene://demo").size(), "scene://hand");
  std::ofstream(cfg) << text;
  s = reload(d, c);
  ASSERT_EQ(json_field(s, "reloads"), "1") << s << d.output();
  EXPECT_EQ(json_field(s, "source"), "scene://hand") << s;
  EXPECT_EQ(json_field(s, "halted"), "true") << "a reload never re-enables: " << s;
  EXPECT_TRUE(eventually([&] {
    return d.output().find("reload: new bridge on the open device for the new source, starting afresh") !=
           std::string::npos;
  })) << d.output();
  EXPECT_EQ(json_field(c.request(R"({"cmd":"enable"})").value_or(""), "ok"), "true");
  EXPECT_TRUE(eventually([&] {
    s = status(c);
    return json_field(s, "state") == "ENABLED" && json_field(s, "halted") == "false";
  })) << s;
  d.signal(SIGTERM);
  EXPECT_EQ(d.wait(30s), mrskin::tools::kOk) << d.output();
}

// The largest true contact force (the mock's, N) in a telemetry line with the grid; -1 without.
double max_true_force_N(const std::string& line) {
  const std::size_t at = line.find(R"("true_force_n":[)");
  if (at == std::string::npos) {
    return -1.0;
  }
  const std::size_t from = at + 16;
  const std::vector<double> f = numbers(line.substr(from, line.find(']', from) - from));
  return f.empty() ? -1.0 : *std::max_element(f.begin(), f.end());
}

// Every grid line's largest true force over `span` (telemetry every 20 ms; bounded).
std::vector<double> true_forces_N(LineClient& t, std::chrono::milliseconds span) {
  std::vector<double> out;
  for (const auto end = std::chrono::steady_clock::now() + span; std::chrono::steady_clock::now() < end;) {
    const double f = max_true_force_N(t.read_line(1s).value_or(""));
    if (f >= 0.0) {
      out.push_back(f);
    }
  }
  return out;
}

// Reads grid lines until one's largest true force passes `test` (bounded: 10 s).
template <typename Test>
bool first_true_force_N(LineClient& t, Test test) {
  for (const auto end = std::chrono::steady_clock::now() + 10s; std::chrono::steady_clock::now() < end;) {
    const double f = max_true_force_N(t.read_line(1s).value_or(""));
    if (f >= 0.0 && test(f)) {
      return true;
    }
  }
  return false;
}

// The largest true force of each grid line stamped (grid_t_s, the daemon's time since its start)
// in [from_s, to_s); reads until a line reaches to_s (bounded: 10 s).
std::vector<double> true_forces_N(LineClient& t, double from_s, double to_s) {
  std::vector<double> out;
  for (const auto end = std::chrono::steady_clock::now() + 10s; std::chrono::steady_clock::now() < end;) {
    const std::string line = t.read_line(1s).value_or("");
    const std::string at = json_field(line, "grid_t_s").value_or("null");
    const double f = max_true_force_N(line);
    if (at == "null" || f < 0.0) {
      continue;
    }
    const double t_s = std::stod(at);
    if (t_s >= to_s) {
      break;
    }
    if (t_s >= from_s) {
      out.push_back(f);
    }
  }
  return out;
}

// A robot on 127.0.0.1:port streaming lifted samples at about 1 kHz for `count` samples.
std::thread udp_robot(std::uint16_t port, std::uint32_t count) {
  return std::thread([port, count] {
    const int out = ::socket(AF_INET, SOCK_DGRAM, 0);
    sockaddr_in to{};
    to.sin_family = AF_INET;
    to.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    to.sin_port = htons(port);
    for (std::uint32_t k = 0; k < count; ++k) {
      mrskin::bridge::UdpSample s;
      s.sequence = k;
      s.stamp_ns = static_cast<std::int64_t>(k) * 1'000'000;
      s.tip_radius_m = 3e-3;
      const auto bytes = mrskin::bridge::encode_udp_sample(s);
      // NOLINTNEXTLINE(cppcoreguidelines-pro-type-reinterpret-cast): the socket API's own cast
      (void)::sendto(out, bytes.data(), bytes.size(), 0, reinterpret_cast<const sockaddr*>(&to), sizeof(to));
      std::this_thread::sleep_for(1ms);
    }
    ::close(out);
  });
}

// Beside a stream the mock's finger waits at the scene's start (depth 0: on the skin, which the
// reservoir's precharge alone pushes at about 0.19 N once the cell has filled) until the stream's
// first sample, and a reload onto a new stream puts it back there to wait for that stream's first
// sample (docs/daemon.md). Without the reset the finger would carry on its old press.
TEST_F(BridgedDaemon, TheMockFingerWaitsForEachNewStreamsFirstSample) {
  const std::uint16_t first = free_port(SOCK_DGRAM);
  const std::uint16_t second = free_port(SOCK_DGRAM);
  ASSERT_TRUE(first != 0 && second != 0 && first != second);
  auto text = [&](std::uint16_t port) {
    std::string t = config_text("[bridge]\nrealtime = false");
    t.replace(t.find("mock://"), std::string("mock://").size(), "mock://?finger=demo");
    t.replace(t.find("scene://demo"), std::string("scene://demo").size(),
              "udp://127.0.0.1:" + std::to_string(port));
    return t;
  };
  const fs::path cfg = dir_ / "bridged.toml";
  std::ofstream(cfg) << text(first);
  Daemon d(dir_, "d", {"--config", cfg.string()});
  LineClient c = connect();
  ASSERT_TRUE(c.connected()) << d.output();
  LineClient t = connect();
  ASSERT_TRUE(t.send_line(R"({"cmd":"telemetry","period_ms":20,"grid":true})"));
  auto resting = [](const std::vector<double>& f) {
    return f.size() >= 5 && *std::max_element(f.begin(), f.end()) < 0.25 &&
           *std::max_element(f.begin(), f.end()) - *std::min_element(f.begin(), f.end()) < 0.02;
  };
  auto pressed = [](const std::vector<double>& f) {
    return !f.empty() &&
           *std::max_element(f.begin(), f.end()) > 0.45;  // 0 -> 4 mm in the demo's first second
  };
  // The skin settles on the resting finger (the first grid lines read 0; slower under sanitizers).
  ASSERT_TRUE(first_true_force_N(t, [](double force_N) { return force_N > 0.1; })) << d.output();
  std::vector<double> f = true_forces_N(t, 400ms);
  EXPECT_TRUE(resting(f)) << ::testing::PrintToString(f);

  std::thread robot = udp_robot(first, 1300);
  f = true_forces_N(t, 1200ms);
  robot.join();
  EXPECT_TRUE(pressed(f)) << ::testing::PrintToString(f);

  std::ofstream(cfg) << text(second);
  const std::string s = reload(d, c);
  ASSERT_EQ(json_field(s, "reloads"), "1") << s << d.output();
  // Back at depth 0 the cell refills slowly (0 -> 0.08 N over 0.8 s here). A finger that carried
  // on would hold the demo's 4 mm (0.43-0.7 N) through the 1.2 s below. Lines are judged by the
  // daemon's own clock, from 0.3 s after the reload took effect (`uptime_s` of that status): once
  // one rests (< 0.25 N) none presses again, and the last ones rest. The first lines may still
  // carry the old finger's force: the reload lifts the finger before the new loop starts, but the
  // mock's plant, slow under ThreadSanitizer, reported it up to 0.42 s later (0.536 N in a
  // clean-clone .ci/run here).
  const double reloaded_s = std::stod(json_field(s, "uptime_s").value_or("0"));
  f = true_forces_N(t, reloaded_s + 0.3, reloaded_s + 1.3);
  const auto lifted = std::find_if(f.begin(), f.end(), [](double force_N) { return force_N < 0.25; });
  EXPECT_TRUE(f.size() >= 10 && lifted != f.end() && *std::max_element(lifted, f.end()) < 0.25 &&
              *std::max_element(f.end() - 5, f.end()) < 0.25)
      << "the finger did not wait for the new stream: " << ::testing::PrintToString(f);

  robot = udp_robot(second, 1300);
  f = true_forces_N(t, 1200ms);
  robot.join();
  EXPECT_TRUE(pressed(f)) << ::testing::PrintToString(f);
  d.signal(SIGTERM);
  EXPECT_EQ(d.wait(30s), mrskin::tools::kOk) << d.output();
}

// A stuck sensor: logged as it is found (naming the sensor, its cells and what the bridge does),
// listed in the status, counted in the statistics; rendering goes on (docs/reliability.md).
TEST_F(BridgedDaemon, ASensorFaultIsLoggedShownAndCounted) {
  Daemon d(dir_, "d",
           {"--config", config("[bridge]\nrealtime = false").string(), "--device", "mock://?faults=stuck:3",
            "--quiet"});
  LineClient c = connect();
  ASSERT_TRUE(c.connected()) << d.output();
  std::string s;
  EXPECT_TRUE(eventually([&] {
    s = status(c);
    return s.find(R"("sensor_faults":[{"sensor":3,"fault":"stuck"}])") != std::string::npos;
  })) << s;
  EXPECT_EQ(json_field(s, "state").value_or(""), "ENABLED") << s;
  d.signal(SIGTERM);
  EXPECT_EQ(d.wait(30s), mrskin::tools::kOk) << d.output();
  const std::string log = d.output();
  EXPECT_NE(log.find("sensor 3 (under valve 3, reads fluid cells"), std::string::npos) << log;
  EXPECT_NE(log.find("stuck: the same reading"), std::string::npos) << log;
  EXPECT_NE(log.find("rendering goes on"), std::string::npos) << log;
  const std::string stats = slurp(stats_);
  EXPECT_NE(stats.find(R"("sensor_faults": {"found": 1, "halts": 0})"), std::string::npos) << stats;
}

// --record: the input stream to a file in the replay:// format, which a second run plays back.
TEST_F(BridgedDaemon, RecordsItsInputForReplay) {
  const fs::path file = dir_ / "input.stream";
  const std::string body = "duration_s = 1\n[bridge]\nrealtime = false";
  const std::string out = expect_exit(body, {"--record", file.string()}, mrskin::tools::kOk, "recorded ");
  const std::string text = slurp(file);
  EXPECT_EQ(text.rfind("# mrskin-stream 1", 0), 0U) << text.substr(0, 200);
  EXPECT_GT(std::count(text.begin(), text.end(), '\n'), 100) << out;
  fs::remove(stats_);
  (void)expect_exit(body, {"--source", "replay://" + file.string()}, mrskin::tools::kOk, "summary:");
  const std::string stats = slurp(stats_);
  EXPECT_GT(std::stoull(json_field(stats, "samples_accepted").value_or("0")), 100U) << stats;
}

// Exit 1: the device disconnected (at 0.5 s, for good) for longer than device_lost_s; the daemon
// stops by itself. On an ideal link, whose configuration reads end long before 0.5 s.
TEST_F(BridgedDaemon, ADeviceLostForGoodIsExit1) {
  (void)expect_exit("device_lost_s = 0.5\n[bridge]\nrealtime = false",
                    {"--device", "mock://?bus=none&faults=disconnect:0.5+600"}, mrskin::tools::kFailure,
                    "lost for good", 60s);
  EXPECT_TRUE(fs::exists(stats_));
}

// Exit 1: the statistics file cannot be written (its directory does not exist).
TEST_F(BridgedDaemon, UnwritableStatisticsAreExit1) {
  (void)expect_exit("duration_s = 0.5\n[bridge]\nrealtime = false",
                    {"--stats-json", (dir_ / "missing" / "stats.json").string()}, mrskin::tools::kFailure,
                    "cannot write statistics");
}

// Exit 3: no such device (a serial no unit has); the control socket it bound first is removed.
TEST_F(BridgedDaemon, NoSuchDeviceIsExit3) {
  (void)expect_exit("[bridge]\nrealtime = false", {"--device", "hid://1209:4d52?serial=0BADF00D"},
                    mrskin::tools::kNoDevice, "no MR skin for hid://1209:4d52");
  EXPECT_FALSE(fs::exists(socket_));
}

// A bus that cannot carry the default 1000 Hz (the 5x5 on classic CAN at 800 kbit/s carries 621 Hz
// at most, by the bus budget): without a rate the loop runs at 80 % of that, and says so; a rate
// asked for that does not fit is refused, exit 2, naming the highest rate (issue 20).
TEST_F(BridgedDaemon, WithoutARateTheLoopRunsAtWhatTheBusCarries) {
  const std::string out = expect_exit(
      "duration_s = 0.3\n[bridge]\nrealtime = false", {"--device", "mock://?bus=can&bitrate=800000"},
      mrskin::tools::kOk, "rate: 1000 Hz does not fit can for this unit (it carries 621 Hz at most)");
  EXPECT_NE(out.find("the loop runs at 496 Hz"), std::string::npos) << out;
  EXPECT_NE(out.find("at 496 Hz"), std::string::npos) << out;
  (void)expect_exit("duration_s = 0.5\nrate_hz = 1000\n[bridge]\nrealtime = false",
                    {"--device", "mock://?bus=can&bitrate=800000"}, mrskin::tools::kUsage,
                    "the highest loop rate can carries is 621 Hz");
  (void)expect_exit("duration_s = 0.5\n[bridge]\nrealtime = false",
                    {"--device", "mock://?bus=can&bitrate=800000", "--rate", "400"}, mrskin::tools::kOk,
                    "at 400 Hz");
}

// Exit 4: a unit that reports another protocol major version in its Identity.
TEST_F(BridgedDaemon, AUnitOfAnotherProtocolMajorIsExit4) {
  (void)expect_exit("[bridge]\nrealtime = false", {"--device", "mock://?protocol_major=2"},
                    mrskin::tools::kMismatch, "reports protocol v2.");
  EXPECT_FALSE(fs::exists(socket_));
}

// What the daemon's main does with the handshake's ProtocolMismatch, without a daemon.
TEST(BridgedExitCodes, AProtocolMismatchMapsToExit4) {
  try {
    throw mrskin::ProtocolMismatch("device on hid://1209:4d52 reports protocol v2.0");
  } catch (...) {
    EXPECT_EQ(mrskin::tools::exit_code_for_current_exception(), mrskin::tools::kMismatch);
  }
}

// The stream source's arrival hook wakes the loop: at 20 Hz, samples arriving between deadlines
// run early ticks (counted in the exit summary). No timing is asserted, only that some did.
TEST_F(BridgedDaemon, UdpSamplesWakeTheLoopEarly) {
  const std::uint16_t port = free_port(SOCK_DGRAM);
  ASSERT_NE(port, 0);
  std::string text = config_text("rate_hz = 20\n[bridge]\nrealtime = false");
  text.replace(text.find("scene://demo"), 12, "udp://127.0.0.1:" + std::to_string(port));
  const fs::path cfg = dir_ / "udp.toml";
  std::ofstream(cfg) << text;
  // An ideal link: the samples must find the loop running, not the configuration reads, which
  // take seconds on a loaded ThreadSanitizer build (docs/protocol.md, "Configuration reads beside
  // the telemetry").
  Daemon d(dir_, "udp", {"--config", cfg.string(), "--device", "mock://?bus=none", "--quiet"});
  LineClient c = connect();
  ASSERT_TRUE(c.connected()) << d.output();
  // The control socket answers before the loop's first tick; on a loaded sanitizer build the open
  // can take longer than the 0.7 s of samples below (a CI run ticked once, after all of them).
  std::string ticking;
  ASSERT_TRUE(eventually([&] {
    ticking = status(c);
    return std::stoull(json_field(ticking, "ticks").value_or("0")) > 0;
  })) << ticking;
  const int out = ::socket(AF_INET, SOCK_DGRAM, 0);
  sockaddr_in to{};
  to.sin_family = AF_INET;
  to.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  to.sin_port = htons(port);
  for (std::uint32_t k = 0; k < 100; ++k) {
    mrskin::bridge::UdpSample s;
    s.sequence = k;
    s.stamp_ns = static_cast<std::int64_t>(k) * 7'000'000;
    s.force_N = 0.5;
    s.indentation_m = 1e-3;
    s.tip_radius_m = 3e-3;
    const auto bytes = mrskin::bridge::encode_udp_sample(s);
    // NOLINTNEXTLINE(cppcoreguidelines-pro-type-reinterpret-cast): the socket API's own cast
    (void)::sendto(out, bytes.data(), bytes.size(), 0, reinterpret_cast<const sockaddr*>(&to), sizeof(to));
    std::this_thread::sleep_for(7ms);  // spread over several 50 ms periods
  }
  ::close(out);
  std::string s;
  EXPECT_TRUE(eventually([&] {
    s = status(c);
    return json_field(s, "stream").has_value() && json_field(s, "stream") != "no sample yet";
  })) << s;
  d.signal(SIGTERM);
  ASSERT_EQ(d.wait(60s), mrskin::tools::kOk) << d.output();
  const std::string output = d.output();
  const std::size_t at = output.find("early wakes ");
  ASSERT_NE(at, std::string::npos) << output;
  EXPECT_GT(std::stoull(output.substr(at + 12)), 0U) << output;
}

TEST_F(BridgedDaemon, ASecondDaemonOnTheSameSocketIsBusy) {
  const fs::path cfg = config("[bridge]\nrealtime = false");
  Daemon first(dir_, "first", {"--config", cfg.string()});
  LineClient c = connect();
  ASSERT_TRUE(c.connected()) << first.output();
  Daemon second(dir_, "second", {"--config", cfg.string(), "--stats-json", (dir_ / "second.json").string()});
  EXPECT_EQ(second.wait(30s), mrskin::tools::kBusy) << second.output();
  EXPECT_NE(second.output().find("another mrskin-bridged"), std::string::npos) << second.output();
  EXPECT_EQ(json_field(status(c), "ok"), "true");  // the first runs on
  first.signal(SIGTERM);
  EXPECT_EQ(first.wait(30s), mrskin::tools::kOk) << first.output();
}

// Late data (every packet arrives, 100 ms late) is logged from the heartbeat's round trip.
TEST_F(BridgedDaemon, LateDataIsLogged) {
  Daemon d(dir_, "d",
           {"--config", config("[bridge]\nrealtime = false").string(), "--device", "mock://?faults=delay:0.1",
            "--duration", "2.5", "--quiet"});
  EXPECT_EQ(d.wait(30s), mrskin::tools::kOk) << d.output();
  const std::string log = d.output();
  const std::size_t at = log.find("link: heartbeat round trip up to ");
  ASSERT_NE(at, std::string::npos) << log;
  EXPECT_GE(std::stod(log.substr(at + 33, 8)), 100.0) << log;  // ms: the delay at least
}

// A file or folder the daemon cannot open or make is exit 1, as the exit-code table says, with
// the path and the OS's reason (issue 25).
TEST_F(BridgedDaemon, AFileItCannotOpenIsExit1) {
  const std::string missing = (dir_ / "no-such-dir").string();
  expect_exit("[bridge]\nrealtime = false", {"--source", "replay://" + missing + "/x.stream"},
              mrskin::tools::kFailure, "cannot open");
  expect_exit("[bridge]\nrealtime = false", {"--record", missing + "/rec.stream", "--duration", "0.2"},
              mrskin::tools::kFailure, "cannot create");
  expect_exit("[bridge]\nrealtime = false", {"--socket", missing + "/a/b.sock", "--duration", "0.2"},
              mrskin::tools::kFailure, "cannot create the control socket directory");
}

// SIGTERM and SIGINT end the start-up too (issue 25): here it waits on a replay FIFO that nobody
// writes, which used to hang with the signals blocked.
TEST_F(BridgedDaemon, ASignalDuringStartUpEndsItAtOnce) {
  for (const int sig : {SIGTERM, SIGINT}) {
    const fs::path fifo = dir_ / "stream.fifo";
    fs::remove(fifo);
    ASSERT_EQ(::mkfifo(fifo.c_str(), 0600), 0);
    Daemon d(dir_, "startup",
             {"--config", config("[bridge]\nrealtime = false").string(), "--source",
              "replay://" + fifo.string(), "--quiet"});
    std::this_thread::sleep_for(300ms);  // into the replay's open
    d.signal(sig);
    EXPECT_EQ(d.wait(10s), mrskin::tools::kOk) << d.output();
    EXPECT_NE(d.output().find("during start-up"), std::string::npos) << d.output();
  }
}

// The control socket as documented (issue 25): a line over 4096 bytes, whole or not, is refused
// and closed; a client silent for idle_timeout_s is closed; a subscribed one is served on.
TEST_F(BridgedDaemon, ALongLineOrAnIdleClientIsClosed) {
  const fs::path cfg = dir_ / "idle.toml";
  std::ofstream(cfg) << config_text("[bridge]\nrealtime = false") << "idle_timeout_s = 1\n";
  Daemon d(dir_, "idle", {"--config", cfg.string(), "--quiet"});
  LineClient c = connect();
  ASSERT_TRUE(c.connected()) << d.output();
  ASSERT_TRUE(c.send_line(std::string(5000, 'x')));
  const std::optional<std::string> reply = c.read_line(5s);
  ASSERT_TRUE(reply.has_value()) << d.output();
  EXPECT_NE(reply->find("request longer than 4096 bytes: closed"), std::string::npos) << *reply;
  EXPECT_FALSE(c.read_line(5s).has_value());  // the connection ended
  LineClient idle = connect();
  LineClient subscribed = connect();
  ASSERT_TRUE(subscribed.send_line(R"({"cmd":"telemetry","period_ms":200})"));
  const std::optional<std::string> said = idle.read_line(10s);
  ASSERT_TRUE(said.has_value()) << d.output();
  EXPECT_NE(said->find("idle for 1 s: closed"), std::string::npos) << *said;
  EXPECT_FALSE(idle.read_line(3s).has_value());
  for (int k = 0; k < 3; ++k) {  // 1.5 s past the idle timeout: still served
    (void)subscribed.read_line(1s);
  }
  EXPECT_TRUE(subscribed.read_line(2s).has_value());
  d.signal(SIGTERM);
  EXPECT_EQ(d.wait(30s), mrskin::tools::kOk) << d.output();
  EXPECT_NE(d.output().find("a line longer than 4096 bytes and was closed"), std::string::npos) << d.output();
  EXPECT_NE(d.output().find("a client idle for 1 s was closed"), std::string::npos) << d.output();
}

TEST_F(BridgedDaemon, AStaleSocketIsReplacedAndDurationEndsTheRun) {
  fs::create_directories(dir_ / "run");
  const fs::path cfg = config("duration_s = 1\n[bridge]\nrealtime = false");
  std::ofstream(socket_).put('x');  // not a socket: refused, named
  Daemon refused(dir_, "refused", {"--config", cfg.string()});
  EXPECT_EQ(refused.wait(30s), mrskin::tools::kUsage) << refused.output();
  EXPECT_NE(refused.output().find("not a socket"), std::string::npos) << refused.output();
  fs::remove(socket_);
  {  // a bound socket nobody listens on: what a killed daemon leaves behind
    const int fd = ::socket(AF_UNIX, SOCK_STREAM, 0);
    sockaddr_un addr{};
    addr.sun_family = AF_UNIX;
    std::copy(socket_.begin(), socket_.end(), static_cast<char*>(addr.sun_path));
    // NOLINTNEXTLINE(cppcoreguidelines-pro-type-reinterpret-cast): the socket API's own cast
    ASSERT_EQ(::bind(fd, reinterpret_cast<const sockaddr*>(&addr), sizeof(addr)), 0);
    ::close(fd);
  }
  Daemon d(dir_, "d", {"--config", cfg.string(), "--quiet"});
  EXPECT_EQ(d.wait(30s), mrskin::tools::kOk) << d.output();
  EXPECT_TRUE(fs::exists(stats_));
}

TEST_F(BridgedDaemon, BadConfigurationIsAUsageError) {
  const fs::path p = dir_ / "bad.toml";
  std::ofstream(p) << "device = \"mock://\"\n[mapping]\nrotation = 90\n";
  Daemon d(dir_, "d", {"--config", p.string()});
  EXPECT_EQ(d.wait(30s), mrskin::tools::kUsage) << d.output();
  EXPECT_NE(d.output().find(p.string() + ":3: mapping.rotation"), std::string::npos) << d.output();
  Daemon flags(dir_, "flags", {"--rate", "0", "--socket", socket_});
  EXPECT_EQ(flags.wait(30s), mrskin::tools::kUsage) << flags.output();
  Daemon both(dir_, "both", {"--scene", "demo", "--source", "scene://demo", "--socket", socket_});
  EXPECT_EQ(both.wait(30s), mrskin::tools::kUsage) << both.output();
  Daemon forever(dir_, "forever", {"--duration", "1e10", "--socket", socket_});
  EXPECT_EQ(forever.wait(30s), mrskin::tools::kUsage) << forever.output();
  Daemon finger(dir_, "finger", {"--device", "mock://?finger=nosuch", "--socket", socket_});
  EXPECT_EQ(finger.wait(30s), mrskin::tools::kUsage) << finger.output();
  EXPECT_NE(finger.output().find("nosuch"), std::string::npos) << finger.output();
  Daemon name(dir_, "name", {"--source", "igtl-listen://127.0.0.1:0?force_device=", "--socket", socket_});
  EXPECT_EQ(name.wait(30s), mrskin::tools::kUsage) << name.output();
  EXPECT_NE(name.output().find("force_device"), std::string::npos) << name.output();
}

}  // namespace
