// mrskin-bridged: runs the bridge in real time on a device, fed by a robot stream or a scene,
// with a control socket, SIGHUP reload and exit codes that say why it stopped (docs/daemon.md).
#include <fmt/format.h>
#include <poll.h>
#include <pthread.h>
#include <spdlog/spdlog.h>
#include <sys/eventfd.h>
#include <sys/signalfd.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <csignal>
#include <cstdio>
#include <fstream>
#include <memory>
#include <optional>
#include <string_view>
#include <thread>

#include "config.hpp"
#include "control_server.hpp"
#include "daemon.hpp"
#include "exit_codes.hpp"
#include "logging.hpp"
#include "mrskin/bridge/scene.hpp"
#include "mrskin/driver/version.hpp"
#include "mrskin/sim/open_mock.hpp"
#include "systemd_notify.hpp"
#include "verdict.hpp"

namespace {

using namespace mrskin::tools;  // exit codes
using mrskin::bridged::Settings;

constexpr const char* kExitCodes =
    "Exit codes:\n"
    "  0  the duration was reached, or SIGINT/SIGTERM stopped it (statistics written; during\n"
    "     start-up it stops at once, with nothing to write)\n"
    "  1  the device was lost for good (disconnected longer than device_lost_s, or another unit\n"
    "     answered), a device fault other than an operator's e-stop was latched at exit, or a file\n"
    "     or folder it names could not be opened or made (a replay file, --record, the control\n"
    "     socket's folder, the statistics file)\n"
    "  2  bad flag, configuration file, key or value (the message names FILE:LINE and the key)\n"
    "  3  device not found, or permission denied\n"
    "  4  the device speaks another protocol version\n"
    "  5  the device is owned by another process, or another daemon answers on the control socket\n";

// SIGINT and SIGTERM while the daemon starts (a device or a profile that takes long to open, a
// replay from a FIFO nobody writes): the main loop does not read signals yet, so a thread of its
// own does, and ends the process at once with exit 0. It reads a signalfd of its own for these two
// only; a SIGHUP stays pending for the main loop.
class StartupSignalGuard {
 public:
  StartupSignalGuard() : sfd_(stop_signals_fd()), stop_(::eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK)) {
    if (sfd_ >= 0 && stop_ >= 0) {
      thread_ = std::thread([this] {
        (void)::pthread_setname_np(::pthread_self(), "mrskin-signals");
        watch();
      });
    }
  }
  StartupSignalGuard(const StartupSignalGuard&) = delete;
  StartupSignalGuard& operator=(const StartupSignalGuard&) = delete;
  StartupSignalGuard(StartupSignalGuard&&) = delete;
  StartupSignalGuard& operator=(StartupSignalGuard&&) = delete;
  ~StartupSignalGuard() { done(); }
  // Start-up is over: the main loop reads the signals from here on.
  void done() noexcept {
    if (thread_.joinable()) {
      const std::uint64_t one = 1;
      [[maybe_unused]] const ssize_t n = ::write(stop_, &one, sizeof(one));
      thread_.join();
    }
    for (int* fd : {&sfd_, &stop_}) {
      if (*fd >= 0) {
        ::close(*fd);
        *fd = -1;
      }
    }
  }

 private:
  static int stop_signals_fd() noexcept {
    sigset_t mask;
    sigemptyset(&mask);
    sigaddset(&mask, SIGINT);
    sigaddset(&mask, SIGTERM);
    return ::signalfd(-1, &mask, SFD_CLOEXEC | SFD_NONBLOCK);
  }
  void watch() const noexcept {
    std::array<pollfd, 2> p{pollfd{sfd_, POLLIN, 0}, pollfd{stop_, POLLIN, 0}};
    while (::poll(p.data(), p.size(), -1) >= 0 || errno == EINTR) {
      if ((p[1].revents & POLLIN) != 0) {
        return;
      }
      signalfd_siginfo si{};
      if ((p[0].revents & POLLIN) != 0 && ::read(sfd_, &si, sizeof(si)) == static_cast<ssize_t>(sizeof(si))) {
        // Nothing to flush yet: no statistics, the device not driven (its watchdog releases the
        // valves). The control socket file, if made, is replaced as stale by the next start.
        const char* text = si.ssi_signo == SIGINT
                               ? "mrskin-bridged: stopped by signal 2 (SIGINT) during start-up\n"
                               : "mrskin-bridged: stopped by signal 15 (SIGTERM) during start-up\n";
        std::fputs(text, stderr);
        std::_Exit(kOk);
      }
    }
  }
  int sfd_ = -1;
  int stop_ = -1;
  std::thread thread_;
};

