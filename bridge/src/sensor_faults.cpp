#include "mrskin/bridge/sensor_faults.hpp"

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>
#include <memory>
#include <vector>

#include "mrskin/driver/errors.hpp"

namespace mrskin::bridge {

const char* to_string(SensorFault fault) noexcept {
  switch (fault) {
    case SensorFault::none:
      return "none";
    case SensorFault::stuck:
      return "stuck";
    case SensorFault::noisy:
      return "noisy";
    case SensorFault::offset:
      return "offset";
  }
  return "unknown";
}

namespace {

constexpr double kOutlierCap = 4.0;

// The run of equal readings a healthy sensor reaches with probability p: with the true value at
// a quantisation step's centre (the likeliest place to repeat), each reading stays in that step
// with probability erf(resolution / (2 sqrt(2) sigma)).
std::size_t stuck_run_for(double noise_std, double resolution, double p) {
  if (!(noise_std > 0.0)) {
    return SensorFaultMonitor::npos;  // no noise: a constant reading is what a healthy one gives
  }
  const double step = resolution > 0.0 ? resolution : noise_std * 1e-6;  // unquantised: never equal
  const double stay = std::erf(step / (2.0 * std::sqrt(2.0) * noise_std));
  if (!(stay > 0.0)) {
    return 2;
  }
  const double run = std::ceil(std::log(p) / std::log(stay)) + 1.0;
  return run > 1e6 ? SensorFaultMonitor::npos : static_cast<std::size_t>(std::max(run, 2.0));
}

// The second difference's weights on the readings before last, last and now: (1, -2, 1) for evenly
// spaced readings; for spacings h1 (before to last) and h2 (last to now), the combination that a
// reading moving at a constant rate leaves at zero, (h2, -(h1 + h2), h1), scaled so that white
// noise of sigma gives it the same mean square, 6 sigma^2, whatever the spacing.
struct SecondDifference {
  double before = 1.0;
  double last = -2.0;
  double now = 1.0;
};

SecondDifference second_difference(std::uint32_t before_to_last_us, std::uint32_t last_to_now_us) noexcept {
  const double h1 = before_to_last_us;
  const double h2 = last_to_now_us;
  const double scale = std::sqrt(6.0 / (h2 * h2 + (h1 + h2) * (h1 + h2) + h1 * h1));
  return {h2 * scale, -(h1 + h2) * scale, h1 * scale};
}

struct LeanLimits {
  double ratio_cap;   // a reading's noise ratio counts for at most this
  double offset_cap;  // a residual counts for at most this, sigmas
  double noise_limit;
  double offset_limit;
};

// SensorFaultMonitor::Impl::update_lean's pass over every sensor at once (the sensors not
// judged have masks that keep their figures and raise nothing), without a branch: for a judged
// sensor the same arithmetic as the full pass. A function of its own so that its arrays are
// restrict parameters (g++ ignores restrict on local pointers, and checked 13 arrays for overlap
// instead of vectorising). Written as selects between doubles, choosing as std::min and
// std::clamp do: g++ 12 vectorises those on SSE2, not a bool turned into an integer; the alarm is
// OR-ed from the flags' bits. True when some test is past its limit. kEven: the readings evenly
// spaced, w is (1, -2, 1) (the common case, with two multiplications a sensor fewer).
template <bool kEven>
bool lean_pass(std::size_t n, const double* __restrict y, const double* __restrict r, double* __restrict last,
               double* __restrict before, double* __restrict run, double* __restrict noise,
               double* __restrict mean, const double* __restrict band, const double* __restrict inv6,
               const double* __restrict noise_alpha, const double* __restrict offset_alpha,
               const double* __restrict weight, const double* __restrict stuck, LeanLimits limits,
               SecondDifference w, double has_last, double noise_on) noexcept {
  std::uint64_t alarm = 0;
  for (std::size_t k = 0; k < n; ++k) {
    const double unexplained =
        std::abs(r[k]) > band[k] + SensorFaultMonitor::kDeadbandMarginSigma ? 1.0 : 0.0;
    const double counts = band[k] == 0.0 ? 1.0 : unexplained;  // a repeat the band does not explain
    const double same = y[k] == last[k] ? has_last : 0.0;
    run[k] = 1.0 + same * (run[k] + counts - 1.0);  // a repeat: run + counts; else 1
    const double d2 =
        kEven ? y[k] - 2.0 * last[k] + before[k] : w.now * y[k] + w.last * last[k] + w.before * before[k];
    const double ratio = d2 * d2 * inv6[k];
    noise[k] +=
        noise_alpha[k] * noise_on * ((limits.ratio_cap < ratio ? limits.ratio_cap : ratio) - noise[k]);
    before[k] = last[k];
    last[k] = y[k];
    const double above_floor = r[k] < -limits.offset_cap ? -limits.offset_cap : r[k];
    const double clamped = limits.offset_cap < above_floor ? limits.offset_cap : above_floor;
    mean[k] += offset_alpha[k] * (clamped - mean[k]);
    const double stuck_flag = run[k] >= stuck[k] ? 1.0 : 0.0;
    const double noisy_flag = weight[k] * noise[k] > limits.noise_limit ? 1.0 : 0.0;
    const double offset_flag = weight[k] * std::abs(mean[k]) > limits.offset_limit ? 1.0 : 0.0;
    alarm |= std::bit_cast<std::uint64_t>(stuck_flag + noisy_flag + offset_flag);
  }
  return alarm != 0;
}

}  // namespace

// The monitor's state, behind SensorFaultMonitor's one pointer (docs/api.md, "ABI").
class __attribute__((visibility("hidden"))) SensorFaultMonitor::Impl {
 public:
  Impl(const model::DeviceProfile& profile, const GridLayout& layout, const SensorFaultOptions& options,
       double reading_deadband);

