// The running daemon: the device session opened once, the bridge and its real-time loop (rebuilt
// on SIGHUP on the same session), and what the tick publishes for the control socket and the
// status line.
//
// Threads: the main thread (signals, status, reload), the tick (RealtimeLoop), the control socket
// thread. Only the tick touches the Bridge and the DeviceSession while the loop runs. It publishes
// small values through atomics after every step; the control thread reads the session itself only
// inside the SessionGate (fault dump), which makes the tick skip its step meanwhile.
#pragma once

#include <array>
#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "config.hpp"
#include "control_server.hpp"
#include "grid_snapshot.hpp"
#include "mrskin/bridge/bridge.hpp"
#include "mrskin/bridge/loop.hpp"
#include "mrskin/bridge/ros2_topics.hpp"
#include "mrskin/bridge/scene.hpp"
#include "mrskin/bridge/sources.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/driver/relaxed_counter.hpp"
#include "mrskin/eval/truth_scorer.hpp"
#include "session_gate.hpp"
#include "thread_cpu.hpp"

namespace mrskin::bridged {

// The slave stream named by a source URI. scene is set for scene:// (it also drives the mock's
// simulated finger). The one place to switch to make_source() (bridge/sources.hpp).
struct OpenedSource {
  std::unique_ptr<bridge::SlaveSource> source;
  bridge::Scene* scene = nullptr;          // scene:// only: it also drives the mock's finger
  bridge::StreamSource* stream = nullptr;  // udp://, replay://, igtl://: its counters
};
// wake (optional): a stream source's arrival hook notifies it (from the source's I/O thread), so
// it must outlive the source.
OpenedSource open_source(const Settings& s, Clock& clock, bridge::Waiter* wake = nullptr);
// mock://...?finger=SCENE: the scene whose script moves the mock's finger while the stream comes
// from elsewhere (a network run scored like a scene run); nullptr without one. Throws
// InvalidArgument for an unknown scene.
std::unique_ptr<bridge::Scene> open_finger_scene(const Settings& s);
bridge::LoopOptions loop_options(const Settings& s, bridge::Waiter* waiter = nullptr);

// Wraps the source to time-stamp fresh samples (the stream watchdog in status).
class WatchedSource final : public bridge::SlaveSource {
 public:
  // recorder (optional): every fresh sample is also recorded (replay:// format).
  explicit WatchedSource(bridge::SlaveSource& inner, bridge::SampleRecorder* recorder = nullptr) noexcept
      : inner_(inner), recorder_(recorder) {}
  bool latest(TimePoint now, bridge::SlaveSample& out) noexcept override;
  [[nodiscard]] TimePoint last_fresh() const noexcept { return last_fresh_; }  // tick thread

 private:
  bridge::SlaveSource& inner_;
  bridge::SampleRecorder* recorder_;
  TimePoint last_stamp_{};
  TimePoint last_fresh_{};
  bool any_ = false;
};

class Daemon final : public bridge::Tickable, public ControlBackend {
 public:
  // Opens the device and the source, builds the bridge and enables the device. Throws the
  // driver's typed errors (exit codes in exit_codes.hpp).
  Daemon(Settings settings, MonotonicClock& clock);
  Daemon(const Daemon&) = delete;
  Daemon& operator=(const Daemon&) = delete;
  Daemon(Daemon&&) = delete;
  Daemon& operator=(Daemon&&) = delete;
  ~Daemon() override;

  // Starts the loop; returns the real-time warning ("" if none, and on later starts).
  std::string start();
  void stop() noexcept;
  // SIGHUP: applies next (already validated) without closing the device. Returns the log lines.
  std::vector<std::string> reload(Settings next);

