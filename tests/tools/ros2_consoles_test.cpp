// Two consoles on one follower over ROS 2's DDS mapping (issue 23's done-when): two mrskin-bridged
// daemons, each on its own mock unit with a pressing finger, read the same CRTK follower published
// by a peer that is not built on Cyclone (Fast DDS, as a ROS 2 node on rmw_fastrtps publishes), and
// publish their skins, which the same peer decodes. Loopback only: the daemons get CYCLONEDDS_URI
// pointing at tests/support/cyclonedds-loopback.xml; the peer pins itself to 127.0.0.1. Bounded:
// the follower publishes 11 s, every wait has a limit.
#include <gtest/gtest.h>
#include <unistd.h>

#include <array>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "child_process.hpp"
#include "exit_codes.hpp"
#include "json_reply.hpp"
#include "line_client.hpp"

namespace {

namespace fs = std::filesystem;
using mrskin::ctl::json_field;
using mrskin::ctl::LineClient;
using mrskin::test::ChildProcess;
using mrskin::test::eventually;
using mrskin::test::kMaxSkippedFraction;
using mrskin::test::slurp;
using namespace std::chrono_literals;

constexpr int kDomain = 151;  // away from 0, where other DDS programs on a shared machine live
// Names unique to this process: another run on the machine (same loopback) must not cross-talk.
const std::string kSuffix = std::string("_").append(std::to_string(::getpid()));
const std::string kArm = "psm_it" + kSuffix;

class Ros2Consoles : public ::testing::Test {
 protected:
  void SetUp() override {
    (void)::setenv("CYCLONEDDS_URI", MRSKIN_CYCLONEDDS_LOOPBACK_URI, 1);
    std::string tmpl = (fs::temp_directory_path() / "mrskin-ros2-test-XXXXXX").string();
    ASSERT_NE(::mkdtemp(tmpl.data()), nullptr);
    dir_ = tmpl;
  }
  void TearDown() override { fs::remove_all(dir_); }

  // A console: its own mock unit whose finger plays the demo, the follower over dds://, its skin
  // published under /NAME.
  std::unique_ptr<ChildProcess> console(const std::string& name) const {
    const fs::path cfg = dir_ / (name + ".toml");
    std::ofstream(cfg) << "device = \"mock://?finger=demo\"\n"
                       << "source = \"dds://" << kArm << "?domain=" << kDomain << "\"\n"
                       << "stats_json = \"" << (dir_ / (name + ".json")).string() << "\"\n"
                       << "[bridge]\nrealtime = false\n"
                       << "[topics]\nnamespace = \"/" << name << "\"\ndomain = " << kDomain << "\n"
                       << "[control]\nsocket = \"" << (dir_ / (name + ".sock")).string() << "\"\n";
    return std::make_unique<ChildProcess>(
        dir_ / (name + ".out"), dir_ / (name + ".out"),
        std::vector<std::string>{MRSKIN_BRIDGED_EXE, "--config", cfg.string(), "--quiet"});
  }
  std::unique_ptr<ChildProcess> peer(const std::string& name, std::vector<std::string> args) const {
    args.insert(args.begin(), MRSKIN_FASTDDS_PEER);
    return std::make_unique<ChildProcess>(dir_ / (name + ".out"), dir_ / (name + ".out"), std::move(args));
  }
  LineClient control(const std::string& name) const {
    LineClient c;
    EXPECT_TRUE(eventually([&] { return c.connect((dir_ / (name + ".sock")).string()); }));
    return c;
  }
  std::string out(const std::string& name) const { return slurp(dir_ / (name + ".out")); }

