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
  model_ = std::make_unique<model::DeviceModel>(*profile);
  observer_ = std::make_unique<model::CellObserver>(*model_, options_.observer);
  inverse_ = std::make_unique<model::CellInverse>(*model_, options_.inverse);
  targets_.assign(cells, model::CellImpedanceTarget{});
  states_.assign(cells, model::CellState{});
  target_N_.assign(cells, 0.0);
  tissue_N_.assign(cells, 0.0);
  feedback_N_.assign(cells, 0.0);
  truth_N_.assign(cells, 0.0);
  current_A_.assign(layout_.valve_count(), 0.0);
}

Bridge::~Bridge() { stop(); }

ResultCode Bridge::enable() noexcept { return session_.request_enable(); }

void Bridge::update_tissue_model(TimePoint now) noexcept {
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
  live_stiffness_.store(stiffness_N_per_m_, std::memory_order_relaxed);
}

void Bridge::compute_targets() noexcept {
  const double dt = 1.0 / options_.rate_hz;
  const std::span<const double> depth_m = observer_->indentation_m();
  const std::span<const double> rate_m_per_s = observer_->velocity_m_per_s();
  const std::span<const double> force_N = observer_->force_N();
  const std::span<const model::CellSolution> last = inverse_->cells();
  // A target stays valid until the stale policy would have faded it out.
  const double valid_until_s =
      slave_.valid ? to_seconds(slave_.stamp - start_) + options_.stale_hold_s + options_.stale_fade_s : 0.0;
  const double stiffness = model_gain_ * stiffness_N_per_m_;
  for (std::size_t i = 0; i < targets_.size(); ++i) {
    // A membrane sucked in after a release reads as depth with no force on it: no finger.
    const bool contact = depth_m[i] > options_.contact_threshold_m && force_N[i] > options_.contact_force_N;
    double rate = rate_m_per_s[i];
    if (std::abs(rate) < options_.unload_rate_m_per_s) {
      rate = 0.0;  // holding: the observer's rate noise must not release a held press
    }
    states_[i].indentation_m = contact ? depth_m[i] : 0.0;
    states_[i].rate_m_per_s = contact ? rate : 0.0;
    const model::CellRole role = last[i].role;
    const bool loaded = contact && (role == model::CellRole::loading || role == model::CellRole::holding);
    // What the finger should feel: the tissue law at the state (the feedback's shift is not part
    // of it); clamped into the envelope after the solve.
    tissue_N_[i] = std::min(stiffness * states_[i].indentation_m + model_gain_ * damping_N_s_per_m_ * rate,
                            options_.max_force_N);
    if (!loaded) {
      feedback_N_[i] = 0.0;
    } else {
      const double error_N = target_N_[i] - force_N[i];
      const bool wound_up = (error_N > 0.0 && last[i].clamped_high) || (error_N < 0.0 && last[i].clamped_low);
      if (!wound_up) {
        feedback_N_[i] = std::clamp(feedback_N_[i] + options_.feedback_gain_per_s * dt * error_N,
                                    -options_.feedback_limit_N, options_.feedback_limit_N);
      }
    }
    model::CellImpedanceTarget& t = targets_[i];
    t.stiffness_N_per_m = stiffness;
    t.damping_N_s_per_m = model_gain_ * damping_N_s_per_m_;
    // The correction enters as a shift of the tissue's surface: k (x - offset) = k x + feedback.
    t.surface_offset_m = stiffness > 1.0 ? -feedback_N_[i] / stiffness : 0.0;
    t.force_ceiling_N = options_.max_force_N;
    t.valid_until_s = valid_until_s;
  }
}

