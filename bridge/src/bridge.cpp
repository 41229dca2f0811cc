#include "mrskin/bridge/bridge.hpp"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>
#include <optional>
#include <string>
#include <vector>

#include "allocate_stage.hpp"
#include "mrskin/driver/atomic_raise.hpp"
#include "mrskin/driver/model/calibration.hpp"
#include "mrskin/driver/model/device_model.hpp"
#include "mrskin/driver/relaxed_counter.hpp"
#include "mrskin/driver/spsc_queue.hpp"
#include "render_stage.hpp"
#include "tick_record.hpp"
#include "tick_statistics.hpp"

namespace mrskin::bridge {

TissueEstimatorOptions default_estimator_options() noexcept {
  TissueEstimatorOptions o;
  o.kind = TissueKind::hunt_crossley;
  o.prior = TissueModel::kelvin_voigt(200.0, 0.0);  // soft: rendered until the fit is confident
  // A first press gives few samples over a short depth span: an early fit with the wrong exponent
  // can look confident (docs/bridge.md, "What the tuning measured").
  o.min_confidence = 0.9;
  o.hold_s = 0.1;
  o.fade_s = 0.2;
  return o;
}

namespace {

constexpr double kReferenceSensorNoise_m = 2e-6;  // the reference design's displacement sensors
// The reference's retreat (30 um) is 15 of its sensors' noise sigmas; on another unit the retreat
// keeps at least this share of that many of its own (7.5 sigmas by default): measured best on
// the fingertip and the palm together (docs/bridge.md, "A retreat above the fit's noise").
constexpr double kRetreatNoiseShare = 0.5;

// scaled (scaled_to_design(given, ...)) with two noise thresholds in the unit's own sensor
// sigmas. The direction latch's retreat stays above the fit's noise: scaled with the design
// alone, the fingertip's (30 um x 0.06 = 1.8 um) sat inside the 2-3 um its fit moves from tick
// to tick, and released its holds on 625 of 1,000 ticks (docs/bridge.md, "Where the 16x16's hold
// goes"). The observer's contact depth (25 um: 12.5 of the reference's 2 um sigmas) keeps as
// many sigmas of quieter sensors: at 25 um the fingertip's sweep left a cell unfound for 2 s
// (docs/bridge.md, "The plant rang on stiff cells").
BridgeOptions with_noise_floor(BridgeOptions scaled, const BridgeOptions& given,
                               const model::DeviceProfile& profile) noexcept {
  double quietest_m = std::numeric_limits<double>::infinity();
  double noisiest_m = 0.0;
  for (const model::SensorSpec& sensor : profile.sensors) {
    if (sensor.quantity == model::SensorQuantity::displacement && sensor.noise_std > 0.0) {
      quietest_m = std::min(quietest_m, sensor.noise_std);
      noisiest_m = std::max(noisiest_m, sensor.noise_std);
    }
  }
  if (std::isfinite(quietest_m)) {  // (the default 5x5: 15 um, below its 30 um as given)
    const double floor_m =
        kRetreatNoiseShare * given.unload_retreat_m * (quietest_m / kReferenceSensorNoise_m);
    scaled.unload_retreat_m = std::max(scaled.unload_retreat_m, floor_m);
    const double contact_m = given.observer.contact_threshold_m * (noisiest_m / kReferenceSensorNoise_m);
    scaled.observer.contact_threshold_m = std::min(scaled.observer.contact_threshold_m, contact_m);
  }
  return scaled;
}

}  // namespace

class __attribute__((visibility("hidden"))) Bridge::Impl {
 public:
  // The public functions, as documented in bridge.hpp (they forward here).
  Impl(DeviceSession& session, SlaveSource& source, BridgeOptions options);
  Impl(const Impl&) = delete;
  Impl& operator=(const Impl&) = delete;
  Impl(Impl&&) = delete;
  Impl& operator=(Impl&&) = delete;
  ~Impl();
  void set_tick_watcher(TickWatcher* watcher) noexcept { watcher_ = watcher; }
  ResultCode enable() noexcept;
  void request(Request r) noexcept;
  [[nodiscard]] bool halted() const noexcept { return halted_.load(std::memory_order_acquire); }
  void retune(const BridgeTuning& tuning);
  [[nodiscard]] BridgeTuning tuning() const noexcept;
  [[nodiscard]] const BridgeOptions& options() const noexcept { return options_; }
  [[nodiscard]] DesignScale scale() const noexcept { return scale_; }
  // The tick's calls: inlined into the public functions, so the pointer costs no call.
  [[gnu::always_inline]] inline ResultCode step(TimePoint now) noexcept;
  std::string start(Clock& clock);
  void stop() noexcept;
  [[nodiscard]] bool running() const noexcept { return loop_ != nullptr && loop_->running(); }
  void notify() noexcept {
    if (loop_ != nullptr) {
      loop_->notify();
    }
  }
  [[nodiscard]] const LoopStats* loop_stats() const noexcept { return loop_ ? &loop_->stats() : nullptr; }
  [[nodiscard]] const BridgeStats& stats() const noexcept { return stats_; }
  [[nodiscard]] std::uint64_t live_ticks() const noexcept { return live_ticks_.value(); }
  [[nodiscard]] double live_rms_error_N() const noexcept {
    return live_rms_N_.load(std::memory_order_relaxed);
  }
  [[nodiscard]] double live_stiffness_N_per_m() const noexcept {
    return live_stiffness_.load(std::memory_order_relaxed);
  }
  [[nodiscard]] std::span<const double> targets_N() const noexcept { return record_.allocated.target_N; }
  [[nodiscard]] std::span<const double> currents_A() const noexcept { return record_.allocated.current_A; }
  [[nodiscard]] std::span<const double> law_N() const noexcept { return record_.rendered.tissue_N; }
  [[nodiscard]] const BusBudgetCheck& bus_budget() const noexcept { return bus_budget_; }
  [[nodiscard]] std::span<const double> floor_N() const noexcept { return record_.allocated.floor_N; }
  [[nodiscard]] std::span<const double> ceiling_N() const noexcept { return record_.allocated.ceiling_N; }
  [[nodiscard]] const model::CellObserver& observer() const noexcept { return *observer_; }
  [[nodiscard]] const model::CellInverse& inverse() const noexcept { return *inverse_; }
  [[nodiscard]] const SensorFaultMonitor& sensor_fault_monitor() const noexcept { return *sensor_faults_; }
  bool take_sensor_fault(SensorFaultEvent& out) noexcept { return sensor_fault_events_.try_pop(out); }
  [[nodiscard]] std::uint64_t live_sensor_faults() const noexcept { return live_sensor_faults_.value(); }
  [[nodiscard]] double tick_period_s() const noexcept { return 1.0 / options_.rate_hz; }
  void set_perf_clock(const Clock* clock) noexcept { perf_clock_ = clock; }

