// Shared by set, selftest, calibrate, record and replay: a device opened for a command, ticked
// at 1 kHz, released on exit and on SIGINT, plus the limit checks every command applies.
//
// mock:// runs on a simulated clock by default: the tool steps the in-process unit itself, so
// a run is bit-for-bit repeatable for a seed and takes a fraction of its device time
// (--realtime runs the mock on its own thread against the monotonic clock, like hardware).
// The press fixture (a finger pressing the cells) exists only on mock://: the simulated
// unit's finger input. A real unit has no actuator the host can drive; checks that need a
// press report SKIP there.
#pragma once

#include <fmt/format.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "command_line.hpp"
#include "exit_codes.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/protocol/messages.hpp"
#include "mrskin/protocol/units.hpp"
#include "mrskin/sim/open_mock.hpp"
#include "tunnel_transport.hpp"

namespace mrskin::ctl {

using tools::CliCommand;
using tools::CliOption;

// The options every command on a free device takes.
inline void add_device_options(CliCommand sub, std::string& uri, bool& realtime) {
  sub.option("--device", uri, "device URI").show_default();
  sub.flag("--realtime", realtime, "run a mock:// unit in real time instead of simulated time");
}

// --bridge [SOCKET] on a command that drives the valves itself (set, selftest, calibrate): lease
// the device of a running mrskin-bridged (TunnelTransport; the bridge is disabled and stays
// halted after). lease_socket() is the socket to lease, or nullopt without --bridge.
struct LeaseOption {
  std::string socket;
  CliOption option;  // --bridge; not given: no lease
  [[nodiscard]] std::optional<std::string> lease_socket() const {
    if (!option.given()) {
      return std::nullopt;
    }
    return bridge_socket(socket);
  }
};
inline void add_lease_option(CliCommand sub, LeaseOption& lease) {
  CliOption o = sub.option("--bridge", lease.socket,
                           "run through a running mrskin-bridged on this control socket: it disables the "
                           "bridge and lends its device until the command ends (the bridge stays halted "
                           "after: mrskinctl enable); without a value, its default socket")
                    .value_optional();
  if (const CliOption device = sub.find("--device"); device.exists()) {
    o.excludes(device);
  }
  lease.option = o;
}

// Set by SIGINT/SIGTERM while a Rig is alive; the command loops poll it, stop and release the
// unit. A function-local static, constant-initialised: no guard, safe to touch from the handler.
inline volatile std::sig_atomic_t& interrupted_flag() noexcept {
  static volatile std::sig_atomic_t flag = 0;
  return flag;
}
inline void on_interrupt(int /*signal*/) { interrupted_flag() = 1; }

// "0.01,0.02" -> {0.01, 0.02}; option names the flag in the error.
inline std::vector<double> parse_number_list(std::string_view text, std::string_view option) {
  std::vector<double> out;
  std::size_t start = 0;
  while (start <= text.size()) {
    const std::size_t comma = std::min(text.find(',', start), text.size());
    const std::string item(text.substr(start, comma - start));
    char* end = nullptr;
    const double v = std::strtod(item.c_str(), &end);
    if (item.empty() || end != item.c_str() + item.size()) {
      throw InvalidArgument(
          fmt::format("{}: '{}' is not a number; give comma-separated values, e.g. 0.01,0.02", option, item));
    }
    out.push_back(v);
    start = comma + 1;
  }
  return out;
}

// Refuses a current vector the device would not take: wrong count, NaN/Inf, outside 0..max.
inline void check_currents(std::span<const double> current_a, const DeviceInfo& info, std::string_view what) {
  if (current_a.size() != info.valves) {
    throw InvalidArgument(fmt::format("{}: {} currents given, the device has {} valves; give one per valve",
                                      what, current_a.size(), info.valves));
  }
  for (std::size_t v = 0; v < current_a.size(); ++v) {
    if (!std::isfinite(current_a[v]) || current_a[v] < 0.0 || current_a[v] > info.max_current_A + 1e-12) {
      throw InvalidArgument(fmt::format("{}: valve {} current {} A is outside 0..{} A (the device's maximum)",
                                        what, v, current_a[v], info.max_current_A));
    }
  }
}

// The protocol's domain of a per-cell target (protocol/messages.hpp, units.hpp).
struct TargetLimits {
  static constexpr double stiffness_max_n_per_m =
      protocol::kStiffnessCountMax * protocol::kStiffnessLsb_N_per_m;
  static constexpr double offset_max_m = protocol::kOffsetCountMax * protocol::kOffsetLsb_m;
  static constexpr double ceiling_max_n = protocol::kCeilingCountMax * protocol::kCeilingLsb_N;
  static constexpr double validity_max_s = protocol::kValidityCountMax * protocol::kValidityLsb_s;
};

inline protocol::CellTarget check_target(std::size_t cell, const protocol::CellTargetSi& t,
                                         const DeviceInfo& info, std::string_view what) {
  if (cell >= info.fluid_cells) {
    throw InvalidArgument(fmt::format("{}: cell {} does not exist; the device has fluid cells 0..{}", what,
                                      cell, info.fluid_cells - 1));
  }
  const auto in = [&](double v, double max, std::string_view name, std::string_view unit) {
    if (!std::isfinite(v) || v < 0.0 || v > max + 1e-12) {
      throw InvalidArgument(fmt::format("{}: {} {} {} is outside 0..{} {} (protocol v1 limit)", what, name, v,
                                        unit, max, unit));
    }
  };
  in(t.stiffness_N_per_m, TargetLimits::stiffness_max_n_per_m, "stiffness", "N/m");
  in(t.offset_m, TargetLimits::offset_max_m, "offset", "m");
  in(t.ceiling_N, TargetLimits::ceiling_max_n, "ceiling", "N");
  in(t.validity_s, TargetLimits::validity_max_s, "validity", "s");
  const auto q = protocol::quantize_cell_target(t);
  if (q.error != protocol::Error::ok) {
    throw InvalidArgument(fmt::format("{}: the target cannot be encoded", what));
  }
  return q.counts;
}

// A progress bar on stderr when it is a terminal, "label: step k/n" lines otherwise, nothing
// with --json (stdout stays one document; stderr stays quiet for scripts).
class Progress {
 public:
  Progress(bool enabled, std::string label, int total)
      : enabled_(enabled), tty_(isatty(STDERR_FILENO) == 1), label_(std::move(label)), total_(total) {}
  Progress(const Progress&) = delete;
  Progress& operator=(const Progress&) = delete;
  Progress(Progress&&) = delete;
  Progress& operator=(Progress&&) = delete;
  ~Progress() {
    if (enabled_ && tty_ && shown_) {
      std::fputs("\n", stderr);
    }
  }
  void step(int k) {
    if (!enabled_) {
      return;
    }
    shown_ = true;
    if (tty_) {
      constexpr int kWidth = 30;
      const int filled = total_ > 0 ? k * kWidth / total_ : kWidth;
      fmt::print(stderr, "\r{:<24} [{}{}] {}/{}", label_, std::string(static_cast<std::size_t>(filled), '#'),
                 std::string(static_cast<std::size_t>(kWidth - filled), ' '), k, total_);
      std::fflush(stderr);
    } else {
      fmt::print(stderr, "{}: step {}/{}\n", label_, k, total_);
    }
  }

