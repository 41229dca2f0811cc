#include "mrskin/bridge/sensor_faults.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
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

}  // namespace

// The monitor's state, behind SensorFaultMonitor's one pointer (docs/api.md, "ABI").
class __attribute__((visibility("hidden"))) SensorFaultMonitor::Impl {
 public:
  Impl(const model::DeviceProfile& profile, const GridLayout& layout, const SensorFaultOptions& options,
       double reading_deadband);

  std::size_t update(std::span<const double> readings, std::span<const double> residual_sigma) noexcept;
  void reset() noexcept;
  void restart_history() noexcept;
  // Room for every watched sensor in judged_, so reset() never allocates (a copy's vector has
  // only its size reserved). Setup only: may throw std::bad_alloc.
  void reserve_judged() {
    judged_.reserve(static_cast<std::size_t>(std::count(watched_.begin(), watched_.end(), 1)));
  }
  void set_reading_deadband(double reading_deadband) noexcept {
    const double band = std::isfinite(reading_deadband) ? std::max(0.0, reading_deadband) : 0.0;
    for (std::size_t k = 0; k < watch_.size(); ++k) {
      watch_[k].deadband_sigma = residual_sigma_[k] > 0.0 ? band / residual_sigma_[k] : 0.0;
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
    return sensor < watch_.size() ? watch_[sensor].stuck_run : npos;
  }
  [[nodiscard]] double noise_ratio(std::size_t sensor) const noexcept {
    return sensor < watch_.size() ? watch_[sensor].noise_ratio : 0.0;
  }
  [[nodiscard]] double mean_residual_sigma(std::size_t sensor) const noexcept {
    return sensor < watch_.size() ? watch_[sensor].mean_residual : 0.0;
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
  // Per sensor, what update() reads and writes for every reading, in one place (one stride):
  // the reading's history, the tests' running figures and their constants.
  struct Watch {
    double last = 0.0;
    double before_last = 0.0;
    double noise_ratio = 0.0;
    double mean_residual = 0.0;
    double inv_six_sigma2 = 0.0;  // 1 / (6 sigma^2): white noise's mean squared 2nd difference
    double deadband_sigma = 0.0;  // the unit's deadband in residual_sigma_ (0: none)
    std::size_t run = 0;
    std::size_t stuck_run = npos;
    std::size_t seen = 0;  // readings so far (up to 2: the second difference needs 3)
  };
  std::vector<Watch> watch_;
  void restart_watch() noexcept {
    for (Watch& w : watch_) {
      w.seen = 0;
      w.run = 0;
      w.noise_ratio = 0.0;
      w.mean_residual = 0.0;
    }
    primed_ = false;
  }
  // Every judged sensor has the two readings before this one (its second difference is defined).
  bool primed_ = false;
  [[nodiscard]] static bool all_finite(std::span<const double> readings,
                                       std::span<const double> residual_sigma) noexcept;
  [[nodiscard]] bool update_scalar(std::span<const double> readings,
                                   std::span<const double> residual_sigma) noexcept;
  [[nodiscard]] bool update_primed(std::span<const double> readings,
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
  watch_.assign(n, Watch{});
  residual_sigma_.assign(n, 0.0);
  readers_of_cell_.assign(cells, 0);
  cells_begin_.push_back(0);
  for (std::size_t k = 0; k < n; ++k) {
    const model::SensorSpec& s = profile.sensors[k];
    if (s.quantity == model::SensorQuantity::displacement && s.place != model::PlaceKind::reservoir) {
      watched_[k] = 1;
      const double sigma2 = s.noise_std * s.noise_std + s.resolution * s.resolution / 12.0;
      watch_[k].inv_six_sigma2 = 1.0 / (6.0 * sigma2);
      watch_[k].stuck_run = stuck_run_for(s.noise_std, s.resolution, options.false_alarm_probability);
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
    const double m = watch_[k].mean_residual;
    if (!(std::abs(m) >= floor)) {
      continue;
    }
    double spread = 0.0;
    for (std::size_t e = neighbours_begin_[k]; e < neighbours_begin_[k + 1]; ++e) {
      if (fault_[neighbours_[e]] == SensorFault::none) {
        spread += watch_[neighbours_[e]].mean_residual;
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
  for (Watch& w : watch_) {
    w.mean_residual = 0.0;
  }
}

std::size_t SensorFaultMonitor::Impl::update(std::span<const double> readings,
                                             std::span<const double> residual_sigma) noexcept {
  if (!options_.enabled || readings.size() != fault_.size() || residual_sigma.size() != fault_.size()) {
    return npos;
  }
  // The common reading (every sensor primed, every value finite) takes the lean pass, which
  // tells whether any test is past its limit; the tests then decide as the full pass would.
  if (primed_ && all_finite(readings, residual_sigma)) {
    return update_primed(readings, residual_sigma) ? decide(readings) : npos;
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
// mean as it was. True when some test is past its limit; sets primed_.
bool SensorFaultMonitor::Impl::update_scalar(std::span<const double> readings,
                                             std::span<const double> residual_sigma) noexcept {
  const double noise_alpha = 1.0 / options_.noise_window_readings;
  const double offset_alpha = 1.0 / options_.offset_window_readings;
  const double ratio_cap = kOutlierCap * options_.noise_ratio_limit;
  const double offset_cap = kOutlierCap * options_.offset_limit_sigma;
  bool alarm = false;
  bool primed = true;
  for (const std::uint32_t sensor : judged_) {
    const std::size_t k = sensor;
    const double y = readings[k];
    if (!std::isfinite(y)) {
      primed = primed && watch_[k].seen >= 2;
      continue;
    }
    const double r = residual_sigma[k];
    Watch& w = watch_[k];
    if (w.seen == 0 || y != w.last) {
      w.run = 1;
    } else if (w.deadband_sigma == 0.0 ||
               (std::isfinite(r) && std::abs(r) > w.deadband_sigma + kDeadbandMarginSigma)) {
      ++w.run;  // a repeat the deadband does not explain
    }           // else: a repeat within the band is no evidence either way; the run holds
    if (w.seen >= 2) {
      const double d2 = y - 2.0 * w.last + w.before_last;
      // One jump (a finger's tap, a gap in the readings) must not pass for noise: each reading
      // counts for at most kOutlierCap limits, so it takes several to cross one.
      const double ratio = std::min(d2 * d2 * w.inv_six_sigma2, ratio_cap);
      w.noise_ratio += noise_alpha * (ratio - w.noise_ratio);
    }
    w.before_last = w.last;
    w.last = y;
    w.seen = std::min<std::size_t>(w.seen + 1, 2);
    if (std::isfinite(r)) {
      w.mean_residual += offset_alpha * (std::clamp(r, -offset_cap, offset_cap) - w.mean_residual);
    }
    primed = primed && w.seen >= 2;
    alarm = alarm || (w.stuck_run != npos && w.run >= w.stuck_run) ||
            w.noise_ratio > options_.noise_ratio_limit ||
            std::abs(w.mean_residual) > options_.offset_limit_sigma;
  }
  primed_ = primed;
  return alarm;
}

// update_scalar's arithmetic for primed sensors and finite values, without its branches; true
// when some test is past its limit.
bool SensorFaultMonitor::Impl::update_primed(std::span<const double> readings,
                                             std::span<const double> residual_sigma) noexcept {
  // Loop constants in locals: the stores into watch_ would otherwise make the compiler read the
  // options again for every sensor.
  const double noise_alpha = 1.0 / options_.noise_window_readings;
  const double offset_alpha = 1.0 / options_.offset_window_readings;
  const double ratio_cap = kOutlierCap * options_.noise_ratio_limit;
  const double noise_limit = options_.noise_ratio_limit;
  const double offset_cap = kOutlierCap * options_.offset_limit_sigma;
  const double offset_limit = options_.offset_limit_sigma;
  bool alarm = false;
  for (const std::uint32_t k : judged_) {
    const double y = readings[k];
    const double r = residual_sigma[k];
    Watch& w = watch_[k];
    const bool counts = w.deadband_sigma == 0.0 || std::abs(r) > w.deadband_sigma + kDeadbandMarginSigma;
    w.run = y == w.last ? w.run + static_cast<std::size_t>(counts) : 1;
    const double d2 = y - 2.0 * w.last + w.before_last;
    w.noise_ratio += noise_alpha * (std::min(d2 * d2 * w.inv_six_sigma2, ratio_cap) - w.noise_ratio);
    w.before_last = w.last;
    w.last = y;
    w.mean_residual += offset_alpha * (std::clamp(r, -offset_cap, offset_cap) - w.mean_residual);
    alarm = alarm || w.run >= w.stuck_run || w.noise_ratio > noise_limit ||
            std::abs(w.mean_residual) > offset_limit;
  }
  return alarm;
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
    const Watch& w = watch_[k];
    if (!std::isfinite(readings[k])) {
      continue;  // not judged on this reading
    }
    if (w.stuck_run != npos && w.run >= w.stuck_run) {
      found = k;
      found_kind = SensorFault::stuck;
      found_evidence = readings[k];
      break;
    }
    if (w.noise_ratio > options_.noise_ratio_limit) {
      found = k;
      found_kind = SensorFault::noisy;
      found_evidence = w.noise_ratio;
      break;
    }
    if (std::abs(w.mean_residual) > std::abs(worst_offset)) {
      worst_offset = w.mean_residual;
      worst_offset_sensor = k;
    }
  }
  if (found == npos && worst_offset_sensor != npos && std::abs(worst_offset) > options_.offset_limit_sigma) {
    found = blame_offset(worst_offset);
    // A stuck sensor under a moving finger leaves a residual before its run is long enough; a
    // healthy one with a shifted zero still moves: this many repeats is stuck (p < 1e-3 here).
    constexpr std::size_t kStuckHint = 8;
    const bool stuck = watch_[found].run >= std::min(kStuckHint, watch_[found].stuck_run);
    found_kind = stuck ? SensorFault::stuck : SensorFault::offset;
    found_evidence = stuck ? watch_[found].last : watch_[found].mean_residual;
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
  return impl_->update(readings, residual_sigma);
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
