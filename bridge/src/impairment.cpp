#include "mrskin/bridge/impairment.hpp"

#include <cmath>
#include <limits>
#include <string>

#include "mrskin/driver/errors.hpp"

namespace mrskin::bridge {
namespace {

constexpr TimePoint kFree{std::numeric_limits<TimePoint::rep>::max()};

}  // namespace

ImpairedSource::ImpairedSource(SlaveSource& inner, const ImpairmentOptions& options)
    : inner_(inner), options_(options), rng_(options.seed) {
  if (!(options.delay_s >= 0.0 && options.jitter_s >= 0.0 && options.jitter_s <= options.delay_s &&
        std::isfinite(options.delay_s) && options.loss >= 0.0 && options.loss < 1.0 &&
        options.capacity > 0)) {
    throw InvalidArgument(
        "impairment: need 0 <= jitter <= delay, 0 <= loss < 1 and capacity > 0 (got delay " +
        std::to_string(options.delay_s) + " s, jitter " + std::to_string(options.jitter_s) + " s, loss " +
        std::to_string(options.loss) + ")");
  }
  flight_.assign(options.capacity, InFlight{SlaveSample{}, kFree});
}

bool ImpairedSource::latest(TimePoint now, SlaveSample& out) noexcept {
  SlaveSample fresh;
  if (inner_.latest(now, fresh) && fresh.valid && (!last_sent_.valid || fresh.stamp != last_sent_.stamp)) {
    last_sent_ = fresh;
    ++stats_.sent;
    std::uniform_real_distribution<double> unit(0.0, 1.0);
    if (unit(rng_) < options_.loss) {
      ++stats_.lost;
    } else if (in_flight_ == flight_.size()) {
      ++stats_.overflowed;
    } else {
      const double delay_s = options_.delay_s + options_.jitter_s * (2.0 * unit(rng_) - 1.0);
      for (InFlight& f : flight_) {
        if (f.arrival == kFree) {
          f.sample = fresh;
          f.arrival = now + from_seconds(delay_s);
          ++in_flight_;
          break;
        }
      }
    }
  }
  // Deliver everything due, in arrival order; the last to arrive is what the host sees now.
  for (;;) {
    InFlight* next = nullptr;
    for (InFlight& f : flight_) {
      if (f.arrival != kFree && f.arrival <= now && (next == nullptr || f.arrival < next->arrival)) {
        next = &f;
      }
    }
    if (next == nullptr) {
      break;
    }
    if (delivered_.valid && next->sample.stamp < newest_delivered_stamp_) {
      ++stats_.reordered;
    }
    delivered_ = next->sample;
    delivered_.received = next->arrival;
    if (delivered_.stamp > newest_delivered_stamp_) {
      newest_delivered_stamp_ = delivered_.stamp;
    }
    ++stats_.delivered;
    next->arrival = kFree;
    --in_flight_;
  }
  if (!delivered_.valid) {
    return false;
  }
  out = delivered_;
  return true;
}

}  // namespace mrskin::bridge