 private:
  // The four stages, in the order step() runs them, then what only watches the tick.
  [[gnu::always_inline]] inline bool observe(TimePoint now) noexcept;  // false: the sensors halted the tick
  [[gnu::always_inline]] inline void render(TimePoint now) noexcept;
  [[gnu::always_inline]] inline void allocate() noexcept;
  [[gnu::always_inline]] inline ResultCode send(TimePoint now, TimePoint began, const Clock& perf) noexcept;
  [[gnu::always_inline]] inline void watch(TimePoint began, const Clock& perf) noexcept;
  bool apply_request() noexcept;     // true while halted
  void release(Request r) noexcept;  // zero currents, disable or estop
  void watch_sensors(TimePoint now) noexcept;
  void count_tick() noexcept;

  DeviceSession& session_;
  SlaveSource& source_;
  BridgeOptions options_;
  DesignScale scale_{};  // the unit's design point against the reference's
  GridLayout layout_;
  // The unit's current limit, A: its Identity's, which a reconnect to the same unit keeps.
  double max_current_A_ = 0.0;
  std::unique_ptr<model::DeviceModel> model_;
  std::unique_ptr<model::CellObserver> observer_;
  std::unique_ptr<model::CellInverse> inverse_;
  const Clock* perf_clock_ = nullptr;
  MonotonicClock default_perf_clock_;
  std::vector<double> valve_gain_;      // calibrated per-valve yield gain
  std::vector<double> sensor_offset_;   // calibrated zero per sensor, the sensors' SI unit
  std::vector<double> sensor_reading_;  // this tick's readings less their zero
  // The tick's record and its stages (made once the model they read exists).
  detail::TickRecord record_;
  std::optional<detail::RenderStage> render_;
  std::optional<detail::AllocateStage> allocate_;
  std::optional<detail::TickStatistics> statistics_;
  TickWatcher* watcher_ = nullptr;
  // The record as a watcher sees it (TickView).
  class RecordView final : public TickView {
   public:
    explicit RecordView(const Impl& bridge) noexcept : b_(bridge) {}
    [[nodiscard]] double since_start_s() const noexcept override { return b_.record_.since_start_s; }
    [[nodiscard]] double period_s() const noexcept override { return 1.0 / b_.options_.rate_hz; }
    [[nodiscard]] std::span<const double> observed_force_N() const noexcept override {
      return b_.record_.observed.force_N;
    }
    [[nodiscard]] std::span<const double> tissue_N() const noexcept override {
      return b_.record_.rendered.tissue_N;
    }
    [[nodiscard]] std::span<const double> target_N() const noexcept override {
      return b_.record_.allocated.target_N;
    }
    [[nodiscard]] std::span<const model::CellSolution> solve() const noexcept override {
      return b_.inverse_->cells();
    }
    [[nodiscard]] bool valves_open(std::size_t cell) const noexcept override {
      return detail::valves_open(b_.layout_, b_.record_.allocated.current_A, cell, b_.max_current_A_);
    }
    [[nodiscard]] double law_force_N(std::size_t cell, double depth_m,
                                     double rate_m_per_s) const noexcept override {
      return b_.render_->cells()[cell].law.force_N(depth_m, rate_m_per_s);
    }