 private:
  bool enabled_;
  bool tty_;
  bool shown_ = false;
  std::string label_;
  int total_;
};

class Rig {
 public:
  static constexpr Duration kTick = std::chrono::milliseconds(1);

  // lease_socket: the device of a running mrskin-bridged on that socket instead of uri (real time).
  Rig(const std::string& uri, bool realtime, const std::optional<std::string>& lease_socket = std::nullopt)
      : simulated_(!lease_socket && uri.rfind("mock://", 0) == 0 && !realtime) {
    if (lease_socket) {
      dev_.session =
          std::make_unique<DeviceSession>(std::make_unique<TunnelTransport>(*lease_socket), clock());
    } else {
      OpenOptions open;
      open.synchronous_mock = simulated_;
      dev_ = open_device(uri, clock(), open);
      mock_ = sim::mock_of(dev_);
    }
    start_ = clock().now();
    next_ = start_;  // NOLINT(cppcoreguidelines-prefer-member-initializer): after the handshake
    interrupted_flag() = 0;
    struct sigaction sa {};
    sa.sa_handler = &on_interrupt;
    sigemptyset(&sa.sa_mask);
    sigaction(SIGINT, &sa, &old_int_);
    sigaction(SIGTERM, &sa, &old_term_);
  }
  Rig(const Rig&) = delete;
  Rig& operator=(const Rig&) = delete;
  Rig(Rig&&) = delete;
  Rig& operator=(Rig&&) = delete;
  ~Rig() {
    release();
    sigaction(SIGINT, &old_int_, nullptr);
    sigaction(SIGTERM, &old_term_, nullptr);
  }