  // Main thread.
  [[nodiscard]] const Settings& settings() const noexcept { return settings_; }
  [[nodiscard]] const DeviceInfo& info() const noexcept { return dev_.session->info(); }
  void drive_finger();  // the mock's simulated finger follows a scene's script
  // The stream source's events not taken yet (connections, the first drop of each reason).
  std::vector<bridge::SourceEvent> take_source_events();
  // The bus budget's warning at the current rate ("" when within 80 % or not limited).
  [[nodiscard]] const std::string& bus_warning() const noexcept { return bridge_->bus_budget().warning; }
  // Set when no rate was given and the bus cannot carry the default: the rate chosen, and why.
  [[nodiscard]] const std::string& rate_note() const noexcept { return rate_note_; }
  // The stream source's latest warning ("" when none): why no sample may be arriving.
  [[nodiscard]] std::string stream_warning() const;
  [[nodiscard]] std::string status_line() const;
  // The log line for a sensor fault: which sensor, where, what was seen, what the bridge did.
  [[nodiscard]] std::string sensor_fault_text(const bridge::SensorFaultEvent& e) const;
  // Main thread, once per status period: what changed since the last call, for the log, each
  // with whether it is a warning: link errors by kind (counted over the period: at most one
  // line per period), disconnects and reconnects, FAULT and its cause, the stream going stale
  // and live again.
  struct HealthEvent {
    bool warning = false;
    std::string text;
  };
  std::vector<HealthEvent> take_health_events();
  [[nodiscard]] bool device_lost(double for_s) const noexcept;
  // Device in FAULT other than an e-stop the operator asked for.
  [[nodiscard]] bool unrequested_fault() const noexcept;
  // After stop(): the run's statistics (since the last reload) with the bus load filled in.
  [[nodiscard]] bridge::BridgeStats final_stats() const;
  // Main thread: reads each thread's CPU time (the first call, at start(), is the baseline; call
  // it once more before stop(), which ends the loop's and the mock's threads).
  void sample_threads();
  [[nodiscard]] const bridge::LoopStats* loop_stats() const noexcept {
    return loop_ ? &loop_->stats() : nullptr;
  }
  [[nodiscard]] double tick_period_s() const noexcept { return 1.0 / settings_.rate_hz; }
  // mock:// only: simulated time the unit skipped because its plant fell behind real time, s
  // (MockDevice::skipped_time_s); -1 on a real unit.
  [[nodiscard]] double mock_skipped_s() const noexcept { return mock_ ? mock_->skipped_time_s() : -1.0; }
  // mock:// only: host packets the lagging unit heard outside the bus (MockBusStats); 0 on a real unit.
  [[nodiscard]] std::uint64_t mock_host_while_lagging() const noexcept {
    return mock_ ? mock_->bus_stats().host_while_lagging : 0;
  }
  // The unit's design point against the default unit's (forces and lengths the bridge scales).
  [[nodiscard]] bridge::DesignScale design_scale() const noexcept { return bridge_->scale(); }
  // The statistics' errors are against the device's true force (mock://), not an estimate.
  [[nodiscard]] bool truth_scored() const noexcept { return scorer_ != nullptr; }
  // Main thread, for the service watchdog: ticks since start (across reloads) and the current
  // loop's overruns (from 0 again after a reload rebuilds the loop).
  [[nodiscard]] std::uint64_t live_ticks() const noexcept { return ticks_base_.load() + ticks_.value(); }
  [[nodiscard]] std::uint64_t live_overruns() const noexcept { return loop_ ? loop_->live_overruns() : 0; }
  [[nodiscard]] double uptime_s() const noexcept { return to_seconds(clock_.now() - t0_); }
  // Reports (datagrams) each way since the loop's start, per 1 ms frame (the handshake and the
  // configuration read left out).
  struct ReportsPerFrame {
    double host_to_device = 0.0;
    double device_to_host = 0.0;
  };
  [[nodiscard]] ReportsPerFrame reports_per_frame() const noexcept;
  [[nodiscard]] std::uint64_t reloads() const noexcept { return reloads_.load(); }
  [[nodiscard]] const bridge::SampleRecorder* recorder() const noexcept { return recorder_.get(); }
  [[nodiscard]] const SessionCounters& link_counters() const noexcept { return dev_.session->counters(); }
  [[nodiscard]] const bridge::SkinPublisher* topics() const noexcept { return topics_.get(); }

