#include "mrskin/driver/clock.hpp"

#include <cerrno>
#include <ctime>

namespace mrskin {

TimePoint MonotonicClock::now() const noexcept {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return TimePoint{static_cast<std::int64_t>(ts.tv_sec) * 1'000'000'000 + ts.tv_nsec};
}

void MonotonicClock::sleep_until(TimePoint t) noexcept {
  timespec ts{};
  ts.tv_sec = static_cast<time_t>(t.count() / 1'000'000'000);
  ts.tv_nsec = static_cast<long>(t.count() % 1'000'000'000);
  while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr) == EINTR) {
  }
}

void SimulatedClock::sleep_until(TimePoint t) noexcept {
  std::int64_t current = now_ns_.load(std::memory_order_acquire);
  while (current < t.count() &&
         !now_ns_.compare_exchange_weak(current, t.count(), std::memory_order_acq_rel)) {
  }
}

}  // namespace mrskin
