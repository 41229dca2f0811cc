// mrskin-follower ARM: plays a built-in scene as a CRTK follower arm publishes it over ROS 2's
// DDS mapping: the slave's contact force on ARM/measured_cf (WrenchStamped) and the tool's
// position on ARM/measured_cp (PoseStamped), in the tissue frame (z along the outward normal, the
// surface at 0). Any number of mrskin-bridged --source dds://ARM consoles can render it.
#include <fmt/format.h>
#include <poll.h>
#include <sys/signalfd.h>
#include <unistd.h>

#include <chrono>
#include <csignal>
#include <cstdint>
#include <string>
#include <thread>

#include "exit_codes.hpp"
#include "logging.hpp"
#include "mrskin/bridge/ros2_topics.hpp"
#include "mrskin/bridge/scene.hpp"
#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/version.hpp"

namespace {

using namespace mrskin;

struct Options {
  std::string arm;
  int domain = 0;
  std::string scene = "demo";
  double rate_hz = 1000.0;
  double duration_s = 0.0;
  double wait_s = 0.0;
};

std::int64_t wall_ns() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

// Blocks SIGINT and SIGTERM and returns a signalfd for them: polled between periods.
int stop_signals() {
  sigset_t mask;
  sigemptyset(&mask);
  sigaddset(&mask, SIGINT);
  sigaddset(&mask, SIGTERM);
  (void)pthread_sigmask(SIG_BLOCK, &mask, nullptr);
  return ::signalfd(-1, &mask, SFD_CLOEXEC | SFD_NONBLOCK);
}

bool signalled(int sfd, int timeout_ms) {
  pollfd p{sfd, POLLIN, 0};
  return ::poll(&p, 1, timeout_ms) > 0;
}

int run(const Options& o, int sfd) {
  if (!(o.rate_hz >= 1.0 && o.rate_hz <= 10000.0) || !(o.duration_s >= 0.0 && o.duration_s <= 1e8) ||
      !(o.wait_s >= 0.0 && o.wait_s <= 3600.0)) {
    throw InvalidArgument("--rate must be 1 to 10000 Hz, --duration 0 to 1e8 s, --wait 0 to 3600 s");
  }
  std::unique_ptr<bridge::Scene> scene = bridge::make_scene(o.scene);
  bridge::FollowerPublisher pub(o.arm, o.domain);
  fmt::print("mrskin-follower: scene {} as {} and {} on DDS domain {} at {} Hz\n", scene->name(),
             pub.wrench_topic(), pub.pose_topic(), o.domain, o.rate_hz);
  std::fflush(stdout);
  using Steady = std::chrono::steady_clock;
  const Steady::time_point waited =
      Steady::now() + std::chrono::duration_cast<Steady::duration>(std::chrono::duration<double>(o.wait_s));
  while (pub.subscribers() == 0 && Steady::now() < waited) {
    if (signalled(sfd, 10)) {
      return tools::kOk;
    }
  }
  MonotonicClock clock;
  const TimePoint t0 = clock.now();
  scene->set_start(t0);
  const auto period = std::chrono::duration_cast<Duration>(std::chrono::duration<double>(1.0 / o.rate_hz));
  const TimePoint end = t0 + from_seconds(o.duration_s);
  std::uint64_t sent = 0;
  std::uint64_t failed = 0;
  int last_subscribers = -1;
  for (TimePoint next = t0; o.duration_s == 0.0 || next < end; next += period) {
    if (signalled(sfd, 0)) {
      break;
    }
    std::this_thread::sleep_for(next - clock.now());
    bridge::SlaveSample s;
    if (!scene->latest(clock.now(), s) || !s.valid) {
      continue;
    }
    bridge::FollowerSample f;
    f.stamp_ns = wall_ns();
    f.force_N = {0.0, 0.0, s.force_N};  // the tissue pushes the tool out along its normal
    f.position_m = {s.contact_x_m, s.contact_y_m, -s.indentation_m};
    (pub.publish(f) ? sent : failed) += 1;
    if (const int n = pub.subscribers(); n != last_subscribers) {
      fmt::print("mrskin-follower: {} console(s) subscribed\n", n);
      std::fflush(stdout);
      last_subscribers = n;
    }
  }
  fmt::print("mrskin-follower: published {} samples ({} failed writes)\n", sent, failed);
  return failed == 0 ? tools::kOk : tools::kFailure;
}

}  // namespace

namespace {

int guarded_main(int argc, char** argv) {
  mrskin::tools::CliApp cli{
      "Publishes a built-in scene as a CRTK follower arm over DDS (ROS 2 topics ARM/measured_cf and "
      "ARM/measured_cp), for mrskin-bridged --source dds://ARM. DDS is configured by CYCLONEDDS_URI."};
  mrskin::tools::CliCommand app = cli.root();
  app.version_flag("--version", std::string(mrskin::library_version()));
  std::string log_level;
  mrskin::tools::add_log_level_option(app, log_level);
  Options o;
  app.option("arm", o.arm, "the arm's ROS 2 namespace, e.g. PSM1").required();
  app.option("--domain", o.domain, "DDS domain id (0 to 232, default 0)");
  app.option("--scene", o.scene, "built-in scene (default demo)");
  app.option("--rate", o.rate_hz, "samples per second (default 1000)");
  app.option("--duration", o.duration_s, "seconds to publish; 0 (default) until SIGINT/SIGTERM");
  app.option("--wait", o.wait_s, "wait this long for a first subscriber before starting (default 0 s)");
  if (const mrskin::tools::CliParse parsed = cli.parse(argc, argv); !parsed.run) {
    return parsed.exit_code == 0 ? mrskin::tools::kOk : mrskin::tools::kUsage;
  }
  mrskin::tools::set_log_level(log_level);
  return run(o, stop_signals());
}

}  // namespace

int main(int argc, char** argv) {
  mrskin::tools::init_logging("mrskin-follower");
  try {
    return guarded_main(argc, argv);
  } catch (...) {
    return mrskin::tools::exit_code_for_current_exception();
  }
}