  std::size_t update(std::span<const double> readings, std::span<const double> residual_sigma,
                     const std::uint32_t* device_time_us) noexcept;
  void reset() noexcept;
  void restart_history() noexcept;
  // Room for every watched sensor in judged_, so reset() never allocates (a copy's vector has
  // only its size reserved). Setup only: may throw std::bad_alloc.
  void reserve_judged() {
    judged_.reserve(static_cast<std::size_t>(std::count(watched_.begin(), watched_.end(), 1)));
  }
  void set_reading_deadband(double reading_deadband) noexcept {
    const double band = std::isfinite(reading_deadband) ? std::max(0.0, reading_deadband) : 0.0;
    for (std::size_t k = 0; k < deadband_sigma_.size(); ++k) {
      deadband_sigma_[k] = residual_sigma_[k] > 0.0 ? band / residual_sigma_[k] : 0.0;
    }
  }
  [[nodiscard]] SensorFault fault(std::size_t sensor) const noexcept {
    return sensor < fault_.size() ? fault_[sensor] : SensorFault::none;
  }
  [[nodiscard]] std::size_t faulty_count() const noexcept { return faulty_; }
  [[nodiscard]] std::size_t healthy_count() const noexcept { return healthy_; }
  [[nodiscard]] std::size_t unobservable_cell() const noexcept { return unobservable_; }
  [[nodiscard]] std::span<const std::size_t> cells_of_sensor(std::size_t sensor) const noexcept;
  [[nodiscard]] std::size_t stuck_run_readings(std::size_t sensor) const noexcept {
    return sensor < stuck_run_.size() ? stuck_run_[sensor] : npos;
  }
  [[nodiscard]] double noise_ratio(std::size_t sensor) const noexcept {
    return sensor < noise_ratio_.size() ? noise_ratio_[sensor] : 0.0;
  }
  [[nodiscard]] double mean_residual_sigma(std::size_t sensor) const noexcept {
    return sensor < mean_residual_.size() ? mean_residual_[sensor] : 0.0;
  }
  [[nodiscard]] double evidence(std::size_t sensor) const noexcept {
    return sensor < evidence_.size() ? evidence_[sensor] : 0.0;
  }