// What the stream carried and what was dropped, by reason.
void print_stream_summary(const mrskin::bridge::BridgeStats& s) {
  std::string reasons;
  for (std::size_t i = 0; i < mrskin::bridge::kDropReasonCount; ++i) {
    if (const std::uint64_t n = s.samples_dropped_by_reason.at(i); n != 0) {
      reasons += fmt::format("{}{} {}", reasons.empty() ? " (" : ", ",
                             mrskin::bridge::drop_reason_name(static_cast<mrskin::bridge::DropReason>(i)), n);
    }
  }
  fmt::print(
      "stream     {} samples accepted, {} dropped{}; contact force received p50 {:.3f} N, p99 {:.3f} N, "
      "max {:.3f} N\n",
      s.samples_accepted, s.samples_dropped, reasons.empty() ? "" : reasons + ")",
      s.slave_force.percentile_N(0.5), s.slave_force.percentile_N(0.99), s.slave_force.max_N());
}

void print_summary(const mrskin::bridge::BridgeStats& s, double rate_hz) {
  fmt::print(
      "summary: {} ticks at {:.0f} Hz, {} overruns, {} skipped periods, tick p50 {:.2f} us p99 {:.2f} us "
      "p99.9 {:.2f} us max {:.2f} us; rendered-force error rms {:.4f} N max {:.4f} N over {} samples "
      "(against the unclamped law {:.4f} N); clamped {:.1f} %\n",
      s.ticks, rate_hz, s.overruns, s.skipped_periods, s.tick_time.percentile_ns(0.5) / 1e3,
      s.tick_time.percentile_ns(0.99) / 1e3, s.tick_time.percentile_ns(0.999) / 1e3,
      static_cast<double>(s.tick_time.max_ns()) / 1e3, s.force_rms_error_N(), s.force_max_abs_error_N,
      s.force_samples, s.unclamped_rms_error_N(), 100.0 * s.clamped_fraction());
}

// The status line and the log share the terminal: a log line first clears the in-place status.
class Console {
 public:
  explicit Console(bool tty) : tty_(tty) {}
  void status(const std::string& line) {
    if (tty_) {
      fmt::print("\r{}\x1b[K", line);
      shown_ = true;
    } else {
      fmt::print("{}\n", line);
    }
    std::fflush(stdout);
  }
  void clear() {
    if (shown_) {
      fmt::print("\r\x1b[K");
      std::fflush(stdout);
      shown_ = false;
    }
  }
  void end_status() {
    if (shown_) {
      fmt::print("\n");
      shown_ = false;
    }
  }
  [[nodiscard]] bool tty() const noexcept { return tty_; }

 private:
  bool tty_;
  bool shown_ = false;
};

Settings load(const std::string& config_path, const mrskin::bridged::Overrides& overrides) {
  Settings s = config_path.empty() ? Settings{} : mrskin::bridged::load_settings(config_path);
  mrskin::bridged::apply(overrides, s);
  mrskin::bridged::validate(s, config_path.empty() ? "command line" : config_path + " with the flags");
  if (s.socket.empty()) {
    s.socket = mrskin::bridged::default_socket_path();
  }
  return s;
}

void log_health_events(const std::vector<mrskin::bridged::Daemon::HealthEvent>& events) {
  for (const mrskin::bridged::Daemon::HealthEvent& e : events) {
    if (e.warning) {
      spdlog::warn("{}", e.text);
    } else {
      spdlog::info("{}", e.text);
    }
  }
}

