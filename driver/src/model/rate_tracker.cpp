#include "rate_tracker.hpp"

#include <algorithm>
#include <cmath>

namespace mrskin::model {

RateTracker::RateTracker(std::size_t cells, const RateTrackerOptions& options)
    : options_(options), lines_(cells), sigma_inv_(cells, 1.0), ring_(cells * kHistory, 0.0) {}

void RateTracker::reset() noexcept {
  std::fill(lines_.begin(), lines_.end(), Line{});
  changes_ = 0;
}

void RateTracker::set_depth_sigma(std::size_t cell, double sigma_m) noexcept {
  if (cell < sigma_inv_.size() && sigma_m > 0.0 && std::isfinite(sigma_m)) {
    sigma_inv_[cell] = 1.0 / sigma_m;
  }
}

// The segment rebuilt from the `samples` depths before this tick's (weights mu^k at tau = -k dt).
void RateTracker::restart(Line& line, std::size_t cell, std::uint32_t samples, double dt_s) noexcept {
  line.w = line.t = line.tt = line.d = line.td = 0.0;
  double weight = 1.0;
  const double* ring = &ring_[cell * kHistory];
  for (std::uint32_t k = 1; k <= samples; ++k) {
    weight *= mu_;
    const double tau = -static_cast<double>(k) * dt_s;
    const double depth = ring[(head_ + kHistory - k) % kHistory];
    line.w += weight;
    line.t += weight * tau;
    line.tt += weight * tau * tau;
    line.d += weight * depth;
    line.td += weight * tau * depth;
  }
  line.up = line.down = 0.0;
  line.up_run = line.down_run = 0;
}

void RateTracker::add(Line& line, double depth_m) noexcept {
  line.w += 1.0;  // tau = 0: t, tt and td are unchanged
  line.d += depth_m;
}

void RateTracker::update(std::span<const double> depth_m, std::span<const double> previous_m, double dt_s,
                         std::span<double> rate_m_per_s) noexcept {
  if (dt_s != cached_dt_s_) {
    const double tau = options_.filter_time_constant_s;
    alpha_ = tau > 0.0 ? 1.0 - std::exp(-dt_s / tau) : 1.0;
    mu_ = std::exp(-dt_s / options_.memory_s);
    // A first-order filter on differences of independent depths (variance s^2 each): its rate's
    // variance is s^2 (2 / dt^2) alpha / (2 - alpha).
    fast_var_ = 2.0 / (dt_s * dt_s) * alpha_ / (2.0 - alpha_);
    cached_dt_s_ = dt_s;
  }
  head_ = (head_ + 1) % kHistory;
  const double h = options_.change_threshold_sigma;
  const double k = options_.change_slack_sigma;
  const std::size_t cells = std::min({lines_.size(), depth_m.size(), previous_m.size(), rate_m_per_s.size()});
  for (std::size_t c = 0; c < cells; ++c) {
    Line& line = lines_[c];
    const double d = depth_m[c];
    const double p = previous_m[c];
    const double predicted_by_filter = p + line.filtered * dt_s;
    line.filtered += alpha_ * ((d - p) / dt_s - line.filtered);
    if (d == 0.0 && p == 0.0) {
      // Untouched: nothing to track (the filter decays on its own).
      line.at_rest = true;
      line.history = 0;
      rate_m_per_s[c] = line.filtered;
      continue;
    }
    double* ring = &ring_[c * kHistory];
    if (line.at_rest) {
      // Leaving rest is a change: the segment starts at the last zero.
      line.at_rest = false;
      ring[(head_ + kHistory - 1) % kHistory] = p;
      restart(line, c, 1, dt_s);
      line.history = 1;
    } else {
      // Move the time origin to this sample.
      line.tt += -2.0 * dt_s * line.t + line.w * dt_s * dt_s;
      line.td -= dt_s * line.d;
      line.t -= line.w * dt_s;
      double predicted = predicted_by_filter;
      const double sxx = line.w > 1.5 ? line.tt - line.t * line.t / line.w : 0.0;
      if (sxx > 0.0) {
        const double slope = (line.td - line.t * line.d / line.w) / sxx;
        predicted = (line.d - slope * line.t) / line.w;
      }
      const double e = (d - predicted) * sigma_inv_[c];
      line.up = std::max(0.0, line.up + e - k);
      line.down = std::max(0.0, line.down - e - k);
      line.up_run = line.up > 0.0 ? line.up_run + 1 : 0;
      line.down_run = line.down > 0.0 ? line.down_run + 1 : 0;
      if (line.up > h || line.down > h) {
        // The segment restarts where the statistic last left zero (this sample is added below).
        const std::uint32_t run = line.up > h ? line.up_run : line.down_run;
        const std::uint32_t before = std::min(std::max<std::uint32_t>(run, 2) - 1, line.history);
        ++changes_;
        restart(line, c, before, dt_s);
      } else {
        line.w *= mu_;
        line.t *= mu_;
        line.tt *= mu_;
        line.d *= mu_;
        line.td *= mu_;
      }
    }
    add(line, d);
    ring[head_] = d;
    line.history = std::min<std::uint32_t>(line.history + 1, kHistory);
    // Inverse-variance blend: the line's slope has variance s^2 / sxx, the filter's s^2 fast_var_.
    const double sxx = line.tt - line.t * line.t / line.w;
    if (line.w > 1.5 && sxx > 0.0) {
      const double slope = (line.td - line.t * line.d / line.w) / sxx;
      const double fast_weight = 1.0 / fast_var_;
      rate_m_per_s[c] = (slope * sxx + line.filtered * fast_weight) / (sxx + fast_weight);
    } else {
      rate_m_per_s[c] = line.filtered;
    }
  }
}

}  // namespace mrskin::model