  // Tick thread.
  ResultCode tick(TimePoint now) noexcept override;

  // ControlBackend (control thread).
  std::string status_members() override;
  std::string fault_members() override;
  std::string telemetry_members() override;
  std::string grid_members() override;
  void grid_subscribers(std::size_t n) noexcept override;
  void request(std::string_view cmd) override;
  std::string lease_begin() override;
  Transport* leased_transport() noexcept override;
  void lease_end() noexcept override;

 private:
  // What a reload changes (plan_reload), and the swap itself (apply_reload: false when refused).
  struct ReloadPlan {
    bool mapping_changed = false;
    bool source_changed = false;
    bool loop_changed = false;
    bool bridge_changed = false;
  };
  [[nodiscard]] ReloadPlan plan_reload(const Settings& next) const;
  bool apply_reload(const Settings& next, const ReloadPlan& plan, std::vector<std::string>& log);
  void build_bridge(const Settings& s);  // setup, before the loop runs
  void fit_default_rate_to_bus();        // setup: rate_note_, default_rate_hz_
  std::unique_ptr<eval::TruthScorer> make_scorer(bridge::Bridge& b);
  void publish(TimePoint now) noexcept;
  void publish_grid(TimePoint now) noexcept;
  void publish_topics() noexcept;  // the skin topics' thread
  [[nodiscard]] std::string stream_state(std::int64_t now_ns) const;
  [[nodiscard]] std::string topics_members() const;  // status: the skin's topics, or null

  Settings settings_;
  double default_rate_hz_ = 0.0;  // the loop rate when none is given: 1000 Hz or what the bus carries
  std::string rate_note_;
  MonotonicClock& clock_;
  OpenedDevice dev_;
  std::shared_ptr<sim::MockDevice> mock_;  // set for mock:// (the simulated unit behind dev_)
  std::optional<sim::MockDeviceTruth> truth_;
  // Scores the bridge against truth_ (mock:// only); a new bridge gets a new one. Declared
  // before bridge_, which calls it: destroyed after it.
  std::unique_ptr<eval::TruthScorer> scorer_;
  // One waiter for the daemon's life, shared by every RealtimeLoop it builds (one runs at a
  // time) and woken by the stream sources' arrival hook: declared before the sources, so it
  // outlives their I/O threads, and never destroyed with a loop on a reload.
  std::unique_ptr<bridge::MonotonicWaiter> waiter_;
  OpenedSource source_;
  std::uint64_t events_seen_ = 0;                     // main thread: source_'s events logged
  std::unique_ptr<bridge::Scene> finger_scene_;       // mock://?finger=SCENE
  std::unique_ptr<bridge::SampleRecorder> recorder_;  // --record: the input, off the tick thread
  std::unique_ptr<WatchedSource> watched_;
  std::unique_ptr<bridge::Bridge> bridge_;
  std::unique_ptr<bridge::RealtimeLoop> loop_;
  std::vector<double> finger_;
  // Where the finger's script starts: t0_, or for a finger= scene beside a stream the stream's
  // first accepted sample (finger_waits_ until then, at the script's start), so the simulated
  // surgeon presses in step with a robot that plays the same script. A reload that changes the
  // source sets both again. (replay:// counts its samples as it loads: no wait.)
  TimePoint finger_t0_{};
  bool finger_waits_ = false;
  std::pair<std::uint64_t, std::uint64_t> reports_at_start_{};  // sent, received
  sim::MockBusStats bus_at_start_{};                            // the mock's bus when the loop started
  TimePoint t0_{};
  ThreadCpuMeter thread_cpu_;
  TimePoint thread_cpu_t0_{};
  bool warned_ = false;

