#include "mrskin/bridge/bridge.hpp"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <string>
#include <vector>

#include "mrskin/driver/model/calibration.hpp"
#include "mrskin/driver/model/device_model.hpp"
#include "mrskin/driver/spsc_queue.hpp"

namespace mrskin::bridge {

TissueEstimatorOptions default_estimator_options() noexcept {
  TissueEstimatorOptions o;
  o.kind = TissueKind::hunt_crossley;
  o.prior = TissueModel::kelvin_voigt(200.0, 0.0);  // soft: rendered until the fit is confident
  // A first press gives few samples over a short depth span: an early fit with the wrong exponent
  // looked confident at 0.6 (demo: 0.076 N RMS against 0.031 N at 0.9).
  o.min_confidence = 0.9;
  o.hold_s = 0.1;
  o.fade_s = 0.2;
  return o;
}

class Bridge::Impl {
 public:
  // The public functions, as documented in bridge.hpp (they forward here).
  Impl(DeviceSession& session, SlaveSource& source, BridgeOptions options);
  Impl(const Impl&) = delete;
  Impl& operator=(const Impl&) = delete;
  Impl(Impl&&) = delete;
  Impl& operator=(Impl&&) = delete;
  ~Impl();
  void set_force_truth(const ForceTruth* truth) noexcept { truth_ = truth; }
  ResultCode enable() noexcept;
  void request(Request r) noexcept;
  [[nodiscard]] bool halted() const noexcept { return halted_.load(std::memory_order_acquire); }
  void retune(const BridgeTuning& tuning);
  [[nodiscard]] BridgeTuning tuning() const noexcept;
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
  [[nodiscard]] std::uint64_t live_ticks() const noexcept {
    return live_ticks_.load(std::memory_order_relaxed);
  }
  [[nodiscard]] double live_rms_error_N() const noexcept {
    return live_rms_N_.load(std::memory_order_relaxed);
  }
  [[nodiscard]] double live_stiffness_N_per_m() const noexcept {
    return live_stiffness_.load(std::memory_order_relaxed);
  }
  [[nodiscard]] std::span<const double> targets_N() const noexcept { return target_N_; }
  [[nodiscard]] std::span<const double> currents_A() const noexcept { return current_A_; }
  [[nodiscard]] const model::CellObserver& observer() const noexcept { return *observer_; }
  [[nodiscard]] const model::CellInverse& inverse() const noexcept { return *inverse_; }
  [[nodiscard]] const SensorFaultMonitor& sensor_fault_monitor() const noexcept { return *sensor_faults_; }
  bool take_sensor_fault(SensorFaultEvent& out) noexcept { return sensor_fault_events_.try_pop(out); }
  [[nodiscard]] std::uint64_t live_sensor_faults() const noexcept {
    return live_sensor_faults_.load(std::memory_order_relaxed);
  }
  [[nodiscard]] double tick_period_s() const noexcept { return 1.0 / options_.rate_hz; }
  void set_perf_clock(const Clock* clock) noexcept { perf_clock_ = clock; }

 private:
  void update_tissue_model(TimePoint now) noexcept;
  void compute_targets() noexcept;
  double direction_rate(std::size_t i, bool contact, double depth_m, double rate_m_per_s) noexcept;
  void lock_short_cells() noexcept;
  void clamp_targets_into_envelope() noexcept;
  [[nodiscard]] bool valves_open(std::size_t cell) const noexcept;  // every valve of the cell at ~0 A
  bool apply_request() noexcept;                                    // true while halted
  void release(Request r) noexcept;                                 // zero currents, disable or estop
  void watch_sensors(TimePoint now) noexcept;
  void score() noexcept;