// Reads the signals that arrived on sfd: SIGHUP reloads the configuration; the first other
// signal is returned (0: none), to stop on.
int read_signals(int sfd, Console& console, mrskin::bridged::Daemon& daemon, const std::string& config_path,
                 const mrskin::bridged::Overrides& overrides,
                 const mrskin::bridged::SystemdNotifier& notifier) {
  pollfd p{sfd, POLLIN, 0};
  (void)::poll(&p, 1, 1);  // 1 ms: the simulated finger follows the script at 1 kHz
  int stop_signal = 0;
  signalfd_siginfo si{};
  while ((p.revents & POLLIN) != 0 && ::read(sfd, &si, sizeof(si)) == static_cast<ssize_t>(sizeof(si))) {
    if (si.ssi_signo != SIGHUP) {
      stop_signal = static_cast<int>(si.ssi_signo);
      continue;
    }
    console.clear();
    if (config_path.empty()) {
      spdlog::info("SIGHUP: no --config file to reload");
      continue;
    }
    (void)notifier.notify("RELOADING=1");
    try {
      Settings next = load(config_path, overrides);
      for (const std::string& line : daemon.reload(std::move(next))) {
        spdlog::info("{}", line);
      }
      mrskin::tools::set_log_level(daemon.settings().log_level);
    } catch (const std::exception& e) {
      spdlog::error("SIGHUP: configuration not reloaded, running on as before: {}", e.what());
    }
    (void)notifier.notify("READY=1");
    p.revents = 0;  // one signal read per wake is enough; the next poll returns at once if more
  }
  return stop_signal;
}

// Once a status period: the events of the link, the stream and the control socket, the device's
// loss and the status line. True when the device is lost for good.
bool status_period(Console& console, mrskin::bridged::Daemon& daemon,
                   mrskin::bridged::ControlServer& server) {
  if (std::vector<mrskin::bridged::Daemon::HealthEvent> health = daemon.take_health_events();
      !health.empty()) {
    console.clear();  // link errors at most once a period, transitions as they happen
    log_health_events(health);
  }
  if (std::vector<std::string> events = server.take_events(); !events.empty()) {
    console.clear();
    for (const std::string& e : events) {
      spdlog::info("{}", e);
    }
  }
  daemon.sample_threads();  // a thread that ends keeps its last reading
  if (daemon.device_lost(daemon.settings().device_lost_s)) {
    console.clear();
    spdlog::error("device {} lost for good (down for more than {} s, or another unit answered)",
                  daemon.settings().device, daemon.settings().device_lost_s);
    return true;
  }
  if (!daemon.settings().quiet) {
    console.status(daemon.status_line());
  }
  return false;
}

// The lines printed at exit after the statistics: bus, scheduler, recording, topics, reloads.
void print_run_report(const mrskin::bridged::Daemon& daemon, const mrskin::bridge::BridgeStats& stats) {
  using namespace mrskin;
  if (std::string_view(stats.bus.kind) != "none") {
    const auto& h2d = stats.bus.host_to_device;
    const auto& d2h = stats.bus.device_to_host;
    // CAN is one bus both directions share: its load is their sum; USB's directions are apart.
    const std::string_view kind = stats.bus.kind;
    const bool shared = kind == "can" || kind == "canfd";
    fmt::print(
        "bus load   {:.1f} % of the modelled {}{} bus since the loop started (host to device {:.1f} %, "
        "device "
        "to host {:.1f} %); dropped {} and {}, longest wait {:.1f} and {:.1f} ms\n",
        100.0 * (shared ? h2d.load + d2h.load : stats.bus_load), shared ? "shared " : "", kind,
        100.0 * h2d.load, 100.0 * d2h.load, h2d.dropped, d2h.dropped, 1e3 * h2d.max_wait_s,
        1e3 * d2h.max_wait_s);
  } else {
    fmt::print(
        "bus load   {:.2f} reports a 1 ms frame, counted (host to device {:.2f}, device to host {:.2f}; "
        "full-speed USB-HID carries 1)\n",
        stats.bus_load, daemon.reports_per_frame().host_to_device, daemon.reports_per_frame().device_to_host);
  }
  if (const bridge::LoopStats* ls = daemon.loop_stats(); ls != nullptr) {
    fmt::print(
        "scheduler  {} priority {}, {}, memory {}; wake latency p50 {:.1f} us, p99 {:.1f} us, p99.9 {:.1f} "
        "us; "
        "early wakes {} (a stream sample woke the loop before its deadline), {} refused (too soon, or ahead "
        "of the rate)\n",
        ls->scheduler.policy_name(), ls->scheduler.priority,
        ls->scheduler.cpu >= 0 ? fmt::format("pinned to CPU {}", ls->scheduler.cpu)
                               : std::string("not pinned"),
        ls->scheduler.memory_locked ? "locked" : "not locked", ls->wake_latency.percentile_ns(0.5) / 1e3,
        ls->wake_latency.percentile_ns(0.99) / 1e3, ls->wake_latency.percentile_ns(0.999) / 1e3,
        ls->early_wakes, ls->refused_wakes);
  }
  if (const double skipped_s = daemon.mock_skipped_s(); skipped_s > 0.0) {
    // The simulated unit, not the bridge: its plant could not keep real time on this machine.
    fmt::print(
        "mock       the simulated unit's plant fell behind real time and skipped {:.2f} s of its time: the "
        "figures above are of a unit slower than real (its plant step: mock://...?physics_dt=, "
        "docs/api.md){}\n",
        skipped_s,
        daemon.mock_host_while_lagging() > 0
            ? fmt::format("; {} host packets reached it while it lagged, outside the bus's figures",
                          daemon.mock_host_while_lagging())
            : std::string());
  }
  if (!stats.threads.empty()) {
    std::string line;
    for (const bridge::BridgeStats::ThreadCpu& t : stats.threads) {
      line += fmt::format("{}{}{} {:.2f} s ({:.0f} %)", line.empty() ? "" : ", ", t.name,
                          t.count > 1 ? fmt::format(" x{}", t.count) : std::string(), t.cpu_s,
                          stats.threads_wall_s > 0.0 ? 100.0 * t.cpu_s / stats.threads_wall_s : 0.0);
    }
    fmt::print("cpu        per thread over {:.1f} s since the loop started: {}\n", stats.threads_wall_s,
               line);
  }
  if (const bridge::SampleRecorder* rec = daemon.recorder(); rec != nullptr) {
    fmt::print("recorded   {} samples to {} ({} dropped)\n", rec->written(), daemon.settings().record,
               rec->dropped());
  }
  if (const bridge::SkinPublisher* topics = daemon.topics(); topics != nullptr) {
    fmt::print("topics     {} frames published under {} ({} failed), {} subscriber(s) at exit\n",
               topics->published(), topics->ns(), topics->failures(), topics->subscribers());
  }
  if (daemon.reloads() > 0) {
    fmt::print("reloads    {} (the statistics cover the run since the last bridge rebuild)\n",
               daemon.reloads());
  }
}