   private:
    const Impl& b_;
  };
  RecordView view_{*this};
  // Send's state across ticks: the currents last sent, when, and whether anything was.
  std::vector<double> sent_A_;
  bool ever_sent_ = false;
  // The sensors' watch across ticks.
  std::unique_ptr<SensorFaultMonitor> sensor_faults_;
  SpscQueue<SensorFaultEvent> sensor_fault_events_{64};
  RelaxedCounter live_sensor_faults_;
  std::uint64_t telemetry_seen_ = 0;  // the session's telemetry count at the last tick
  std::uint64_t link_gaps_seen_ = 0;  // ...and its timeouts and reconnects
  bool watched_last_tick_ = false;    // false: a gap (halted, observer error) before this tick
  bool sensor_halt_ = false;          // a cell has no healthy sensor: no enable
  std::atomic<unsigned char> pending_request_{0};
  std::atomic<bool> halted_{false};
  static constexpr double kReferenceDepth_m = 4e-3;  // live stiffness is reported at this depth
  TimePoint start_{};
  bool started_ = false;
  BridgeStats stats_;
  BusBudgetCheck bus_budget_;
  RelaxedCounter live_ticks_;
  std::atomic<double> live_rms_N_{0.0};
  std::atomic<double> live_stiffness_{0.0};
  Clock* loop_clock_ = nullptr;
  std::unique_ptr<RealtimeLoop> loop_;  // last: destroyed (stopped) first
};

Bridge::Impl::Impl(DeviceSession& session, SlaveSource& source, BridgeOptions options)
    : session_(session),
      source_(source),
      options_(options),
      layout_(session.info().rows, session.info().cols),
      max_current_A_(session.info().max_current_A) {
  if (!(options_.rate_hz >= 1.0 && options_.rate_hz <= 20000.0)) {
    throw InvalidArgument("bridge rate " + std::to_string(options_.rate_hz) + " Hz is outside 1..20000 Hz");
  }
  const model::DeviceProfile* profile = session.profile();
  if (profile == nullptr) {
    throw InvalidArgument(
        "the bridge needs the device's profile: open the device with SessionOptions::read_configuration = "
        "true");
  }
  if (options_.scale_to_design) {
    scale_ = design_scale(profile->design);
    options_ = with_noise_floor(scaled_to_design(options_, scale_), options_, *profile);
  }
  const std::size_t cells = layout_.fluid_cell_count();
  if (session.info().sensors != profile->sensors.size() || session.info().valves != layout_.valve_count() ||
      profile->rows != layout_.rows() || profile->cols != layout_.cols()) {
    throw InvalidArgument("device '" + profile->name + "' reports " + std::to_string(session.info().sensors) +
                          " sensors and " + std::to_string(session.info().valves) +
                          " valves, which its stored profile does not match: rewrite the device's profile");
  }
  if (!options_.mapping.valid()) {
    throw InvalidArgument("the workspace mapping needs finite numbers and cells_per_m > 0");
  }
  if (!(options_.loading_open_fraction >= 0.0)) {
    throw InvalidArgument("loading_open_fraction must be >= 0 (infinity: off), got " +
                          std::to_string(options_.loading_open_fraction));
  }
  if (options_.check_bus_budget) {
    bus_budget_ = check_bus_budget(session.info(), session.transport(), options_.rate_hz);
  }
  // The unit's own parameters: its stored calibration applied to the profile it was built to.
  model::Calibration calibration;
  if (!session.info().calibration.empty()) {
    calibration = model::parse_calibration(session.info().calibration, "the calibration stored on the device",
                                           layout_.valve_count(), profile->sensors.size());
  }
  // The sensors' zero at rest (mrskinctl calibrate), subtracted before the observer reads them.
  sensor_offset_.assign(profile->sensors.size(), 0.0);
  std::copy(calibration.sensor_offset.begin(), calibration.sensor_offset.end(), sensor_offset_.begin());
  sensor_reading_.assign(profile->sensors.size(), 0.0);
  model_ = std::make_unique<model::DeviceModel>(model::apply_calibration(*profile, calibration));
  observer_ = std::make_unique<model::CellObserver>(*model_, options_.observer);
  // A unit's declared deadband (protocol 1.2) repeats readings: no evidence of a stuck sensor.
  const double reading_deadband = session.info().sensor_deadband_counts * session.info().sensor_lsb;
  sensor_faults_ =
      std::make_unique<SensorFaultMonitor>(*profile, layout_, options_.sensor_faults, reading_deadband);
  inverse_ = std::make_unique<model::CellInverse>(*model_, options_.inverse);
  valve_gain_.assign(layout_.valve_count(), 1.0);
  for (std::size_t v = 0; v < valve_gain_.size(); ++v) {
    valve_gain_[v] = calibration.valve_gain(v);
  }
  if (observer_->set_valve_yield_gain(valve_gain_) != model::Status::ok ||
      inverse_->set_valve_yield_gain(valve_gain_) != model::Status::ok) {
    throw InvalidArgument(
        "the calibration stored on the device has unusable valve gains: recalibrate the unit");
  }
  detail::Rendering& r = record_.rendered;
  r.state.assign(cells, model::CellState{});
  r.target.assign(cells, model::CellImpedanceTarget{});
  r.tissue_N.assign(cells, 0.0);
  r.contact.assign(cells, 0);
  detail::Allocation& a = record_.allocated;
  a.current_A.assign(layout_.valve_count(), 0.0);
  a.target_N.assign(cells, 0.0);
  a.below_floor.assign(cells, 0);
  a.drain_held.assign(cells, 0);
  a.floor_N.assign(cells, std::numeric_limits<double>::quiet_NaN());
  a.ceiling_N.assign(cells, std::numeric_limits<double>::quiet_NaN());
  sent_A_.assign(layout_.valve_count(), 0.0);
  render_.emplace(options_, layout_, scale_);
  allocate_.emplace(options_, layout_, *model_, *inverse_, *observer_, valve_gain_, max_current_A_);
  statistics_.emplace(options_, *inverse_, cells);
}

Bridge::Impl::~Impl() { stop(); }

ResultCode Bridge::Impl::enable() noexcept { return session_.request_enable(); }

void Bridge::Impl::request(Request r) noexcept {
  atomic_raise(pending_request_, static_cast<unsigned char>(r));  // the strongest pending request wins
}

void Bridge::Impl::release(Request r) noexcept {
  std::vector<double>& current_A = record_.allocated.current_A;
  std::fill(current_A.begin(), current_A.end(), 0.0);
  (void)session_.send_valve_currents(current_A);  // released in this tick, whatever the state
  std::copy(current_A.begin(), current_A.end(), sent_A_.begin());
  (void)(r == Request::estop ? session_.request_estop() : session_.request_disable());
  render_->clear_feedback();
  halted_.store(true, std::memory_order_release);
}

bool Bridge::Impl::apply_request() noexcept {
  const auto r = static_cast<Request>(pending_request_.exchange(0, std::memory_order_acq_rel));
  if (r == Request::estop || r == Request::disable) {
    release(r);
  } else if (r == Request::enable && !sensor_halt_) {  // a cell nobody reads stays released
    (void)session_.request_enable();
    halted_.store(false, std::memory_order_release);
  }
  return halted_.load(std::memory_order_relaxed);
}

// Fresh telemetry only: a tick that read nothing new must not count as a repeated reading.
void Bridge::Impl::watch_sensors(TimePoint now) noexcept {
  const SessionCounters& link = session_.counters();
  const std::uint64_t gaps = link.telemetry_timeouts + link.reconnects;
  if (!watched_last_tick_ || gaps != link_gaps_seen_) {
    sensor_faults_->restart_history();  // readings from before a gap are no history for these tests
    // A reconnected unit declared its deadband anew (and a bridge built while it was away read 0).
    sensor_faults_->set_reading_deadband(session_.info().sensor_deadband_counts * session_.info().sensor_lsb);
    link_gaps_seen_ = gaps;
  }
  watched_last_tick_ = true;
  if (link.telemetry == telemetry_seen_) {
    return;
  }
  telemetry_seen_ = link.telemetry;
  // Spaced by the unit's clock: a late tick reads the newest of several readings.
  const std::size_t k = sensor_faults_->update(sensor_reading_, observer_->sensor_residual_sigma(),
                                               session_.sensor_device_time_us());
  if (k == SensorFaultMonitor::npos) {
    return;
  }
  (void)observer_->set_sensor_excluded(k, true);
  ++stats_.sensor_faults;
  SensorFaultEvent e;
  e.sensor = k;
  e.fault = sensor_faults_->fault(k);
  e.evidence = sensor_faults_->evidence(k);
  e.unobservable_cell = sensor_faults_->unobservable_cell();
  e.at_s = to_seconds(now - start_);
  e.healthy_left = sensor_faults_->healthy_count();
  (void)sensor_fault_events_.try_push(e);
  live_sensor_faults_.set(stats_.sensor_faults);
  if (e.unobservable_cell != SensorFaultMonitor::npos && !sensor_halt_) {
    sensor_halt_ = true;
    ++stats_.sensor_fault_halts;
    release(Request::disable);
  }
}

void Bridge::Impl::count_tick() noexcept {
  ++stats_.ticks;
  live_ticks_.set(stats_.ticks);
}

// Observe: the readings less their zero through the observer, and the sensors' watch on them.
bool Bridge::Impl::observe(TimePoint now) noexcept {
  const double dt = 1.0 / options_.rate_hz;
  const std::span<const double> raw = session_.sensors();
  const std::size_t readings = std::min(sensor_reading_.size(), raw.size());
  for (std::size_t k = 0; k < readings; ++k) {
    sensor_reading_[k] = raw[k] - sensor_offset_[k];
  }
  if (observer_->update(sensor_reading_, record_.allocated.current_A, dt) != model::Status::ok) {
    ++stats_.observer_errors;  // the estimate of the last good tick stands
    watched_last_tick_ = false;
  } else {
    watch_sensors(now);
  }
  detail::Observation& o = record_.observed;
  o.depth_m = observer_->indentation_m();
  o.rate_m_per_s = observer_->velocity_m_per_s();
  o.force_N = observer_->force_N();
  o.outflow_m3_per_s = observer_->outflow_m3_per_s();
  return !sensor_halt_;
}

// Render: the stream into the tissue estimate, then each cell's law at its state.
void Bridge::Impl::render(TimePoint now) noexcept {
  render_->take_stream(source_, now, start_, stats_, record_.rendered);
  live_stiffness_.store(render_->estimate().model.tangent_stiffness_N_per_m(kReferenceDepth_m),
                        std::memory_order_relaxed);
  render_->render(record_.observed, inverse_->cells(), record_.allocated.target_N,
                  record_.allocated.drain_held, 1.0 / options_.rate_hz, record_.rendered);
}

// Allocate: the inverse and every correction of its currents (allocate_stage.hpp).
void Bridge::Impl::allocate() noexcept {
  allocate_->run(record_.rendered, record_.observed.force_N, record_.since_start_s, stats_,
                 record_.allocated);
}

// Send: only the blocks of valves whose counts changed go; each block again every
// resend_period_s, a few blocks a tick (DeviceSession::send_valve_current_changes), so a hold or a
// skin nobody touches costs little bus traffic and a large grid's refresh loads no single tick
// (the device's watchdog runs on the session's heartbeat).
ResultCode Bridge::Impl::send(TimePoint now, TimePoint began, const Clock& perf) noexcept {
  const std::vector<double>& current_A = record_.allocated.current_A;
  const bool changed = !std::equal(current_A.begin(), current_A.end(), sent_A_.begin());
  if (changed) {  // unchanged currents are the ones sent, counted when they changed
    for (const double a : current_A) {
      stats_.max_current_A = std::max(stats_.max_current_A, a);
    }
  }
  const Duration period = from_seconds(options_.resend_period_s);
  // The blocks a tick may refresh: all of them once a period, spread evenly over its ticks.
  const auto refresh_per_tick = [&] {
    return std::max<std::size_t>(
        1, static_cast<std::size_t>(std::ceil(static_cast<double>(session_.valve_current_blocks()) /
                                              (options_.resend_period_s * options_.rate_hz))));
  };
  ResultCode sent = ResultCode::ok;
  if (changed || !ever_sent_) {
    sent = session_.send_valve_current_changes(current_A, now, period, refresh_per_tick());
    if (sent == ResultCode::ok) {
      std::copy(current_A.begin(), current_A.end(), sent_A_.begin());
      ever_sent_ = true;
    }
  } else if (now >= session_.valve_refresh_due(period)) {
    sent = session_.refresh_valve_currents(now, period, refresh_per_tick());
  } else {
    ++stats_.unchanged_sends_skipped;
  }
  if (sent != ResultCode::ok) {
    ++stats_.send_failures;
  } else if (record_.rendered.fresh_sample) {
    const Duration processing = perf.now() - began;
    stats_.processing_latency.add(processing.count());
    stats_.end_to_end_latency.add((now - record_.rendered.fresh_arrival + processing).count());
  }
  return sent;
}

// After the tick: the statistics and the watcher read its record; nothing here feeds back.
void Bridge::Impl::watch(TimePoint began, const Clock& perf) noexcept {
  statistics_->count(record_, inverse_->cells(), stats_);
  if (watcher_ != nullptr) {
    watcher_->on_tick(view_, stats_);
    live_rms_N_.store(stats_.force_rms_error_N(), std::memory_order_relaxed);
  }
  count_tick();
  const std::int64_t took_ns = (perf.now() - began).count();
  stats_.tick_time.add(took_ns);
  if (static_cast<double>(took_ns) > 1e9 / options_.rate_hz) {
    ++stats_.overruns;
  }
}

ResultCode Bridge::Impl::step(TimePoint now) noexcept {
  const Clock& perf = perf_clock_ != nullptr ? *perf_clock_ : default_perf_clock_;
  const TimePoint began = perf.now();
  const ResultCode rc = session_.poll(now);
  if (rc == ResultCode::disconnected) {
    return rc;
  }
  if (!started_) {
    start_ = now;
    started_ = true;
  }
  if (apply_request()) {
    watched_last_tick_ = false;
    count_tick();  // halted: polled, nothing rendered
    return rc;
  }
  record_.now = now;
  record_.since_start_s = to_seconds(now - start_);
  if (!observe(now)) {
    count_tick();  // a cell nobody reads: released, nothing rendered
    return rc;
  }
  render(now);
  allocate();
  const ResultCode sent = send(now, began, perf);
  watch(began, perf);
  return rc == ResultCode::ok ? sent : rc;
}

void apply_tuning(const BridgeTuning& t, BridgeOptions& o) noexcept {
  o.rate_hz = t.rate_hz;
  o.feedback_gain_per_s = t.feedback_gain_per_s;
  o.footprint_cells = t.footprint_cells;
  o.resend_period_s = t.resend_period_s;
  o.mapping = t.mapping;
  o.estimator.hold_s = t.stale_hold_s;
  o.estimator.fade_s = t.stale_fade_s;
  o.realtime = t.realtime;
  o.rt_priority = t.rt_priority;
  o.loop_cpu = t.loop_cpu;
}

BridgeTuning Bridge::Impl::tuning() const noexcept {
  BridgeTuning t;
  t.rate_hz = options_.rate_hz;
  t.feedback_gain_per_s = options_.feedback_gain_per_s;
  t.footprint_cells = options_.footprint_cells;
  t.resend_period_s = options_.resend_period_s;
  t.mapping = options_.mapping;
  t.stale_hold_s = render_->estimator().options().hold_s;
  t.stale_fade_s = render_->estimator().options().fade_s;
  t.realtime = options_.realtime;
  t.rt_priority = options_.rt_priority;
  t.loop_cpu = options_.loop_cpu;
  return t;
}

void Bridge::Impl::retune(const BridgeTuning& t) {
  if (running()) {
    throw InvalidArgument("retune the bridge between ticks: stop() its loop first");
  }
  if (!(t.rate_hz >= 1.0 && t.rate_hz <= 20000.0)) {
    throw InvalidArgument("bridge rate " + std::to_string(t.rate_hz) + " Hz is outside 1..20000 Hz");
  }
  if (!(t.feedback_gain_per_s >= 0.0 && std::isfinite(t.feedback_gain_per_s)) ||
      !(t.footprint_cells > 0.0 && std::isfinite(t.footprint_cells)) ||
      !(t.resend_period_s > 0.0 && std::isfinite(t.resend_period_s))) {
    throw InvalidArgument(
        "retune: feedback_gain_per_s >= 0, footprint_cells > 0 and resend_period_s > 0 (finite)");
  }
  if (!t.mapping.valid()) {
    throw InvalidArgument("the workspace mapping needs finite numbers and cells_per_m > 0");
  }
  BusBudgetCheck budget = bus_budget_;
  if (options_.check_bus_budget && t.rate_hz != options_.rate_hz) {
    budget = check_bus_budget(session_.info(), session_.transport(), t.rate_hz);  // throws: nothing changed
  }
  render_->estimator().set_stale_policy(t.stale_hold_s, t.stale_fade_s);  // throws before anything changed
  bus_budget_ = std::move(budget);
  if (t.rate_hz != options_.rate_hz || t.realtime != options_.realtime ||
      t.rt_priority != options_.rt_priority || t.loop_cpu != options_.loop_cpu) {
    loop_.reset();  // the library's loop is made again at start() with the new rate
    loop_clock_ = nullptr;
  }
  apply_tuning(t, options_);
  // What the rate sets: the unloading latch's smoothing and the drain's constants (the observer's
  // filters take dt per tick).
  render_->retune_rate();
  allocate_->retune_rate();
}

std::string Bridge::Impl::start(Clock& clock) {
  if (running()) {
    return {};
  }
  if (loop_ == nullptr || loop_clock_ != &clock) {  // one loop per clock: its warning comes once
    LoopOptions lo;
    lo.rate_hz = options_.rate_hz;
    lo.realtime = options_.realtime;
    lo.priority = options_.rt_priority;
    lo.cpu = options_.loop_cpu;
    loop_ = std::make_unique<RealtimeLoop>(
        clock, [](void* self, TimePoint now) noexcept { return static_cast<Impl*>(self)->step(now); }, this,
        lo);
    loop_clock_ = &clock;
  }
  return loop_->start();
}

void Bridge::Impl::stop() noexcept {
  if (loop_ == nullptr || !loop_->running()) {
    return;
  }
  loop_->stop();
  stats_.skipped_periods += loop_->stats().skipped_periods;
}

// --- the public face: one pointer to the state ---------------------------------------------

Bridge::Bridge(DeviceSession& session, SlaveSource& source, BridgeOptions options)
    : impl_(std::make_unique<Impl>(session, source, std::move(options))) {}
Bridge::~Bridge() = default;
void Bridge::set_tick_watcher(TickWatcher* watcher) noexcept { impl_->set_tick_watcher(watcher); }
ResultCode Bridge::enable() noexcept { return impl_->enable(); }
void Bridge::request(Request r) noexcept { impl_->request(r); }
bool Bridge::halted() const noexcept { return impl_->halted(); }
void Bridge::retune(const BridgeTuning& tuning) { impl_->retune(tuning); }
BridgeTuning Bridge::tuning() const noexcept { return impl_->tuning(); }
const BridgeOptions& Bridge::options() const noexcept { return impl_->options(); }
DesignScale Bridge::scale() const noexcept { return impl_->scale(); }

DesignScale design_scale(const model::DesignPoint& design) noexcept {
  DesignScale s;
  if (design.indentation_m > 0.0 && std::isfinite(design.indentation_m)) {
    s.length = design.indentation_m / kReferenceDesignIndentation_m;
  }
  if (design.force_range_N > 0.0 && std::isfinite(design.force_range_N)) {
    s.force = design.force_range_N / kReferenceDesignForce_N;
  }
  return s;
}

BridgeOptions scaled_to_design(BridgeOptions o, DesignScale s) noexcept {
  if (s.length == 1.0 && s.force == 1.0) {
    return o;  // the reference design: bit for bit as given
  }
  for (double* length : {&o.contact_threshold_m, &o.unload_rate_m_per_s, &o.load_exit_rate_m_per_s,
                         &o.unload_retreat_m, &o.inverse.hold_rate_tolerance_m_per_s,
                         &o.inverse.indentation_tolerance_m, &o.inverse.rate_tolerance_m_per_s}) {
    *length *= s.length;  // rates too: the same motion in the unit's own depth
  }
  // Not the observer's: its fit and its contact depth are set by the sensors' noise, which the
  // profile states apart (a threshold of a few noise sigmas would find contact in the noise).
  for (double* force : {&o.max_force_N, &o.contact_force_N, &o.feedback_limit_N, &o.relative_error_floor_N,
                        &o.inverse.force_tolerance_N}) {
    *force *= s.force;
  }
  o.passivity_tolerance_J *= s.force * s.length;
  return o;
}

ResultCode Bridge::step(TimePoint now) noexcept { return impl_->step(now); }
std::string Bridge::start(Clock& clock) { return impl_->start(clock); }
void Bridge::stop() noexcept { impl_->stop(); }
bool Bridge::running() const noexcept { return impl_->running(); }
void Bridge::notify() noexcept { impl_->notify(); }
const LoopStats* Bridge::loop_stats() const noexcept { return impl_->loop_stats(); }
const BridgeStats& Bridge::stats() const noexcept { return impl_->stats(); }
std::uint64_t Bridge::live_ticks() const noexcept { return impl_->live_ticks(); }
double Bridge::live_rms_error_N() const noexcept { return impl_->live_rms_error_N(); }
double Bridge::live_stiffness_N_per_m() const noexcept { return impl_->live_stiffness_N_per_m(); }
std::span<const double> Bridge::targets_N() const noexcept { return impl_->targets_N(); }
std::span<const double> Bridge::currents_A() const noexcept { return impl_->currents_A(); }
std::span<const double> Bridge::law_N() const noexcept { return impl_->law_N(); }
const BusBudgetCheck& Bridge::bus_budget() const noexcept { return impl_->bus_budget(); }
std::span<const double> Bridge::envelope_floor_N() const noexcept { return impl_->floor_N(); }
std::span<const double> Bridge::envelope_ceiling_N() const noexcept { return impl_->ceiling_N(); }
const model::CellObserver& Bridge::observer() const noexcept { return impl_->observer(); }
const model::CellInverse& Bridge::inverse() const noexcept { return impl_->inverse(); }
const SensorFaultMonitor& Bridge::sensor_fault_monitor() const noexcept {
  return impl_->sensor_fault_monitor();
}
bool Bridge::take_sensor_fault(SensorFaultEvent& out) noexcept { return impl_->take_sensor_fault(out); }
std::uint64_t Bridge::live_sensor_faults() const noexcept { return impl_->live_sensor_faults(); }
double Bridge::tick_period_s() const noexcept { return impl_->tick_period_s(); }
void Bridge::set_perf_clock(const Clock* clock) noexcept { impl_->set_perf_clock(clock); }

static_assert(sizeof(Bridge) == sizeof(void*), "Bridge is one pointer: its state lives in Bridge::Impl");

}  // namespace mrskin::bridge
