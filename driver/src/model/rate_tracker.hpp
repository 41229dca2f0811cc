// Per-cell indentation rate from the observer's fitted depths: a line through the depths since
// the last detected change in rate, blended with a first-order filter on the difference.
//
// Why: the finger's rate is piecewise smooth (a press at a steady speed, a hold), and the
// fitted depth carries 2-5 um of noise. Differencing it at 1 kHz and filtering over 4 ms leaves
// about +-1.5 mm/s of rate noise; a longer filter lags every start and stop. A line fitted over
// the samples since the rate last changed has far less noise on a steady press (its variance
// falls as 1 / N^3) and no lag from before the change. The change is found by a two-sided CUSUM
// on the line's one-step prediction error, in units of the cell's depth noise; the segment then
// restarts at the sample where the CUSUM last left zero. The line's memory is bounded (an
// exponential weight, memory_s) so a smooth acceleration is followed too. The output is the
// line's slope and the filter's rate weighted by their inverse variances: right after a change
// the line has few samples and the filter carries the estimate.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

namespace mrskin::model {

struct RateTrackerOptions {
  double filter_time_constant_s = 4e-3;  // the first-order filter on the difference
  double memory_s = 0.02;                // the line's exponential memory
  double change_threshold_sigma = 5.0;   // CUSUM decision threshold h
  double change_slack_sigma = 0.5;       // CUSUM reference value k
};

class RateTracker {
 public:
  RateTracker(std::size_t cells, const RateTrackerOptions& options);

  void reset() noexcept;
  // A cell's depth noise (m, > 0; 1 m until set): the unit of the prediction errors.
  void set_depth_sigma(std::size_t cell, double sigma_m) noexcept;
  // One tick: the fitted depths now and a tick ago; writes each cell's rate (m/s).
  void update(std::span<const double> depth_m, std::span<const double> previous_m, double dt_s,
              std::span<double> rate_m_per_s) noexcept;
  // Changes detected since reset (all cells), for tests and tuning.
  [[nodiscard]] std::uint64_t changes_detected() const noexcept { return changes_; }

 private:
  static constexpr std::size_t kHistory = 16;  // depths kept per cell for a restart
  struct Line {
    // Weighted sums over the segment, time measured from the latest sample (tau <= 0).
    double w = 0.0;
    double t = 0.0;
    double tt = 0.0;
    double d = 0.0;
    double td = 0.0;
    double filtered = 0.0;  // the first-order filter's rate, m/s
    double up = 0.0;        // CUSUM statistics, sigmas
    double down = 0.0;
    std::uint32_t up_run = 0;  // samples since each statistic was last zero
    std::uint32_t down_run = 0;
    std::uint32_t history = 0;  // valid depths in the ring (at most kHistory)
    bool at_rest = true;        // zero depth now and a tick ago: nothing to track
  };
  void restart(Line& line, std::size_t cell, std::uint32_t samples, double dt_s) noexcept;
  static void add(Line& line, double depth_m) noexcept;

  RateTrackerOptions options_;
  std::vector<Line> lines_;
  std::vector<double> sigma_inv_;  // per cell, 1 / m
  std::vector<double> ring_;       // kHistory depths per cell, newest at head_
  std::size_t head_ = 0;
  double cached_dt_s_ = -1.0;
  double alpha_ = 1.0;     // filter gain per tick
  double mu_ = 0.0;        // line's weight decay per tick
  double fast_var_ = 0.0;  // the filter's rate variance per unit depth variance, 1/s^2
  std::uint64_t changes_ = 0;
};

}  // namespace mrskin::model