// The service's side of systemd (docs/daemon.md, "systemd"): READY=1 once the first tick ran,
// then WATCHDOG=1 every half WatchdogSec while the loop is healthy (WatchdogGate), one error line
// when it is withheld and one when it resumes. Main thread; nothing without NOTIFY_SOCKET.
class ServiceState {
 public:
  ServiceState(const mrskin::bridged::SystemdNotifier& notifier, mrskin::TimePoint t0)
      : notifier_(notifier), next_ping_(t0) {}
  void poll(const mrskin::bridged::Daemon& daemon, mrskin::TimePoint now) {
    if (!notifier_.active()) {
      return;
    }
    if (!ready_) {
      if (daemon.live_ticks() == 0) {
        return;
      }
      ready_ = notifier_.notify("READY=1\nSTATUS=rendering");
    }
    const std::optional<std::chrono::microseconds> interval = notifier_.watchdog_interval();
    if (!interval || now < next_ping_) {
      return;
    }
    next_ping_ = now + std::chrono::duration_cast<mrskin::Duration>(*interval);
    if (gate_.healthy(daemon.live_ticks(), daemon.live_overruns())) {
      (void)notifier_.notify("WATCHDOG=1");
      if (withheld_) {
        withheld_ = false;
        spdlog::info("the loop ticks on time again: service watchdog petted");
      }
    } else if (!withheld_) {
      withheld_ = true;
      spdlog::error(
          "the loop is stalled or overrunning: service watchdog not petted (systemd restarts the service "
          "after WatchdogSec)");
    }
  }

 private:
  const mrskin::bridged::SystemdNotifier& notifier_;
  mrskin::bridged::WatchdogGate gate_;
  mrskin::TimePoint next_ping_;
  bool ready_ = false;
  bool withheld_ = false;
};

