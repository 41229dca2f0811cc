// Injected time. Nothing in mrskin reads a system clock directly: the loop, the session
// and the mock device all take a Clock, so tests run on simulated time.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>

#include "mrskin/driver/export.hpp"

namespace mrskin {

using Duration = std::chrono::nanoseconds;
// A time point is the duration since the clock's own epoch.
using TimePoint = std::chrono::nanoseconds;

class MRSKIN_DRIVER_API Clock {
 public:
  Clock() = default;
  Clock(const Clock&) = delete;
  Clock& operator=(const Clock&) = delete;
  Clock(Clock&&) = delete;
  Clock& operator=(Clock&&) = delete;
  virtual ~Clock() = default;

  [[nodiscard]] virtual TimePoint now() const noexcept = 0;
  // Blocks until now() >= t (a simulated clock jumps there instead). Never on the tick path.
  virtual void sleep_until(TimePoint t) noexcept = 0;
};

// CLOCK_MONOTONIC.
class MRSKIN_DRIVER_API MonotonicClock final : public Clock {
 public:
  [[nodiscard]] TimePoint now() const noexcept override;
  void sleep_until(TimePoint t) noexcept override;
};

// Advanced by hand; thread-safe reads. sleep_until() moves time forward to t.
class MRSKIN_DRIVER_API SimulatedClock final : public Clock {
 public:
  explicit SimulatedClock(TimePoint start = TimePoint{0}) noexcept : now_ns_(start.count()) {}
  [[nodiscard]] TimePoint now() const noexcept override {
    return TimePoint{now_ns_.load(std::memory_order_acquire)};
  }
  void sleep_until(TimePoint t) noexcept override;
  void advance(Duration d) noexcept { now_ns_.fetch_add(d.count(), std::memory_order_acq_rel); }

 private:
  std::atomic<std::int64_t> now_ns_;
};

inline double to_seconds(Duration d) noexcept { return std::chrono::duration<double>(d).count(); }
inline Duration from_seconds(double s) noexcept {
  return std::chrono::duration_cast<Duration>(std::chrono::duration<double>(s));
}
// A timeout or period stretched by a time scale (MRSKIN_TIME_SCALE: above 1 on a slow machine).
// A scale below 1e-3, or NaN, counts as 1e-3: no wait collapses to zero or overflows.
inline Duration scaled_duration(Duration d, double time_scale) noexcept {
  const double k = time_scale >= 1e-3 ? time_scale : 1e-3;
  return Duration{static_cast<Duration::rep>(static_cast<double>(d.count()) * k)};
}

}  // namespace mrskin