  DeviceSession& session_;
  SlaveSource& source_;
  BridgeOptions options_;
  GridLayout layout_;
  // The unit's current limit, A: its Identity's, which a reconnect to the same unit keeps.
  double max_current_A_ = 0.0;
  std::unique_ptr<model::DeviceModel> model_;
  std::unique_ptr<model::CellObserver> observer_;
  std::unique_ptr<model::CellInverse> inverse_;
  const ForceTruth* truth_ = nullptr;
  const Clock* perf_clock_ = nullptr;
  MonotonicClock default_perf_clock_;
  std::vector<model::CellImpedanceTarget> targets_;
  std::vector<model::CellState> states_;
  std::vector<double> target_N_;            // tissue law clamped into this tick's envelope (loaded cells)
  std::vector<double> tissue_N_;            // tissue law at the cell's state
  std::vector<double> feedback_N_;          // integral correction per cell
  std::vector<unsigned char> unloading_;    // per cell: latched release (direction_rate)
  std::vector<unsigned char> loading_;      // per cell: latched loading (direction_rate)
  std::vector<double> extreme_m_;           // per cell: peak depth while loaded, trough while unloading
  std::vector<double> smooth_depth_m_;      // per cell: depth smoothed for the unloading latch
  std::vector<unsigned char> below_floor_;  // per cell: target below the observed open-valve floor
  double unload_filter_alpha_ = 1.0;
  std::vector<double> current_A_;
  std::vector<double> valve_gain_;      // calibrated per-valve yield gain
  std::vector<double> sensor_offset_;   // calibrated zero per sensor, the sensors' SI unit
  std::vector<double> sensor_reading_;  // this tick's readings less their zero
  std::vector<double> sent_A_;          // currents last sent
  std::unique_ptr<SensorFaultMonitor> sensor_faults_;
  SpscQueue<SensorFaultEvent> sensor_fault_events_{64};
  std::atomic<std::uint64_t> live_sensor_faults_{0};
  std::uint64_t telemetry_seen_ = 0;  // the session's telemetry count at the last tick
  std::uint64_t link_gaps_seen_ = 0;  // ...and its timeouts and reconnects
  bool watched_last_tick_ = false;    // false: a gap (halted, observer error) before this tick
  bool sensor_halt_ = false;          // a cell has no healthy sensor: no enable
  TimePoint last_send_{};
  bool ever_sent_ = false;
  std::atomic<unsigned char> pending_request_{0};
  std::atomic<bool> halted_{false};
  std::vector<double> truth_N_;
  std::vector<double> finger_m_;                 // the truth's finger this tick...
  std::vector<double> finger_prev_m_;            // ...and last tick
  std::vector<int> finger_still_ticks_;          // per cell: ticks the true finger has not moved
  std::vector<unsigned char> finger_retreated_;  // per cell: its last move was out
  static constexpr int kStillTicks = 5;          // still this long after a retreat: holding
  SlaveSample slave_{};
  bool fresh_sample_ = false;  // this tick consumed a new slave sample
  TimePoint fresh_arrival_{};
  static constexpr double kReferenceDepth_m = 4e-3;  // live stiffness is reported at this depth
  // A valve below this fraction of full current yields next to nothing: it counts as open.
  static constexpr double kOpenValveFraction = 0.02;
  std::unique_ptr<TissueEstimator> estimator_;
  TissueEstimate estimate_{};
  std::vector<TissueModel> cell_model_;            // per cell: the tissue mapped onto it
  std::vector<unsigned char> cell_mapped_;         // ...once the instrument has been over it
  std::vector<PassiveTissueUpdate> cell_law_;      // per cell: the law rendered, changed passively
  std::vector<PassivityObserver> cell_passivity_;  // per cell: energy at the rendered port
  std::vector<unsigned char> port_open_;           // ...while the finger is in the cell
  TimePoint start_{};
  bool started_ = false;
  BridgeStats stats_;
  std::atomic<std::uint64_t> live_ticks_{0};
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
  const std::size_t cells = layout_.fluid_cell_count();
  if (session.info().sensors != profile->sensors.size() || session.info().valves != layout_.valve_count() ||
      profile->rows != layout_.rows() || profile->cols != layout_.cols()) {
    throw InvalidArgument("device '" + profile->name + "' reports " + std::to_string(session.info().sensors) +
                          " sensors and " + std::to_string(session.info().valves) +
                          " valves, which its stored profile does not match: rewrite the device's profile");
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
  sensor_faults_ = std::make_unique<SensorFaultMonitor>(*profile, layout_, options_.sensor_faults);
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
  targets_.assign(cells, model::CellImpedanceTarget{});
  states_.assign(cells, model::CellState{});
  target_N_.assign(cells, 0.0);
  tissue_N_.assign(cells, 0.0);
  feedback_N_.assign(cells, 0.0);
  unloading_.assign(cells, 0);
  loading_.assign(cells, 0);
  below_floor_.assign(cells, 0);
  smooth_depth_m_.assign(cells, 0.0);
  unload_filter_alpha_ = 1.0 - std::exp(-1.0 / (options_.rate_hz * std::max(options_.unload_filter_s, 1e-9)));
  extreme_m_.assign(cells, 0.0);
  truth_N_.assign(cells, 0.0);
  estimator_ = std::make_unique<TissueEstimator>(options_.estimator);
  cell_model_.assign(cells, TissueModel{});
  cell_mapped_.assign(cells, 0);
  cell_law_.assign(cells, PassiveTissueUpdate{});
  cell_passivity_.assign(cells, PassivityObserver{options_.passivity_tolerance_J});
  port_open_.assign(cells, 0);
  if (!options_.mapping.valid()) {
    throw InvalidArgument("the workspace mapping needs finite numbers and cells_per_m > 0");
  }
  finger_m_.assign(cells, 0.0);
  finger_prev_m_.assign(cells, 0.0);
  finger_still_ticks_.assign(cells, 0);
  finger_retreated_.assign(cells, 0);
  current_A_.assign(layout_.valve_count(), 0.0);
  sent_A_.assign(layout_.valve_count(), 0.0);
}

Bridge::Impl::~Impl() { stop(); }

ResultCode Bridge::Impl::enable() noexcept { return session_.request_enable(); }

void Bridge::Impl::request(Request r) noexcept {
  auto wanted = static_cast<unsigned char>(r);
  unsigned char pending = pending_request_.load(std::memory_order_relaxed);
  while (wanted > pending &&
         !pending_request_.compare_exchange_weak(pending, wanted, std::memory_order_acq_rel)) {
  }
}

void Bridge::Impl::release(Request r) noexcept {
  std::fill(current_A_.begin(), current_A_.end(), 0.0);
  (void)session_.send_valve_currents(current_A_);  // released in this tick, whatever the state
  std::copy(current_A_.begin(), current_A_.end(), sent_A_.begin());
  (void)(r == Request::estop ? session_.request_estop() : session_.request_disable());
  std::fill(feedback_N_.begin(), feedback_N_.end(), 0.0);
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
    link_gaps_seen_ = gaps;
  }
  watched_last_tick_ = true;
  if (link.telemetry == telemetry_seen_) {
    return;
  }
  telemetry_seen_ = link.telemetry;
  const std::size_t k = sensor_faults_->update(sensor_reading_, observer_->sensor_residual_sigma());
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
  live_sensor_faults_.store(stats_.sensor_faults, std::memory_order_relaxed);
  if (e.unobservable_cell != SensorFaultMonitor::npos && !sensor_halt_) {
    sensor_halt_ = true;
    ++stats_.sensor_fault_halts;
    release(Request::disable);
  }
}

void Bridge::Impl::update_tissue_model(TimePoint now) noexcept {
  // Model-mediated rendering: the slave stream updates the online tissue estimate, and the cells
  // under the mapped contact point take it; the stale policy (hold, then fade to released) is the
  // estimator's.
  SlaveSample sample;
  if (source_.latest(now, sample) && sample.valid) {
    ++stats_.slave_samples;
    if (!slave_.valid || sample.stamp != slave_.stamp) {
      fresh_sample_ = true;  // its effect leaves with this tick's frame (latency figures)
      stats_.slave_force.add(sample.force_N);
      fresh_arrival_ = sample.received.count() != 0 ? sample.received : sample.stamp;
    }
    slave_ = sample;
    // Out-of-order, duplicate and malformed samples are refused and counted by the estimator.
    (void)estimator_->push(
        TissueSample{to_seconds(sample.stamp - start_), sample.force_N, sample.indentation_m});
    if (sample.ended) {
      estimator_->end_stream(to_seconds(now - start_));
    }
  }
  const bool was_fresh = estimate_.freshness == TissueFreshness::fresh;
  estimate_ = estimator_->estimate(to_seconds(now - start_));
  if (estimate_.freshness != TissueFreshness::fresh) {
    ++stats_.stale_ticks;
    stats_.stream_stalls += was_fresh ? 1 : 0;
  }
  if (estimate_.freshness == TissueFreshness::fresh && slave_.indentation_m > 0.0) {
    // The cells around the mapped contact point take the current estimate; the others keep
    // theirs (a map of the tissue as the instrument went over it).
    const CellPoint at =
        options_.mapping.to_cell(slave_.contact_x_m, slave_.contact_y_m, layout_.rows(), layout_.cols());
    const double reach = std::max(options_.footprint_cells, options_.mapping.to_cells(slave_.tip_radius_m));
    const auto& cells = layout_.fluid_cells();
    for (std::size_t i = 0; i < cells.size(); ++i) {
      const double dr = cells[i].row - at.row;
      const double dc = cells[i].col - at.col;
      if (dr * dr + dc * dc <= reach * reach) {
        cell_model_[i] = estimate_.model;  // fresh: scale 1
        cell_mapped_[i] = 1;
      }
    }
  }
  live_stiffness_.store(estimate_.model.tangent_stiffness_N_per_m(kReferenceDepth_m),
                        std::memory_order_relaxed);
}

double Bridge::Impl::direction_rate(std::size_t i, bool contact, double depth_m,
                                    double rate_m_per_s) noexcept {
  // Hysteresis in position, not in rate: the observer's rate noise (~0.5 mm/s RMS) must neither
  // release a held press nor re-hold a release that is under way. A cell unloads once its depth
  // has fallen retreat_m below its peak, and loads again once it has risen retreat_m above its
  // trough. Between the two, rates within the deadband count as holding.
  const double retreat_m = options_.unload_retreat_m;
  if (!contact) {
    loading_[i] = 0;
    unloading_[i] = 0;
    extreme_m_[i] = 0.0;
    smooth_depth_m_[i] = 0.0;
    return 0.0;
  }
  // On a smoothed depth: the fit's noise (2-3 um RMS, ~20 um peaks) shrinks well below retreat_m.
  smooth_depth_m_[i] += unload_filter_alpha_ * (depth_m - smooth_depth_m_[i]);
  depth_m = smooth_depth_m_[i];
  if (unloading_[i] == 0) {
    extreme_m_[i] = std::max(extreme_m_[i], depth_m);
    if (depth_m < extreme_m_[i] - retreat_m) {
      unloading_[i] = 1;
      extreme_m_[i] = depth_m;
    }
  } else {
    extreme_m_[i] = std::min(extreme_m_[i], depth_m);
    if (depth_m > extreme_m_[i] + retreat_m) {
      unloading_[i] = 0;
      extreme_m_[i] = depth_m;
    }
  }
  if (unloading_[i] != 0) {
    loading_[i] = 0;
    // Released: the inverse sees a retreating finger whatever the noise says.
    return std::min(rate_m_per_s, -options_.unload_rate_m_per_s);
  }
  // Loading starts above the deadband and lasts until the rate falls below load_exit_rate:
  // hysteresis in rate, so the noise at a press's smooth start does not flip the inverse between
  // loading and holding every few ticks (hand: 0.039 -> 0.032 N RMS, p95 14 -> 8.7 %).
  if (rate_m_per_s > options_.unload_rate_m_per_s ||
      (loading_[i] != 0 && rate_m_per_s > options_.load_exit_rate_m_per_s)) {
    loading_[i] = 1;
    return rate_m_per_s;
  }
  loading_[i] = 0;
  return 0.0;
}

void Bridge::Impl::compute_targets() noexcept {
  const double dt = 1.0 / options_.rate_hz;
  const std::span<const double> depth_m = observer_->indentation_m();
  const std::span<const double> rate_m_per_s = observer_->velocity_m_per_s();
  const std::span<const double> force_N = observer_->force_N();
  const std::span<const double> outflow = observer_->outflow_m3_per_s();  // empty: local force model
  const std::span<const model::CellSolution> last = inverse_->cells();
  const double valid_until_s = estimate_.valid_until_s;
  for (std::size_t i = 0; i < targets_.size(); ++i) {
    // A membrane sucked in after a release reads as depth with no force on it: no finger.
    const bool contact = depth_m[i] > options_.contact_threshold_m && force_N[i] > options_.contact_force_N;
    const double rate = direction_rate(i, contact, depth_m[i], rate_m_per_s[i]);
    states_[i].indentation_m = contact ? depth_m[i] : 0.0;
    states_[i].rate_m_per_s = contact ? rate : 0.0;
    const model::CellRole role = last[i].role;
    const bool loaded = contact && (role == model::CellRole::loading || role == model::CellRole::holding);
    // The cell's law: its mapped tissue (or the current estimate where the instrument never was),
    // scaled by the stale policy, changed passively while the finger is in the cell.
    const TissueModel wanted =
        cell_mapped_[i] != 0 ? cell_model_[i].scaled(estimate_.scale) : estimate_.model;
    PassiveTissueUpdate& law = cell_law_[i];
    if (contact || law.surface_offset_m() > 0.0 || law.tank_J() > 0.0) {
      law.update(wanted, states_[i].indentation_m);
    }
    // What the finger should feel (the feedback's shift is not part of it); clamped into the
    // envelope after the solve.
    tissue_N_[i] = std::min(law.force_N(states_[i].indentation_m, rate), options_.max_force_N);
    // The rendered port opens and closes at zero force and depth, so the energy of the first and
    // last contact threshold's worth of travel is counted both ways.
    if (contact || port_open_[i] != 0) {
      PassivityObserver& port = cell_passivity_[i];
      const double before_J = port.stats().energy_J;
      if (port_open_[i] == 0) {
        port.observe(0.0, 0.0);
      }
      port.observe(contact ? tissue_N_[i] : 0.0, contact ? states_[i].indentation_m : 0.0);
      port_open_[i] = contact ? 1 : 0;
      stats_.passivity_energy_J += port.stats().energy_J - before_J;
      stats_.passivity_min_energy_J = std::min(stats_.passivity_min_energy_J, port.stats().min_energy_J);
    }
    if (!loaded) {
      feedback_N_[i] = 0.0;
    } else {
      const double error_N = target_N_[i] - force_N[i];
      // Optionally frozen while holding: the force is then mostly the trapped volume's. Off by
      // default: the valves hold near their threshold and the integral still trims the slow leak
      // (demo: 0.016 N hold error with it, 0.032 N without, at 0.061 against 0.037 A peak).
      const bool sealed = i < outflow.size() && outflow[i] < options_.sealed_outflow_m3_per_s;
      const bool wound_up = (error_N > 0.0 && (last[i].clamped_high || sealed)) ||
                            (error_N < 0.0 && last[i].clamped_low) ||
                            (options_.freeze_feedback_while_holding && role == model::CellRole::holding);
      if (!wound_up) {
        feedback_N_[i] = std::clamp(feedback_N_[i] + options_.feedback_gain_per_s * dt * error_N,
                                    -options_.feedback_limit_N, options_.feedback_limit_N);
      }
    }
    model::CellImpedanceTarget& t = targets_[i];
    t = law.target(states_[i].indentation_m, options_.max_force_N, valid_until_s);
    // The correction enters as a shift of the tissue's surface: F(x - offset) ~ F(x) + feedback,
    // through the law's tangent stiffness at the state.
    const double tangent =
        law.model().tangent_stiffness_N_per_m(states_[i].indentation_m - law.surface_offset_m());
    if (tangent > 1.0) {
      t.surface_offset_m -= feedback_N_[i] / tangent;
    }
  }
}

void Bridge::Impl::lock_short_cells() noexcept {
  // Semi-active: a loaded cell that wants more than the quasi-static envelope allows (or more
  // than it has yet, below) gains nothing from open valves and loses fluid through them. Its valves hold at
  // least the threshold of the force it asked for (p = (F - F_membrane) / A_eff across the two passages of a
  // chamber), so no volume leaves before the finger has pushed the pressure there.
  const std::span<const model::CellSolution> cells = inverse_->cells();
  const std::span<const double> force_N = observer_->force_N();
  const model::ContactPatch& patch = model_->contact();
  const double per_passage_Pa_per_Pa = model_->valve_law().yield_pressure_Pa(1.0);
  for (std::size_t i = 0; i < cells.size(); ++i) {
    const model::CellSolution& c = cells[i];
    const bool holding = c.role == model::CellRole::holding;
    const bool loaded = holding || c.role == model::CellRole::loading;
    const double margin = holding ? options_.hold_margin : 0.0;
    // A loading cell whose observed force is still below its request: the inverse's feed-forward
    // expects the viscous force of a steady flow through open valves, but the network's
    // compliance is still filling, and open valves would let the finger's volume out before it
    // builds the pressure. Held at the request's threshold until the force gets there.
    const bool short_of_request =
        options_.lock_while_short && c.role == model::CellRole::loading && force_N[i] < c.requested_force_N;
    if (!loaded || !(c.clamped_high || margin > 0.0 || short_of_request)) {
      continue;
    }
    const model::Result<double> membrane_N = model::pad_membrane_force_N(patch, states_[i].indentation_m);
    if (!membrane_N.ok() || patch.effective_area_m2 <= 0.0) {
      continue;
    }
    const double pressure_Pa =
        ((1.0 + margin) * c.requested_force_N - membrane_N.value) / patch.effective_area_m2;
    const double yield_Pa = std::max(0.0, pressure_Pa) / (2.0 * per_passage_Pa_per_Pa);
    for (const std::size_t v : layout_.valves_of_cell(i)) {
      const model::Result<double> lock_A = inverse_->current_for_yield_stress_A(yield_Pa / valve_gain_[v]);
      const double current_A = lock_A.ok() ? lock_A.value : max_current_A_;
      current_A_[v] = std::max(current_A_[v], std::min(current_A, max_current_A_));
    }
  }
}

bool Bridge::Impl::valves_open(std::size_t cell) const noexcept {
  const double open_A = kOpenValveFraction * max_current_A_;
  return std::ranges::all_of(layout_.valves_of_cell(cell),
                             [&](std::size_t v) { return current_A_[v] <= open_A; });
}

void Bridge::Impl::clamp_targets_into_envelope() noexcept {
  // Scored against the role and envelope of this tick's solve: a cell that just turned to
  // holding is scored on its hold target, never on last tick's release.
  const std::span<const model::CellSolution> cells = inverse_->cells();
  const std::span<const double> force_N = observer_->force_N();
  for (std::size_t i = 0; i < target_N_.size(); ++i) {
    const model::CellSolution& c = cells[i];
    const bool loaded = c.role == model::CellRole::loading || c.role == model::CellRole::holding;
    double floor_N = c.force_min_N;
    if (loaded && valves_open(i)) {
      // With every valve of the cell open the device cannot render less than what the fluid
      // already pushes: the observer's network force, which knows the fluid's history (pressure
      // left by earlier flow, compliance still filling). The quasi-static floor does not: as a
      // press starts it is too high (hand: 0.20 N against 0.08 N true), later too low (0.60 against
      // 0.72 N). With it: every organ scene within 0.04 N RMS (docs/bridge.md).
      floor_N = force_N[i];
      below_floor_[i] = tissue_N_[i] < floor_N ? 1 : 0;
    } else {
      below_floor_[i] = 0;
    }
    target_N_[i] = loaded ? std::clamp(tissue_N_[i], floor_N, std::max(floor_N, c.force_max_N)) : 0.0;
  }
}

void Bridge::Impl::score() noexcept {
  const double dt = 1.0 / options_.rate_hz;
  const std::span<const model::CellSolution> cells = inverse_->cells();
  const std::span<const double> force_N = observer_->force_N();
  for (std::size_t i = 0; i < target_N_.size(); ++i) {
    const bool loaded =
        cells[i].role == model::CellRole::loading || cells[i].role == model::CellRole::holding;
    if (loaded) {
      ++stats_.target_cell_ticks;
      if (cells[i].clamped_low || cells[i].clamped_high || below_floor_[i] != 0) {
        ++stats_.clamped_cell_ticks;
      }
    }
  }
  // The ports' total (compute_targets integrates each cell's): below zero the rendering gave energy.
  if (stats_.passivity_energy_J < -options_.passivity_tolerance_J) {
    ++stats_.active_ticks;
  }
  if (truth_ == nullptr) {
    return;
  }
  truth_->true_forces(truth_N_);
  const bool finger_known = truth_->finger_indentation(finger_m_);
  // The finger holds when it moves out slower than this (scenes hold exactly still).
  constexpr double kHoldRate_m_per_s = 1e-6;
  for (std::size_t i = 0; i < truth_N_.size(); ++i) {
    const bool role_loaded =
        cells[i].role == model::CellRole::loading || cells[i].role == model::CellRole::holding;
    bool pressing = role_loaded;
    bool retreating = false;
    double finger_rate = 0.0;
    if (finger_known) {
      const bool touching = finger_m_[i] > options_.contact_threshold_m;
      finger_rate = (finger_m_[i] - finger_prev_m_[i]) / dt;
      // A finger still for one tick in the middle of a retreat is one whose script was not
      // advanced that tick (the daemon moves it from another thread, every ~1.1 ms): it holds
      // once it has been still for kStillTicks, not before (real time: the demo's score counted
      // those ticks as presses against a releasing cell, 0.08-0.09 N RMS).
      if (finger_rate < -kHoldRate_m_per_s) {
        finger_still_ticks_[i] = 0;
        finger_retreated_[i] = 1;
      } else if (finger_rate > kHoldRate_m_per_s) {
        finger_still_ticks_[i] = 0;
        finger_retreated_[i] = 0;
      } else if (finger_still_ticks_[i] < kStillTicks) {
        ++finger_still_ticks_[i];
      }
      const bool holding_still = finger_still_ticks_[i] >= kStillTicks || finger_retreated_[i] == 0;
      pressing = touching && finger_rate >= -kHoldRate_m_per_s && holding_still;
      retreating = touching && !pressing;
    }
    // A pressed cell the controller does not load is scored against the bare tissue law, except
    // that a released cell (in contact, valves open) cannot render less than what the fluid and
    // the membrane push: the envelope's floor, the observer's force, as for a loaded cell with
    // its valves open (tumour: a finger stopping on a cell it half left, 0.23 N against 0.05 N).
    double target_N = role_loaded ? target_N_[i] : std::clamp(tissue_N_[i], 0.0, options_.max_force_N);
    if (cells[i].role == model::CellRole::unloading && valves_open(i)) {
      target_N = std::max(target_N, std::min(force_N[i], options_.max_force_N));
    }
    const double e = truth_N_[i] - target_N;
    if (pressing) {
      stats_.force_sq_error_sum_N2 += e * e;
      stats_.force_max_abs_error_N = std::max(stats_.force_max_abs_error_N, std::abs(e));
      ++stats_.force_samples;
      if (target_N >= 0.3) {
        stats_.relative_error.add(e / target_N);
      }
      // The same law and envelope at the finger's true state (without it: the estimated one).
      double true_state_N = target_N;
      if (finger_known) {
        true_state_N = std::min(cell_law_[i].force_N(finger_m_[i], finger_rate), options_.max_force_N);
        if (role_loaded) {
          const double floor_N = valves_open(i) ? force_N[i] : cells[i].force_min_N;
          true_state_N = std::clamp(true_state_N, floor_N, std::max(floor_N, cells[i].force_max_N));
        } else if (cells[i].role == model::CellRole::unloading && valves_open(i)) {
          true_state_N = std::max(true_state_N, std::min(force_N[i], options_.max_force_N));
        }
      }
      const double e_true = truth_N_[i] - true_state_N;
      stats_.true_state_sq_error_sum_N2 += e_true * e_true;
      if (true_state_N >= 0.3) {
        stats_.true_state_relative_error.add(e_true / true_state_N);
      }
    } else if (retreating) {
      stats_.release_sq_error_sum_N2 += e * e;
      ++stats_.release_samples;
    }
  }
  if (finger_known) {
    std::copy(finger_m_.begin(), finger_m_.end(), finger_prev_m_.begin());
  }
  live_rms_N_.store(stats_.force_rms_error_N(), std::memory_order_relaxed);
}

ResultCode Bridge::Impl::step(TimePoint now) noexcept {
  const Clock& perf = perf_clock_ != nullptr ? *perf_clock_ : default_perf_clock_;
  const TimePoint t0 = perf.now();
  ResultCode rc = session_.poll(now);
  if (rc == ResultCode::disconnected) {
    return rc;
  }
  if (!started_) {
    start_ = now;
    started_ = true;
  }
  if (apply_request()) {
    watched_last_tick_ = false;
    ++stats_.ticks;  // halted: polled, nothing rendered
    live_ticks_.store(stats_.ticks, std::memory_order_relaxed);
    return rc;
  }
  const double dt = 1.0 / options_.rate_hz;
  const std::span<const double> raw = session_.sensors();
  const std::size_t readings = std::min(sensor_reading_.size(), raw.size());
  for (std::size_t k = 0; k < readings; ++k) {
    sensor_reading_[k] = raw[k] - sensor_offset_[k];
  }
  if (observer_->update(sensor_reading_, current_A_, dt) != model::Status::ok) {
    ++stats_.observer_errors;  // the estimate of the last good tick stands
    watched_last_tick_ = false;
  } else {
    watch_sensors(now);
    if (sensor_halt_) {
      ++stats_.ticks;
      live_ticks_.store(stats_.ticks, std::memory_order_relaxed);
      return rc;
    }
  }
  update_tissue_model(now);
  compute_targets();
  if (inverse_->solve(targets_, states_, to_seconds(now - start_)) == model::Status::ok) {
    const std::span<const double> currents = inverse_->currents_A();
    std::copy(currents.begin(), currents.end(), current_A_.begin());
    lock_short_cells();
    if (options_.compensate_hysteresis) {
      // The inverse maps yield to current on the anhysteretic curve; the steel's play keeps more
      // yield coming down and gives less going up. Over 9 scenes x seeds 1-8: 69 of 72 runs meet
      // both accuracy figures with this, 57 without (docs/bridge.md).
      for (std::size_t v = 0; v < current_A_.size(); ++v) {
        if (current_A_[v] > 0.0) {
          current_A_[v] =
              std::min(observer_->hysteresis_compensated_current_A(v, current_A_[v]), max_current_A_);
        }
      }
    }
    clamp_targets_into_envelope();
    stats_.inverse_residual_sum_N += inverse_->report().residual_norm_N;
    if (inverse_->report().from_cache) {
      ++stats_.inverse_cached;
    }
  } else {
    ++stats_.inverse_errors;  // the last good currents stand
  }
  // Unchanged currents are not sent again until the refresh period: a hold, or a skin nobody
  // touches, costs no bus traffic (the device's watchdog runs on the session's heartbeat).
  const bool changed = !std::equal(current_A_.begin(), current_A_.end(), sent_A_.begin());
  if (changed) {  // unchanged currents are the ones sent, counted when they changed
    for (const double a : current_A_) {
      stats_.max_current_A = std::max(stats_.max_current_A, a);
    }
  }
  const bool due = now - last_send_ >= from_seconds(options_.resend_period_s);
  ResultCode sent = ResultCode::ok;
  if (changed || due || !ever_sent_) {
    sent = session_.send_valve_currents(current_A_);
    if (sent == ResultCode::ok) {
      std::copy(current_A_.begin(), current_A_.end(), sent_A_.begin());
      last_send_ = now;
      ever_sent_ = true;
    }
  } else {
    ++stats_.unchanged_sends_skipped;
  }
  if (sent != ResultCode::ok) {
    ++stats_.send_failures;
    rc = rc == ResultCode::ok ? sent : rc;
  } else if (fresh_sample_) {
    const Duration processing = perf.now() - t0;
    stats_.processing_latency.add(processing.count());
    stats_.end_to_end_latency.add((now - fresh_arrival_ + processing).count());
  }
  fresh_sample_ = false;
  score();
  ++stats_.ticks;
  live_ticks_.store(stats_.ticks, std::memory_order_relaxed);
  const std::int64_t took_ns = (perf.now() - t0).count();
  stats_.tick_time.add(took_ns);
  if (static_cast<double>(took_ns) > 1e9 / options_.rate_hz) {
    ++stats_.overruns;
  }
  return rc;
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
}

BridgeTuning Bridge::Impl::tuning() const noexcept {
  BridgeTuning t;
  t.rate_hz = options_.rate_hz;
  t.feedback_gain_per_s = options_.feedback_gain_per_s;
  t.footprint_cells = options_.footprint_cells;
  t.resend_period_s = options_.resend_period_s;
  t.mapping = options_.mapping;
  t.stale_hold_s = estimator_->options().hold_s;
  t.stale_fade_s = estimator_->options().fade_s;
  t.realtime = options_.realtime;
  t.rt_priority = options_.rt_priority;
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
  estimator_->set_stale_policy(t.stale_hold_s, t.stale_fade_s);  // throws before anything changed
  if (t.rate_hz != options_.rate_hz || t.realtime != options_.realtime ||
      t.rt_priority != options_.rt_priority) {
    loop_.reset();  // the library's loop is made again at start() with the new rate
    loop_clock_ = nullptr;
  }
  apply_tuning(t, options_);
  // What the rate sets: the unloading latch's smoothing (the observer's filters take dt per tick).
  unload_filter_alpha_ = 1.0 - std::exp(-1.0 / (options_.rate_hz * std::max(options_.unload_filter_s, 1e-9)));
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
void Bridge::set_force_truth(const ForceTruth* truth) noexcept { impl_->set_force_truth(truth); }
ResultCode Bridge::enable() noexcept { return impl_->enable(); }
void Bridge::request(Request r) noexcept { impl_->request(r); }
bool Bridge::halted() const noexcept { return impl_->halted(); }
void Bridge::retune(const BridgeTuning& tuning) { impl_->retune(tuning); }
BridgeTuning Bridge::tuning() const noexcept { return impl_->tuning(); }
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