// After the loop: the last events, the summary, the statistics file; returns the exit code.
int finish(mrskin::bridged::Daemon& daemon, mrskin::bridged::ControlServer& server, Console& console,
           int stop_signal, bool lost) {
  using namespace mrskin;
  server.stop();
  daemon.sample_threads();  // before stop() ends the loop's and the mock's threads
  daemon.stop();
  console.end_status();
  for (const std::string& e : server.take_events()) {  // the last ones, not lost to the exit
    spdlog::info("{}", e);
  }
  log_health_events(daemon.take_health_events());
  if (stop_signal != 0) {
    fmt::print("stopped by signal {} ({})\n", stop_signal, stop_signal == SIGINT ? "SIGINT" : "SIGTERM");
  }
  const Settings& final_cfg = daemon.settings();
  const bridge::BridgeStats stats = daemon.final_stats();
  print_summary(stats, final_cfg.rate_hz);
  print_stream_summary(stats);
  print_run_report(daemon, stats);
  bridged::VerdictLimits limits;
  limits.rms_error_N *= daemon.design_scale().force;  // the figure at the unit's design point
  for (const std::string& line :
       bridged::verdict_lines(stats, daemon.truth_scored(), daemon.tick_period_s(), limits)) {
    fmt::print("{}\n", line);
  }
  int code = kOk;
  if (!final_cfg.stats_json.empty()) {
    std::ofstream out(final_cfg.stats_json);
    out << bridge::to_json(stats, daemon.tick_period_s());
    if (!out) {
      spdlog::error("cannot write statistics to {}: check the directory exists and is writable",
                    final_cfg.stats_json);
      code = kFailure;
    } else {
      fmt::print("statistics written to {}\n", final_cfg.stats_json);
    }
  }
  if (lost) {
    return kFailure;
  }
  if (daemon.unrequested_fault()) {
    spdlog::error("the device is in FAULT at exit: see `fault` on the control socket or the log");
    return kFailure;
  }
  return code;
}

int run(Settings cfg, const std::string& config_path, const mrskin::bridged::Overrides& overrides, int sfd) {
  using namespace mrskin;
  const bridged::SystemdNotifier notifier;
  Console console(::isatty(STDOUT_FILENO) == 1);
  StartupSignalGuard startup;  // SIGINT/SIGTERM end the start-up within a poll
  // The socket first: a second daemon stops here (kBusy) without touching the device.
  bridged::ControlServer server(cfg.socket, cfg.max_clients, cfg.idle_timeout_s);
  MonotonicClock clock;
  bridged::Daemon daemon(cfg, clock);
  const DeviceInfo& info = daemon.info();
  fmt::print(
      "mrskin-bridged {}: {} serial {:08X} firmware {} protocol v{}.{}, {} x {} grid, {} valves, {} "
      "sensors; source {}\n",
      library_version(), cfg.device, info.serial, info.firmware, info.protocol_major, info.protocol_minor,
      info.rows, info.cols, info.valves, info.sensors, cfg.source);
  std::fflush(stdout);
  if (!daemon.rate_note().empty()) {
    spdlog::warn("{}", daemon.rate_note());
  }
  if (!daemon.bus_warning().empty()) {
    spdlog::warn("{}", daemon.bus_warning());
  }
  if (const std::string warning = daemon.start(); !warning.empty()) {
    spdlog::warn("{}", warning);
  }
  // Start-up ends before the control socket answers: a client that sees the daemon and then
  // signals it gets the flushed statistics (the window between them once lost them under TSan).
  startup.done();  // a signal that came meanwhile is still pending for the loop below
  server.start(daemon);
  // The control thread calls into the daemon: it must stop first, on every way out of here.
  const std::unique_ptr<bridged::ControlServer, void (*)(bridged::ControlServer*)> stop_server(
      &server, [](bridged::ControlServer* s) { s->stop(); });
  spdlog::info("control socket {}", server.path());
  const TimePoint t0 = clock.now();
  TimePoint next_status = t0 + std::chrono::milliseconds(500);
  ServiceState service(notifier, t0);
  int stop_signal = 0;
  bool lost = false;
  while (stop_signal == 0 && !lost) {
    const Settings& now_cfg = daemon.settings();
    if (now_cfg.duration_s > 0.0 && clock.now() >= t0 + from_seconds(now_cfg.duration_s)) {
      break;
    }
    stop_signal = read_signals(sfd, console, daemon, config_path, overrides, notifier);
    service.poll(daemon, clock.now());
    daemon.drive_finger();
    if (std::vector<mrskin::bridge::SourceEvent> events = daemon.take_source_events(); !events.empty()) {
      console.clear();  // each reason once, connections as they happen: no spam to rate-limit
      for (const mrskin::bridge::SourceEvent& e : events) {
        if (e.warning) {
          spdlog::warn("source: {}", e.text);
        } else {
          spdlog::info("source: {}", e.text);
        }
      }
    }
    if (clock.now() >= next_status) {
      next_status += std::chrono::milliseconds(console.tty() ? 500 : 1000);
      lost = status_period(console, daemon, server);
    }
  }
  (void)notifier.notify("STOPPING=1");
  return finish(daemon, server, console, stop_signal, lost);
}