  Clock& clock() noexcept { return simulated_ ? static_cast<Clock&>(sim_) : static_cast<Clock&>(mono_); }
  [[nodiscard]] bool simulated() const noexcept { return simulated_; }
  [[nodiscard]] DeviceSession& session() const noexcept { return *dev_.session; }
  [[nodiscard]] const DeviceInfo& info() const noexcept { return dev_.session->info(); }
  // The press fixture: the mock's finger (nullptr on a real unit).
  [[nodiscard]] sim::MockDevice* fixture() const noexcept { return mock_.get(); }
  [[nodiscard]] static bool interrupted() noexcept { return interrupted_flag() != 0; }
  double elapsed_s() noexcept { return to_seconds(clock().now() - start_); }
  [[nodiscard]] ResultCode last() const noexcept { return last_; }

  // One 1 ms tick: steps a simulated mock, then polls (drains telemetry, heartbeats).
  ResultCode tick() noexcept {
    if (simulated_) {
      sim_.advance(kTick);
      mock_->step(sim_.now());
    } else {
      next_ = std::max(next_ + kTick, mono_.now());  // behind: skip, never burst
      mono_.sleep_until(next_);
    }
    last_ = dev_.session->poll(clock().now());
    return last_;
  }
  // Ticks for duration_s (stops early on SIGINT), calling each() after every tick.
  template <class F>
  void run_for(double duration_s, F&& each) {
    const TimePoint end = clock().now() + from_seconds(duration_s);
    while (clock().now() < end && !interrupted()) {
      tick();
      each();
    }
  }
  void run_for(double duration_s) {
    run_for(duration_s, [] {});
  }
  bool await_state(DeviceState want, double timeout_s) {
    const TimePoint end = clock().now() + from_seconds(timeout_s);
    while (session().state() != want && clock().now() < end && !interrupted()) {
      tick();
    }
    return session().state() == want;
  }
  // Enables the unit or throws an Error naming the state and fault cause.
  void enable() {
    (void)session().request_enable();
    enabled_ = true;
    if (!await_state(DeviceState::enabled, 1.0)) {
      throw Error(fmt::format(
          "the device did not enable within 1 s: state {}, fault {}; check `mrskinctl info --log`, let a hot "
          "coil cool down, or power-cycle the unit",
          to_string(session().state()), fault_name(session().fault_code())));
    }
  }
  // Zero currents, disable, and wait (bounded) for the status; idempotent, never throws.
  void release() noexcept {
    if (!enabled_) {
      return;
    }
    enabled_ = false;
    const std::vector<double> zero(info().valves, 0.0);
    (void)session().send_valve_currents(zero);
    (void)session().request_disable();
    if (sim::MockDevice* f = fixture(); f != nullptr && simulated_) {
      lift_finger();
    }
    const TimePoint end = clock().now() + std::chrono::milliseconds(300);
    while (session().state() == DeviceState::enabled && clock().now() < end) {
      tick();
    }
  }
  // Protocol 1.1 degauss: disables the unit and asks it to run a decaying alternating current
  // through its coils, then ticks until its status clears the degaussing flag (bounded). A unit
  // with a unipolar driver ignores the request: its status never shows the flag.
  enum class DegaussOutcome { done, unsupported, unfinished };
  DegaussOutcome degauss(double timeout_s) noexcept {
    release();
    (void)session().request_degauss();
    const TimePoint start = clock().now();
    bool seen = false;
    while (clock().now() - start < from_seconds(timeout_s) && !interrupted()) {
      tick();
      seen = seen || session().degaussing();
      if (seen && !session().degaussing()) {
        return DegaussOutcome::done;
      }
      if (!seen && clock().now() - start > std::chrono::milliseconds(300)) {
        return DegaussOutcome::unsupported;  // its status came back (every 100 ms) without the flag
      }
    }
    return seen ? DegaussOutcome::unfinished : DegaussOutcome::unsupported;
  }
  void lift_finger() const noexcept {
    if (sim::MockDevice* f = fixture(); f != nullptr) {
      const std::vector<double> none(info().fluid_cells, 0.0);
      f->set_finger_indentation(none);
    }
  }

 private:
  bool simulated_;
  SimulatedClock sim_;
  MonotonicClock mono_;
  OpenedDevice dev_;
  std::shared_ptr<sim::MockDevice> mock_;  // set for mock:// (the unit behind dev_)
  TimePoint start_{};
  TimePoint next_{};
  ResultCode last_ = ResultCode::ok;
  bool enabled_ = false;
  struct sigaction old_int_ {};
  struct sigaction old_term_ {};
};

}  // namespace mrskin::ctl