 private:
  void latch(std::size_t sensor, SensorFault fault, double evidence) noexcept;
  void find_neighbours();
  [[nodiscard]] std::size_t blame_offset(double worst_offset) const noexcept;
  void judge_every_watched_sensor() noexcept;

  SensorFaultOptions options_;
  std::vector<unsigned char> watched_;  // displacement sensors
  std::vector<std::uint32_t> judged_;   // the watched sensors not latched, ascending: update's walk
  std::vector<double> residual_sigma_;  // the observer's sigma for the residual (its definition)
  std::vector<std::size_t> cells_begin_;
  std::vector<std::size_t> cells_;
  std::vector<std::size_t> readers_of_cell_;  // healthy displacement sensors reading each cell
  // Per watched sensor, the other watched sensors that read one of its cells (offset blame).
  std::vector<std::size_t> neighbours_begin_;
  std::vector<std::uint32_t> neighbours_;
  std::vector<SensorFault> fault_;
  std::vector<double> evidence_;
  // Per sensor, what update() reads and writes for every reading, an array each (the lean pass
  // runs down them together): the reading's history, the tests' running figures and constants.
  std::vector<double> last_;
  std::vector<double> before_last_;
  std::vector<double> noise_ratio_;
  std::vector<double> mean_residual_;
  std::vector<double> inv_six_sigma2_;  // 1 / (6 sigma^2): white noise's mean squared 2nd difference
  std::vector<double> deadband_sigma_;  // the unit's deadband in residual_sigma_ (0: none)
  std::vector<double> run_;             // equal readings in a row (a count; exact in a double)
  std::vector<std::size_t> stuck_run_;  // npos: never stuck (not watched, or no noise)
  // Readings in a row so far (up to 2: the second difference needs 3); a reading that was not
  // finite starts it again (its sensor's history then spans other times than the others').
  std::vector<double> seen_;
  // The unit's clock at the last two readings, for the second difference's spacing: a host that
  // wakes late reads the newest of several readings (SecondDifference).
  std::uint32_t time_last_us_ = 0;
  std::uint32_t time_before_us_ = 0;
  unsigned times_seen_ = 0;    // readings with a time in a row, up to 2
  bool evenly_spaced_ = true;  // this reading and the two before it (else spacing_ weighs them)
  SecondDifference spacing_;
  // The lean pass's masks. A judged sensor: its windows' weights, 1, its stuck run; any other:
  // 0, 0, 0 and infinity, so that its figures stand and raise nothing.
  std::vector<double> noise_alpha_;
  std::vector<double> offset_alpha_;
  std::vector<double> judged_weight_;
  std::vector<double> stuck_limit_;
  void set_judged(std::size_t k, bool judged) noexcept {
    noise_alpha_[k] = judged ? 1.0 / options_.noise_window_readings : 0.0;
    offset_alpha_[k] = judged ? 1.0 / options_.offset_window_readings : 0.0;
    judged_weight_[k] = judged ? 1.0 : 0.0;
    stuck_limit_[k] = judged && stuck_run_[k] != npos ? static_cast<double>(stuck_run_[k])
                                                      : std::numeric_limits<double>::infinity();
  }
  void restart_watch() noexcept {
    std::fill(seen_.begin(), seen_.end(), 0.0);
    times_seen_ = 0;
    lean_ = Lean::fresh;
    std::fill(run_.begin(), run_.end(), 0.0);
    std::fill(noise_ratio_.begin(), noise_ratio_.end(), 0.0);
    std::fill(mean_residual_.begin(), mean_residual_.end(), 0.0);
  }
  [[nodiscard]] static bool all_finite(std::span<const double> readings,
                                       std::span<const double> residual_sigma) noexcept;
  [[nodiscard]] bool update_scalar(std::span<const double> readings,
                                   std::span<const double> residual_sigma) noexcept;
  // Where the judged sensors' histories stand, for the lean pass: all alike, with no reading yet
  // (no repeat to count), with one (no noise test: its second difference needs three), with two
  // or more (primed); or not alike, after a reading that was not finite (the full pass).
  enum class Lean : unsigned char { mixed, fresh, one_reading, primed };
  Lean lean_ = Lean::fresh;
  [[nodiscard]] bool update_lean(std::span<const double> readings,
                                 std::span<const double> residual_sigma) noexcept;
  [[nodiscard]] std::size_t decide(std::span<const double> readings) noexcept;
  std::size_t faulty_ = 0;
  std::size_t healthy_ = 0;
  std::size_t unobservable_ = npos;
};

SensorFaultMonitor::Impl::Impl(const model::DeviceProfile& profile, const GridLayout& layout,
                               const SensorFaultOptions& options, double reading_deadband)
    : options_(options) {
  if (!(reading_deadband >= 0.0) || !std::isfinite(reading_deadband)) {
    throw InvalidArgument("sensor fault monitor: the sensor deadband must be finite and >= 0 (0: none)");
  }
  if (!(options.false_alarm_probability > 0.0 && options.false_alarm_probability < 1.0) ||
      !(options.noise_ratio_limit > 1.0) || !(options.noise_window_readings >= 1.0) ||
      !(options.offset_limit_sigma > 0.0) || !(options.offset_window_readings >= 1.0)) {
    throw InvalidArgument(
        "sensor fault options: false_alarm_probability in (0, 1), noise_ratio_limit > 1, "
        "offset_limit_sigma > 0, and both windows >= 1 reading");
  }
  const std::size_t n = profile.sensors.size();
  const std::size_t cells = layout.fluid_cell_count();
  watched_.assign(n, 0);
  for (std::vector<double>* a :
       {&last_, &before_last_, &noise_ratio_, &mean_residual_, &inv_six_sigma2_, &deadband_sigma_, &run_,
        &noise_alpha_, &offset_alpha_, &judged_weight_, &stuck_limit_}) {
    a->assign(n, 0.0);
  }
  stuck_run_.assign(n, npos);
  seen_.assign(n, 0.0);
  residual_sigma_.assign(n, 0.0);
  readers_of_cell_.assign(cells, 0);
  cells_begin_.push_back(0);
  for (std::size_t k = 0; k < n; ++k) {
    const model::SensorSpec& s = profile.sensors[k];
    if (s.quantity == model::SensorQuantity::displacement && s.place != model::PlaceKind::reservoir) {
      watched_[k] = 1;
      const double sigma2 = s.noise_std * s.noise_std + s.resolution * s.resolution / 12.0;
      inv_six_sigma2_[k] = 1.0 / (6.0 * sigma2);
      stuck_run_[k] = stuck_run_for(s.noise_std, s.resolution, options.false_alarm_probability);
      // The observer's residual is in max(noise, resolution / sqrt 12) (CellObserver).
      residual_sigma_[k] = std::max(s.noise_std, s.resolution / std::sqrt(12.0));
      if (s.place == model::PlaceKind::fluid_cell) {
        cells_.push_back(s.index);
      } else {
        for (const std::size_t c : layout.cells_of_valve(s.index)) {
          cells_.push_back(c);
        }
      }
    }
    std::sort(cells_.begin() + static_cast<std::ptrdiff_t>(cells_begin_[k]), cells_.end());
    cells_begin_.push_back(cells_.size());
    for (std::size_t e = cells_begin_[k]; e < cells_begin_[k + 1]; ++e) {
      ++readers_of_cell_[cells_[e]];
    }
  }
  find_neighbours();
  set_reading_deadband(reading_deadband);
  fault_.assign(n, SensorFault::none);
  evidence_.assign(n, 0.0);
  healthy_ = static_cast<std::size_t>(std::count(watched_.begin(), watched_.end(), 1));
  reserve_judged();
  judge_every_watched_sensor();
}

void SensorFaultMonitor::Impl::find_neighbours() {
  const std::size_t n = watched_.size();
  std::vector<std::vector<std::uint32_t>> readers(readers_of_cell_.size());
  for (std::size_t k = 0; k < n; ++k) {
    for (std::size_t e = cells_begin_[k]; e < cells_begin_[k + 1]; ++e) {
      readers[cells_[e]].push_back(static_cast<std::uint32_t>(k));
    }
  }
  neighbours_begin_.assign(1, 0);
  std::vector<std::uint32_t> mine;
  for (std::size_t k = 0; k < n; ++k) {
    mine.clear();
    for (std::size_t e = cells_begin_[k]; e < cells_begin_[k + 1]; ++e) {
      for (const std::uint32_t other : readers[cells_[e]]) {
        if (other != k) {
          mine.push_back(other);
        }
      }
    }
    std::sort(mine.begin(), mine.end());
    mine.erase(std::unique(mine.begin(), mine.end()), mine.end());
    neighbours_.insert(neighbours_.end(), mine.begin(), mine.end());
    neighbours_begin_.push_back(neighbours_.size());
  }
}

// One shifted zero is spread by the fit onto the sensors that read its cells, with the opposite
// sign (the fit moves those depths towards the shifted reading, and they read the move). Where a
// neighbour is left with as large a mean as the culprit's (two sensors reading the same cells
// split it evenly: offset:0 on the 5x5 leaves +14.5 sigma on sensor 0 and -14.5 on sensor 2), the
// culprit is the one its neighbours oppose: among the sensors within kTieFraction of the largest
// mean, the largest |m_k - kSpreadWeight * (the sum of k's healthy neighbours' means)|.
std::size_t SensorFaultMonitor::Impl::blame_offset(double worst_offset) const noexcept {
  constexpr double kTieFraction = 0.5;
  constexpr double kSpreadWeight = 0.5;
  const double floor = kTieFraction * std::abs(worst_offset);
  std::size_t blamed = npos;
  double best = -1.0;
  for (const std::uint32_t k : judged_) {
    const double m = mean_residual_[k];
    if (!(std::abs(m) >= floor)) {
      continue;
    }
    double spread = 0.0;
    for (std::size_t e = neighbours_begin_[k]; e < neighbours_begin_[k + 1]; ++e) {
      if (fault_[neighbours_[e]] == SensorFault::none) {
        spread += mean_residual_[neighbours_[e]];
      }
    }
    const double score = std::abs(m - kSpreadWeight * spread);
    if (score > best) {
      best = score;
      blamed = k;
    }
  }
  return blamed;
}

void SensorFaultMonitor::Impl::judge_every_watched_sensor() noexcept {
  judged_.clear();  // within its reserve: no allocation
  for (std::size_t k = 0; k < watched_.size(); ++k) {
    set_judged(k, watched_[k] != 0);
    if (watched_[k] != 0) {
      judged_.push_back(static_cast<std::uint32_t>(k));
    }
  }
}

std::span<const std::size_t> SensorFaultMonitor::Impl::cells_of_sensor(std::size_t sensor) const noexcept {
  if (sensor + 1 >= cells_begin_.size()) {
    return {};
  }
  return {cells_.data() + cells_begin_[sensor], cells_begin_[sensor + 1] - cells_begin_[sensor]};
}

void SensorFaultMonitor::Impl::reset() noexcept {
  for (std::size_t k = 0; k < fault_.size(); ++k) {
    if (fault_[k] != SensorFault::none) {
      for (std::size_t e = cells_begin_[k]; e < cells_begin_[k + 1]; ++e) {
        ++readers_of_cell_[cells_[e]];
      }
    }
  }
  std::fill(fault_.begin(), fault_.end(), SensorFault::none);
  std::fill(evidence_.begin(), evidence_.end(), 0.0);
  judge_every_watched_sensor();
  restart_watch();
  healthy_ += faulty_;
  faulty_ = 0;
  unobservable_ = npos;
}

void SensorFaultMonitor::Impl::restart_history() noexcept { restart_watch(); }

void SensorFaultMonitor::Impl::latch(std::size_t sensor, SensorFault fault, double evidence) noexcept {
  fault_[sensor] = fault;
  evidence_[sensor] = evidence;
  std::erase(judged_, static_cast<std::uint32_t>(sensor));
  set_judged(sensor, false);
  ++faulty_;
  --healthy_;
  for (std::size_t e = cells_begin_[sensor]; e < cells_begin_[sensor + 1]; ++e) {
    const std::size_t c = cells_[e];
    // A cell the profile never read is no news; one whose last reader failed is.
    if (readers_of_cell_[c] > 0 && --readers_of_cell_[c] == 0 && unobservable_ == npos) {
      unobservable_ = c;
    }
  }
  // The fit moves once the sensor is out: the others' residual means start again.
  std::fill(mean_residual_.begin(), mean_residual_.end(), 0.0);
}

std::size_t SensorFaultMonitor::Impl::update(std::span<const double> readings,
                                             std::span<const double> residual_sigma,
                                             const std::uint32_t* device_time_us) noexcept {
  if (!options_.enabled || readings.size() != fault_.size() || residual_sigma.size() != fault_.size()) {
    return npos;
  }
  // The spacing of before, last and this reading on the unit's clock (uint32 differences: it
  // wraps); evenly spaced while fewer than three readings came with a time.
  evenly_spaced_ = true;
  if (device_time_us == nullptr) {
    times_seen_ = 0;
  } else {
    const std::uint32_t before_to_last_us = time_last_us_ - time_before_us_;
    const std::uint32_t last_to_now_us = *device_time_us - time_last_us_;
    if (times_seen_ >= 2 && before_to_last_us != last_to_now_us) {
      evenly_spaced_ = false;
      spacing_ = second_difference(before_to_last_us, last_to_now_us);
    }
    time_before_us_ = time_last_us_;
    time_last_us_ = *device_time_us;
    times_seen_ = std::min(times_seen_ + 1U, 2U);
  }
  // The common reading (the sensors' histories alike, every value finite) takes the lean pass,
  // which
  // tells whether any test is past its limit; the tests then decide as the full pass would.
  if (lean_ != Lean::mixed && all_finite(readings, residual_sigma)) {
    const bool alarm = update_lean(readings, residual_sigma);
    if (lean_ != Lean::primed) {  // every judged sensor has one reading more
      const bool was_fresh = lean_ == Lean::fresh;
      std::fill(seen_.begin(), seen_.end(), was_fresh ? 1.0 : 2.0);
      lean_ = was_fresh ? Lean::one_reading : Lean::primed;
    }
    return alarm ? decide(readings) : npos;
  }
  return update_scalar(readings, residual_sigma) ? decide(readings) : npos;
}

// Every reading and residual finite (x - x is 0 for a finite x, NaN otherwise).
bool SensorFaultMonitor::Impl::all_finite(std::span<const double> readings,
                                          std::span<const double> residual_sigma) noexcept {
  double sum = 0.0;
  for (std::size_t k = 0; k < readings.size(); ++k) {
    sum += (readings[k] - readings[k]) + (residual_sigma[k] - residual_sigma[k]);
  }
  return sum == 0.0;
}

// One reading into each judged sensor's history and running figures; a sensor whose reading is
// not finite is skipped (the observer refuses the tick), a residual that is not finite leaves the
// mean as it was. True when some test is past its limit; sets lean_.
bool SensorFaultMonitor::Impl::update_scalar(std::span<const double> readings,
                                             std::span<const double> residual_sigma) noexcept {
  const double noise_alpha = 1.0 / options_.noise_window_readings;
  const double offset_alpha = 1.0 / options_.offset_window_readings;
  const double ratio_cap = kOutlierCap * options_.noise_ratio_limit;
  const double offset_cap = kOutlierCap * options_.offset_limit_sigma;
  bool alarm = false;
  bool primed = true;
  bool one_each = true;  // (the full pass runs after a reading that was not finite: none is fresh)
  for (const std::uint32_t sensor : judged_) {
    const std::size_t k = sensor;
    const double y = readings[k];
    if (!std::isfinite(y)) {
      seen_[k] = 0.0;  // the noise test needs three readings in a row again; the stuck run goes on
      primed = false;
      one_each = false;
      continue;
    }
    const double r = residual_sigma[k];
    if (run_[k] == 0.0 || y != last_[k]) {  // a run of 0: no reading yet
      run_[k] = 1.0;
    } else if (deadband_sigma_[k] == 0.0 ||
               (std::isfinite(r) && std::abs(r) > deadband_sigma_[k] + kDeadbandMarginSigma)) {
      run_[k] += 1.0;  // a repeat the deadband does not explain
    }                  // else: a repeat within the band is no evidence either way; the run holds
    if (seen_[k] >= 2.0) {
      const double d2 = evenly_spaced_
                            ? y - 2.0 * last_[k] + before_last_[k]
                            : spacing_.now * y + spacing_.last * last_[k] + spacing_.before * before_last_[k];
      // One jump (a finger's tap, a gap in the readings) must not pass for noise: each reading
      // counts for at most kOutlierCap limits, so it takes several to cross one.
      const double ratio = std::min(d2 * d2 * inv_six_sigma2_[k], ratio_cap);
      noise_ratio_[k] += noise_alpha * (ratio - noise_ratio_[k]);
    }
    before_last_[k] = last_[k];
    last_[k] = y;
    seen_[k] = std::min(seen_[k] + 1.0, 2.0);
    primed = primed && seen_[k] >= 2.0;
    one_each = one_each && seen_[k] == 1.0;
    if (std::isfinite(r)) {
      mean_residual_[k] += offset_alpha * (std::clamp(r, -offset_cap, offset_cap) - mean_residual_[k]);
    }
    alarm = alarm || run_[k] >= stuck_limit_[k] || noise_ratio_[k] > options_.noise_ratio_limit ||
            std::abs(mean_residual_[k]) > options_.offset_limit_sigma;
  }
  lean_ = primed ? Lean::primed : (one_each ? Lean::one_reading : Lean::mixed);
  return alarm;
}

// update_scalar's arithmetic for finite values, without its branches, while the judged sensors'
// histories are alike (lean_); true when some test is past its limit.
bool SensorFaultMonitor::Impl::update_lean(std::span<const double> readings,
                                           std::span<const double> residual_sigma) noexcept {
  const LeanLimits limits{kOutlierCap * options_.noise_ratio_limit, kOutlierCap * options_.offset_limit_sigma,
                          options_.noise_ratio_limit, options_.offset_limit_sigma};
  const auto pass = [&]<bool kEven>() {
    return lean_pass<kEven>(readings.size(), readings.data(), residual_sigma.data(), last_.data(),
                            before_last_.data(), run_.data(), noise_ratio_.data(), mean_residual_.data(),
                            deadband_sigma_.data(), inv_six_sigma2_.data(), noise_alpha_.data(),
                            offset_alpha_.data(), judged_weight_.data(), stuck_limit_.data(), limits,
                            spacing_, lean_ == Lean::fresh ? 0.0 : 1.0, lean_ == Lean::primed ? 1.0 : 0.0);
  };
  // Evenly spaced (every reading a host that keeps its periods gets): the pass without the weights.
  return evenly_spaced_ ? pass.template operator()<true>() : pass.template operator()<false>();
}

// The tests on the running figures, in sensor order: the first stuck or noisy sensor, else an
// offset past its limit (blamed as blame_offset says). Latches and returns the sensor, or npos.
std::size_t SensorFaultMonitor::Impl::decide(std::span<const double> readings) noexcept {
  std::size_t found = npos;
  SensorFault found_kind = SensorFault::none;
  double found_evidence = 0.0;
  double worst_offset = 0.0;
  std::size_t worst_offset_sensor = npos;
  for (const std::uint32_t k : judged_) {
    if (!std::isfinite(readings[k])) {
      continue;  // not judged on this reading
    }
    if (run_[k] >= stuck_limit_[k]) {
      found = k;
      found_kind = SensorFault::stuck;
      found_evidence = readings[k];
      break;
    }
    if (noise_ratio_[k] > options_.noise_ratio_limit) {
      found = k;
      found_kind = SensorFault::noisy;
      found_evidence = noise_ratio_[k];
      break;
    }
    if (std::abs(mean_residual_[k]) > std::abs(worst_offset)) {
      worst_offset = mean_residual_[k];
      worst_offset_sensor = k;
    }
  }
  if (found == npos && worst_offset_sensor != npos && std::abs(worst_offset) > options_.offset_limit_sigma) {
    found = blame_offset(worst_offset);
    // A stuck sensor under a moving finger leaves a residual before its run is long enough; a
    // healthy one with a shifted zero still moves: this many repeats is stuck (p < 1e-3 here).
    constexpr std::size_t kStuckHint = 8;
    const bool stuck = run_[found] >= static_cast<double>(std::min(kStuckHint, stuck_run_[found]));
    found_kind = stuck ? SensorFault::stuck : SensorFault::offset;
    found_evidence = stuck ? last_[found] : mean_residual_[found];
  }
  if (found != npos) {
    latch(found, found_kind, found_evidence);
  }
  return found;
}

// --- the public face: one pointer to the state ---------------------------------------------

SensorFaultMonitor::SensorFaultMonitor(const model::DeviceProfile& profile, const GridLayout& layout,
                                       const SensorFaultOptions& options, double reading_deadband)
    : impl_(std::make_unique<Impl>(profile, layout, options, reading_deadband)) {}
SensorFaultMonitor::SensorFaultMonitor(const SensorFaultMonitor& other)
    : impl_(std::make_unique<Impl>(*other.impl_)) {
  impl_->reserve_judged();
}
SensorFaultMonitor& SensorFaultMonitor::operator=(const SensorFaultMonitor& other) {
  return *this = SensorFaultMonitor(other);
}
SensorFaultMonitor::SensorFaultMonitor(SensorFaultMonitor&&) noexcept = default;
SensorFaultMonitor& SensorFaultMonitor::operator=(SensorFaultMonitor&&) noexcept = default;
SensorFaultMonitor::~SensorFaultMonitor() = default;
std::size_t SensorFaultMonitor::update(std::span<const double> readings,
                                       std::span<const double> residual_sigma) noexcept {
  return impl_->update(readings, residual_sigma, nullptr);
}
std::size_t SensorFaultMonitor::update(std::span<const double> readings,
                                       std::span<const double> residual_sigma,
                                       std::uint32_t device_time_us) noexcept {
  return impl_->update(readings, residual_sigma, &device_time_us);
}
void SensorFaultMonitor::reset() noexcept { impl_->reset(); }
void SensorFaultMonitor::set_reading_deadband(double reading_deadband) noexcept {
  impl_->set_reading_deadband(reading_deadband);
}
void SensorFaultMonitor::restart_history() noexcept { impl_->restart_history(); }
SensorFault SensorFaultMonitor::fault(std::size_t sensor) const noexcept { return impl_->fault(sensor); }
std::size_t SensorFaultMonitor::faulty_count() const noexcept { return impl_->faulty_count(); }
std::size_t SensorFaultMonitor::healthy_count() const noexcept { return impl_->healthy_count(); }
std::size_t SensorFaultMonitor::unobservable_cell() const noexcept { return impl_->unobservable_cell(); }
std::span<const std::size_t> SensorFaultMonitor::cells_of_sensor(std::size_t sensor) const noexcept {
  return impl_->cells_of_sensor(sensor);
}
std::size_t SensorFaultMonitor::stuck_run_readings(std::size_t sensor) const noexcept {
  return impl_->stuck_run_readings(sensor);
}
double SensorFaultMonitor::noise_ratio(std::size_t sensor) const noexcept {
  return impl_->noise_ratio(sensor);
}
double SensorFaultMonitor::mean_residual_sigma(std::size_t sensor) const noexcept {
  return impl_->mean_residual_sigma(sensor);
}
double SensorFaultMonitor::evidence(std::size_t sensor) const noexcept { return impl_->evidence(sensor); }

static_assert(sizeof(SensorFaultMonitor) == sizeof(void*),
              "SensorFaultMonitor is one pointer: its state lives in SensorFaultMonitor::Impl");

}  // namespace mrskin::bridge