int guarded_main(int argc, char** argv) {
  mrskin::sim::register_mock_scheme();  // mock:// (the simulated unit, mrskin::sim)
  // Before any thread exists (the mock device's, the loop's, the control socket's), so that all
  // inherit the mask and the signals arrive only through the signalfd.
  sigset_t mask;
  sigemptyset(&mask);
  sigaddset(&mask, SIGINT);
  sigaddset(&mask, SIGTERM);
  sigaddset(&mask, SIGHUP);
  (void)pthread_sigmask(SIG_BLOCK, &mask, nullptr);
  const int sfd = ::signalfd(-1, &mask, SFD_CLOEXEC | SFD_NONBLOCK);
  if (sfd < 0) {
    std::perror("signalfd");
    return kFailure;
  }

  mrskin::tools::CliApp cli{
      "mrskin-bridged: renders a slave robot's palpation forces on the MR skin in real time"};
  mrskin::tools::CliCommand app = cli.root();
  app.version_flag("--version", std::string(mrskin::library_version()));
  app.footer(kExitCodes);
  std::string config_path;
  mrskin::bridged::Overrides o;
  std::string scenes;
  for (const std::string_view name : mrskin::bridge::scene_names()) {
    scenes += (scenes.empty() ? "" : ", ") + std::string(name);
  }
  bool check = false;
  app.option("--config", config_path, "TOML configuration file; flags override it (docs/daemon.md)")
      .existing_file();
  app.option("--device", o.device, "device URI (default mock://)");
  const mrskin::tools::CliOption source =
      app.option("--source", o.source, "slave stream URI (default scene://demo)");
  app.option("--scene", o.source, "shorthand for --source scene://NAME: " + scenes)
      .excludes(source)
      .transform([](const std::string& name) { return "scene://" + name; });
  app.option("--duration", o.duration_s, "seconds to run; 0 runs until SIGINT/SIGTERM");
  app.option("--rate", o.rate_hz,
             "loop rate, Hz (1 to 20000; default 1000, or 80 % of the highest rate the unit's bus carries)");
  app.option("--cpu", o.cpu,
             "pin the tick thread to this CPU (-1: not pinned, the default; [bridge] cpu; docs/loop.md)");
  app.option("--stats-json", o.stats_json, "write loop statistics as JSON to this file at exit");
  app.option("--record", o.record,
             "record the input stream to this file (replay:// format: play it back with "
             "--source replay://FILE)");
  app.flag("--quiet", o.quiet, "no live status lines");
  mrskin::tools::add_log_level_option(app, o.log_level.emplace());
  app.option("--socket", o.socket,
             "control socket path (default $RUNTIME_DIRECTORY/bridged.sock, "
             "$XDG_RUNTIME_DIR/mrskin/bridged.sock or /tmp/mrskin-UID/bridged.sock)");
  app.option("--topics", o.topics_namespace,
             "publish the skin as ROS 2 topics over DDS under this namespace (e.g. /mrskin; "
             "[topics] in the config; docs/sources.md)");
  app.flag("--check-config", check, "check the configuration, print the socket path and exit");
  if (const mrskin::tools::CliParse parsed = cli.parse(argc, argv); !parsed.run) {
    return parsed.exit_code == 0 ? kOk : kUsage;
  }
  if (o.log_level->empty()) {
    o.log_level.reset();  // not given: the file's, or info
  }
  const Settings cfg = load(config_path, o);
  mrskin::tools::set_log_level(cfg.log_level);
  if (check) {
    mrskin::bridged::check_uris(cfg);
    fmt::print("configuration ok: device {}, source {}, rate {} Hz, socket {}\n", cfg.device, cfg.source,
               cfg.rate_hz, cfg.socket);
    return kOk;
  }
  const int code = run(cfg, config_path, o, sfd);
  ::close(sfd);
  return code;
}

}  // namespace

int main(int argc, char** argv) {
  mrskin::tools::init_logging("mrskin-bridged");
  try {
    return guarded_main(argc, argv);
  } catch (...) {
    return mrskin::tools::exit_code_for_current_exception();
  }
}