  // Control -> tick: the operator's request, forwarded to the current Bridge at the next tick.
  std::atomic<unsigned char> pending_{0};
  std::atomic<unsigned char> operator_halt_{0};  // last request: 0 enable, 2 disable, 3 estop
  // The control thread reads the session while the tick stays out of it (session_gate.hpp).
  SessionGate gate_;
  std::atomic<bool> leased_{false};  // control thread: it holds the gate for a client's session

  // Published by the tick after every step.
  std::atomic<std::uint8_t> state_{0};
  std::atomic<std::uint8_t> fault_code_{0};
  std::atomic<std::uint8_t> last_fault_code_{0};
  RelaxedCounter faults_;
  std::atomic<bool> halted_{false};
  std::atomic<bool> connected_{true};
  std::atomic<bool> valves_released_{true};
  RelaxedCounter ticks_;                      // this bridge's ticks
  std::atomic<std::uint64_t> ticks_base_{0};  // earlier bridges' (reloads)
  std::atomic<double> rms_N_{0.0};
  std::atomic<double> stiffness_{0.0};
  std::atomic<double> peak_target_N_{0.0};
  std::atomic<double> peak_current_A_{0.0};
  RelaxedCounter sent_;
  RelaxedCounter received_;
  RelaxedCounter identity_changes_;
  // Link errors by kind (SessionCounters), for the log and the status.
  RelaxedCounter crc_errors_;
  RelaxedCounter decode_errors_;
  RelaxedCounter sequence_gaps_;
  RelaxedCounter link_duplicates_;
  RelaxedCounter telemetry_timeouts_;
  RelaxedCounter disconnects_;
  RelaxedCounter reconnects_;
  // The longest heartbeat round trip since the main thread last looked (it exchanges 0 in), ns.
  std::atomic<std::int64_t> max_round_trip_ns_{0};
  // Main thread: what take_health_events() last reported.
  struct HealthSeen {
    std::array<std::uint64_t, 7> link{};  // the counters above, in order
    std::uint8_t state = 0;
    std::uint8_t fault = 0;
    bool stale = false;
    bool any_sample = false;
    TimePoint at{};
  } seen_;
  std::atomic<std::int64_t> last_fresh_ns_{0};  // 0: no sample yet
  std::atomic<std::int64_t> disconnected_since_ns_{0};
  std::atomic<std::uint64_t> reloads_{0};
  // Sensor faults: the tick forwards the bridge's reports here (the queue outlives a reload's
  // bridge); the main thread logs them and keeps the list the status shows.
  SpscQueue<bridge::SensorFaultEvent> sensor_faults_{64};
  std::vector<std::pair<std::size_t, bridge::SensorFault>> faulty_sensors_;  // guarded by shown_mutex_
  // Settings the control thread shows (rate, device, source): main writes on reload.
  mutable std::mutex shown_mutex_;
  Settings shown_;

  // Grid telemetry: the tick publishes the arrays every kGridPeriod while a client subscribes.
  static constexpr Duration kGridPeriod = std::chrono::milliseconds(10);
  std::unique_ptr<GridSeqlock> grid_;
  std::atomic<std::size_t> grid_subscribers_{0};
  CoilThermalEstimate thermal_;  // tick thread (setup before)
  TimePoint last_thermal_{};
  int rows_ = 0;
  int cols_ = 0;
  double max_current_A_ = 0.0;
  double force_range_N_ = 0.0;
  std::string sensor_unit_ = "m";
  GridSeqlock::Copy grid_copy_;  // control thread
  std::vector<double> true_N_;   // tick thread: the mock's true forces

  // [topics]: the skin as ROS 2 topics, published by their own thread from grid_.
  std::unique_ptr<bridge::SkinPublisher> topics_;
  std::thread topics_thread_;
  std::mutex topics_mutex_;
  std::condition_variable topics_wake_;
  bool topics_stop_ = false;  // guarded by topics_mutex_
  std::atomic<bool> topics_on_{false};
};

}  // namespace mrskin::bridged