  fs::path dir_;
};

TEST_F(Ros2Consoles, TwoConsolesRenderOneFollowerPublishedByAFastDdsPeer) {
  const std::array<std::string, 2> names{"console_a" + kSuffix, "console_b" + kSuffix};
  std::array<std::unique_ptr<ChildProcess>, 2> consoles{console(names[0]), console(names[1])};
  std::array<LineClient, 2> controls{control(names[0]), control(names[1])};
  ASSERT_TRUE(controls[0].connected() && controls[1].connected()) << out(names[0]) << out(names[1]);
  // The peer reads both skins while the follower runs.
  std::array<std::unique_ptr<ChildProcess>, 2> skins{
      peer("skin_a", {"subscribe", "--ns", names[0], "--domain", std::to_string(kDomain), "--duration", "30",
                      "--min", "200"}),
      peer("skin_b", {"subscribe", "--ns", names[1], "--domain", std::to_string(kDomain), "--duration", "30",
                      "--min", "200"})};
  // The follower starts a second after the consoles, as a robot that comes up late would: each
  // console's finger must wait for its first sample (before 2026-11-29 it did not, 0.14 N).
  std::this_thread::sleep_for(1s);
  std::unique_ptr<ChildProcess> follower =
      peer("follower", {"publish", "--arm", kArm, "--domain", std::to_string(kDomain), "--rate", "1000",
                        "--duration", "11", "--wait-match", "20", "--subscribers", "2"});
  EXPECT_EQ(follower->wait(60s), 0) << out("follower");
  // The figure while the follower streamed: the live RMS error as it stops. After it, the finger
  // presses on while the skin releases (its passive floor against a zero target), which the
  // statistics at exit score too.
  std::array<double, 2> streamed_rms_N{};
  for (std::size_t i = 0; i < 2; ++i) {
    const std::string s = controls.at(i).request(R"({"cmd":"status"})").value_or("");
    streamed_rms_N.at(i) = std::stod(json_field(s, "rms_error_n").value_or("nan"));
  }
  std::printf("follower: %s", out("follower").c_str());
  EXPECT_NE(out("follower").find("matched 2 subscriber(s)"), std::string::npos) << out("follower");
  // The follower has gone: both consoles fade to released.
  for (std::size_t i = 0; i < 2; ++i) {
    std::string s;
    EXPECT_TRUE(eventually(
        [&] {
          s = controls.at(i).request(R"({"cmd":"status"})").value_or("");
          return json_field(s, "stream") == "stale, released";
        },
        5s))
        << s;
  }
  for (std::size_t i = 0; i < 2; ++i) {
    EXPECT_EQ(skins.at(i)->wait(40s), 0) << out(i == 0 ? "skin_a" : "skin_b");
  }
  for (std::size_t i = 0; i < 2; ++i) {
    consoles.at(i)->signal(SIGTERM);
    ASSERT_EQ(consoles.at(i)->wait(60s), mrskin::tools::kOk) << out(names.at(i));
    const std::string log = out(names.at(i));
    EXPECT_NE(log.find("dds: a publisher matched on rt/" + kArm + "/measured_cf"), std::string::npos) << log;
    EXPECT_NE(log.find("fading to released"), std::string::npos) << log;
    const std::string stats = slurp(dir_ / (names.at(i) + ".json"));
    const auto number = [&](const char* key) { return std::stod(json_field(stats, key).value_or("nan")); };
    std::printf(
        "%s: rms %.4f N while streamed; at exit %s force samples, rms %s N, p95 %s (true state: %s), "
        "samples accepted %s\n",
        names.at(i).c_str(), streamed_rms_N.at(i), json_field(stats, "force_samples").value_or("?").c_str(),
        json_field(stats, "force_rms_error_n").value_or("?").c_str(),
        json_field(stats, "relative_error_p95").value_or("?").c_str(),
        stats.substr(stats.find(R"("true_state")"), 96).c_str(),
        json_field(stats, "samples_accepted").value_or("?").c_str());
    EXPECT_GE(number("samples_accepted"), 5000.0) << stats;  // of 11,000: best effort on loopback
    EXPECT_GT(number("force_samples"), 0.0) << stats;
#if defined(NDEBUG) && !defined(MRSKIN_SANITIZED)
    // Each console's finger plays the demo from the follower's first sample on (docs/daemon.md):
    // discovery matches the follower after 0.07 s on most runs here and after about 1.05 s on some,
    // and with the finger started at the console's start a second late was 0.135-0.157 N while
    // streamed against 0.011-0.014 N in step (2026-11-29).
    // The closed-loop figures (docs/bridge.md), as for the OpenIGTLink field robot, when the loop
    // kept its periods: on a machine that starves it (a CI run of 3,734 skipped periods in 8,505
    // ticks scored p95 0.14) the skipped time, not the bridge, decides them. The simulated-clock
    // tests hold the figures deterministically (bridge_closed_loop_test).
    if (number("skipped_periods") <= kMaxSkippedFraction * number("ticks")) {
      EXPECT_GE(number("force_samples"), 5000.0) << stats;
      EXPECT_LE(streamed_rms_N.at(i), 0.04) << stats;
      EXPECT_LE(number("relative_error_p95"), 0.07) << stats;
    } else {
      std::printf("%s: the loop skipped %s periods in %s ticks: the real-time figures are not judged\n",
                  names.at(i).c_str(), json_field(stats, "skipped_periods").value_or("?").c_str(),
                  json_field(stats, "ticks").value_or("?").c_str());
    }
#endif
  }
  // What the peer decoded of each skin.
  for (const char* skin : {"skin_a", "skin_b"}) {
    const std::string text = out(skin);
    EXPECT_NE(text.find("operating_state count="), std::string::npos) << text;
    EXPECT_NE(text.find("last=ENABLED"), std::string::npos) << text;
    EXPECT_NE(text.find("dims=[row:5,col:5]"), std::string::npos) << text;
  }
}

}  // namespace