void Bridge::lock_short_cells() noexcept {
  // Semi-active: a loaded cell that wants more than the quasi-static envelope allows gains
  // nothing from open valves and loses fluid through them. Its valves hold at least the
  // threshold of the force it asked for (p = (F - F_membrane) / A_eff across the two passages
  // of a chamber), so no volume leaves before the finger has pushed the pressure there.
  const std::span<const model::CellSolution> cells = inverse_->cells();
  const model::ContactPatch& patch = model_->contact();
  const double per_passage_Pa_per_Pa = model_->valve_law().yield_pressure_Pa(1.0);
  for (std::size_t i = 0; i < cells.size(); ++i) {
    const model::CellSolution& c = cells[i];
    const bool loaded = c.role == model::CellRole::loading || c.role == model::CellRole::holding;
    if (!loaded || !c.clamped_high) {
      continue;
    }
    const model::Result<double> membrane_N = model::pad_membrane_force_N(patch, states_[i].indentation_m);
    if (!membrane_N.ok() || patch.effective_area_m2 <= 0.0) {
      continue;
    }
    const double pressure_Pa = (c.requested_force_N - membrane_N.value) / patch.effective_area_m2;
    const double yield_Pa = std::max(0.0, pressure_Pa) / (2.0 * per_passage_Pa_per_Pa);
    const model::Result<double> lock_A = inverse_->current_for_yield_stress_A(yield_Pa);
    const double current_A = lock_A.ok() ? lock_A.value : session_.info().max_current_A;
    for (const std::size_t v : layout_.valves_of_cell(i)) {
      current_A_[v] = std::max(current_A_[v], std::min(current_A, session_.info().max_current_A));
    }
  }
}

void Bridge::clamp_targets_into_envelope() noexcept {
  // Scored against the role and envelope of this tick's solve: a cell that just turned to
  // holding is scored on its hold target, never on last tick's release.
  const std::span<const model::CellSolution> cells = inverse_->cells();
  for (std::size_t i = 0; i < target_N_.size(); ++i) {
    const model::CellSolution& c = cells[i];
    const bool loaded = c.role == model::CellRole::loading || c.role == model::CellRole::holding;
    target_N_[i] =
        loaded ? std::clamp(tissue_N_[i], c.force_min_N, std::max(c.force_min_N, c.force_max_N)) : 0.0;
  }
}

void Bridge::score() noexcept {
  const std::span<const model::CellSolution> cells = inverse_->cells();
  for (std::size_t i = 0; i < target_N_.size(); ++i) {
    const bool loaded =
        cells[i].role == model::CellRole::loading || cells[i].role == model::CellRole::holding;
    if (loaded) {
      ++stats_.target_cell_ticks;
      if (cells[i].clamped_low || cells[i].clamped_high) {
        ++stats_.clamped_cell_ticks;
      }
    }
  }
  if (truth_ == nullptr) {
    return;
  }
  truth_->true_forces(truth_N_);
  for (std::size_t i = 0; i < truth_N_.size(); ++i) {
    const model::CellRole role = cells[i].role;
    if (role != model::CellRole::loading && role != model::CellRole::holding) {
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
  if (!started_) {
    start_ = now;
    started_ = true;
  }
  const double dt = 1.0 / options_.rate_hz;
  if (observer_->update(session_.sensors(), current_A_, dt) != model::Status::ok) {
    ++stats_.observer_errors;  // the estimate of the last good tick stands
  }
  update_tissue_model(now);
  compute_targets();
  if (inverse_->solve(targets_, states_, to_seconds(now - start_)) == model::Status::ok) {
    const std::span<const double> currents = inverse_->currents_A();
    std::copy(currents.begin(), currents.end(), current_A_.begin());
    lock_short_cells();
    clamp_targets_into_envelope();
    stats_.inverse_residual_sum_N += inverse_->report().residual_norm_N;
    if (inverse_->report().from_cache) {
      ++stats_.inverse_cached;
    }
  } else {
    ++stats_.inverse_errors;  // the last good currents stand
  }
  for (const double a : current_A_) {
    stats_.max_current_A = std::max(stats_.max_current_A, a);
  }
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
