#include "mrskin/bridge/bridge.hpp"

#include <algorithm>
#include <cmath>
#include <string>

namespace mrskin::bridge {

Bridge::Bridge(DeviceSession& session, SlaveSource& source, BridgeOptions options)
    : session_(session),
      source_(source),
      options_(options),
      layout_(session.info().rows, session.info().cols) {
  if (!(options_.rate_hz >= 1.0 && options_.rate_hz <= 20000.0)) {
    throw InvalidArgument("bridge rate " + std::to_string(options_.rate_hz) + " Hz is outside 1..20000 Hz");
  }
  const std::size_t cells = layout_.fluid_cell_count();
  if (session.info().sensors != cells) {
    throw InvalidArgument("device has " + std::to_string(session.info().sensors) + " sensors for " +
                          std::to_string(cells) +
                          " fluid cells; this bridge needs one displacement sensor per fluid cell "
                          "(the network observer for other sensor layouts is not built yet)");
  }
  if (session.info().valves != layout_.valve_count()) {
    throw InvalidArgument("device reports " + std::to_string(session.info().valves) + " valves but a " +
                          std::to_string(layout_.rows()) + " x " + std::to_string(layout_.cols()) +
                          " checkerboard has " + std::to_string(layout_.valve_count()));
  }
  indentation_m_.assign(cells, 0.0);
  previous_indentation_m_.assign(cells, 0.0);
  rate_m_per_s_.assign(cells, 0.0);
  target_N_.assign(cells, 0.0);
  demand_N_.assign(cells, 0.0);
  truth_N_.assign(cells, 0.0);
  contact_.assign(cells, 0);
  loading_.assign(cells, 0);
  current_A_.assign(layout_.valve_count(), 0.0);
  valve_yield_N_.assign(layout_.valve_count(), 0.0);
  residual_N_.assign(cells, 0.0);
}

Bridge::~Bridge() { stop(); }

ResultCode Bridge::enable() noexcept { return session_.request_enable(); }

void Bridge::compute_targets(TimePoint now) noexcept {
  const double dt = 1.0 / options_.rate_hz;
  // Online tissue model: secant stiffness of the slave's force-indentation stream.
  SlaveSample sample;
  if (source_.latest(now, sample) && sample.valid) {
    ++stats_.slave_samples;
    slave_ = sample;
    if (sample.indentation_m > 0.5e-3) {
      const double k_instant = sample.force_N / sample.indentation_m;
      const double alpha = dt / (options_.stiffness_filter_s + dt);
      stiffness_N_per_m_ += alpha * (k_instant - stiffness_N_per_m_);
    }
  }
  // Stale-data policy: hold the model, then fade it to the released state.
  const double age_s = slave_.valid ? to_seconds(now - slave_.stamp) : 1e9;
  if (age_s <= options_.stale_hold_s) {
    model_gain_ = 1.0;
  } else {
    ++stats_.stale_ticks;
    model_gain_ = std::clamp(1.0 - (age_s - options_.stale_hold_s) / options_.stale_fade_s, 0.0, 1.0);
  }
  const auto sensors = session_.sensors();
  const double k_m = options_.model.membrane_stiffness_N_per_m;
  const double k_c = options_.model.contact_stiffness_N_per_m;
  for (std::size_t i = 0; i < indentation_m_.size(); ++i) {
    const double x = sensors[i];
    // Filtered rate: raw differences of a noisy sensor at 1 kHz are mm/s of noise.
    const double v_raw = (x - previous_indentation_m_[i]) / dt;
    const double beta = dt / (options_.rate_filter_s + dt);
    rate_m_per_s_[i] += beta * (v_raw - rate_m_per_s_[i]);
    const double v = rate_m_per_s_[i];
    previous_indentation_m_[i] = x;
    indentation_m_[i] = x;
    contact_[i] = x > options_.contact_threshold_m ? 1 : 0;
    // Loading/holding vs unloading, with hysteresis.
    if (v < -options_.unload_rate_m_per_s) {
      loading_[i] = 0;
    } else if (v > options_.unload_rate_m_per_s || contact_[i] == 0) {
      loading_[i] = 1;
    }
    if (contact_[i] == 0) {
      target_N_[i] = 0.0;
      demand_N_[i] = 0.0;
      continue;
    }
    // Renderable envelope: valves open (membrane only) up to valves locked (contact
    // stiffness), and never above the device's range.
    const double f_min = k_m * x;
    const double f_max = std::min(options_.max_force_N, k_c * x);
    const double wanted = model_gain_ * (stiffness_N_per_m_ * x + damping_N_s_per_m_ * v);
    const double clamped = std::clamp(wanted, f_min, std::max(f_min, f_max));
    ++stats_.target_cell_ticks;
    if (clamped != wanted) {
      ++stats_.clamped_cell_ticks;
    }
    target_N_[i] = clamped;
    if (loading_[i] == 0) {
      // Unloading: a semi-active cell can only let go; release so the membrane returns.
      demand_N_[i] = 0.0;
      continue;
    }
    // Yield force the valves must hold: target minus the membrane's share.
    const double fluid_m = std::max(0.0, x - clamped / k_c);
    demand_N_[i] = std::max(0.0, clamped - k_m * fluid_m);
  }
  live_stiffness_.store(stiffness_N_per_m_, std::memory_order_relaxed);
}

void Bridge::allocate_currents() noexcept {
  // A cell's yield force is the mean of its valves' (shared with neighbours), so the 12
  // valves are one allocation: least squares over contacted cells with 0 <= f <= f_max,
  // solved by projected coordinate descent.
  const double max_A = session_.info().max_current_A;
  const double max_yield_N = placeholder_yield_force(options_.model, max_A, max_A);
  constexpr double kRidge = 1e-6;
  // Start from each valve carrying the mean demand of the cells it touches.
  for (std::size_t v = 0; v < valve_yield_N_.size(); ++v) {
    double sum = 0.0;
    int n = 0;
    for (const std::size_t c : layout_.cells_of_valve(v)) {
      if (contact_[c] != 0) {
        sum += demand_N_[c];
        ++n;
      }
    }
    valve_yield_N_[v] = n == 0 ? 0.0 : std::min(sum / n, max_yield_N);
  }
  for (std::size_t c = 0; c < residual_N_.size(); ++c) {
    residual_N_[c] = 0.0;
    if (contact_[c] == 0) {
      continue;
    }
    const auto& valves = layout_.valves_of_cell(c);
    double mean = 0.0;
    for (const std::size_t v : valves) {
      mean += valve_yield_N_[v];
    }
    residual_N_[c] = mean / static_cast<double>(valves.size()) - demand_N_[c];
  }
  for (int sweep = 0; sweep < options_.allocation_sweeps; ++sweep) {
    for (std::size_t v = 0; v < valve_yield_N_.size(); ++v) {
      double gradient = kRidge * valve_yield_N_[v];
      double curvature = kRidge;
      for (const std::size_t c : layout_.cells_of_valve(v)) {
        if (contact_[c] != 0) {
          const double w = 1.0 / static_cast<double>(layout_.valves_of_cell(c).size());
          gradient += w * residual_N_[c];
          curvature += w * w;
        }
      }
      const double updated = std::clamp(valve_yield_N_[v] - gradient / curvature, 0.0, max_yield_N);
      const double delta = updated - valve_yield_N_[v];
      if (delta == 0.0) {
        continue;
      }
      valve_yield_N_[v] = updated;
      for (const std::size_t c : layout_.cells_of_valve(v)) {
        if (contact_[c] != 0) {
          residual_N_[c] += delta / static_cast<double>(layout_.valves_of_cell(c).size());
        }
      }
    }
  }
  for (std::size_t v = 0; v < current_A_.size(); ++v) {
    bool touched = false;
    for (const std::size_t c : layout_.cells_of_valve(v)) {
      touched = touched || contact_[c] != 0;
    }
    if (!touched) {
      valve_yield_N_[v] = 0.0;  // nothing to resist: release
    }
    current_A_[v] = placeholder_current_for_yield(options_.model, valve_yield_N_[v], max_A);
  }
}

void Bridge::score() noexcept {
  if (truth_ == nullptr) {
    return;
  }
  truth_->true_forces(truth_N_);
  for (std::size_t i = 0; i < truth_N_.size(); ++i) {
    if (contact_[i] == 0 || loading_[i] == 0) {
      continue;
    }
    const double e = truth_N_[i] - target_N_[i];
    stats_.force_sq_error_sum_N2 += e * e;
    stats_.force_max_abs_error_N = std::max(stats_.force_max_abs_error_N, std::abs(e));
    ++stats_.force_samples;
  }
  live_rms_N_.store(stats_.force_rms_error_N(), std::memory_order_relaxed);
}

ResultCode Bridge::step(TimePoint now) noexcept {
  const Clock& perf = perf_clock_ != nullptr ? *perf_clock_ : default_perf_clock_;
  const TimePoint t0 = perf.now();
  ResultCode rc = session_.poll(now);
  if (rc == ResultCode::disconnected) {
    return rc;
  }
  compute_targets(now);
  allocate_currents();
  const ResultCode sent = session_.send_valve_currents(current_A_);
  if (sent != ResultCode::ok) {
    ++stats_.send_failures;
    rc = rc == ResultCode::ok ? sent : rc;
  }
  score();
  ++stats_.ticks;
  live_ticks_.store(stats_.ticks, std::memory_order_relaxed);
  const std::int64_t took_ns = (perf.now() - t0).count();
  stats_.tick_time.add(took_ns);
  if (static_cast<double>(took_ns) > 1e9 / options_.rate_hz) {
    ++stats_.overruns;
  }
  last_tick_ = now;
  have_last_tick_ = true;
  return rc;
}

void Bridge::start(Clock& clock) {
  if (running_.exchange(true)) {
    return;
  }
  thread_ = std::thread([this, &clock] {
    const Duration period = from_seconds(1.0 / options_.rate_hz);
    TimePoint next = clock.now();
    while (running_.load(std::memory_order_acquire)) {
      (void)step(clock.now());
      next += period;
      const TimePoint now = clock.now();
      if (now > next + period) {
        // Behind: skip the missed periods instead of bursting to catch up.
        const auto missed = (now - next) / period;
        stats_.skipped_periods += static_cast<std::uint64_t>(missed);
        next += missed * period;
      }
      clock.sleep_until(next);
    }
  });
}

void Bridge::stop() noexcept {
  if (running_.exchange(false) && thread_.joinable()) {
    thread_.join();
  }
}

}  // namespace mrskin::bridge
