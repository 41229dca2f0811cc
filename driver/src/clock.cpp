#include "mrskin/driver/clock.hpp"

#include <cerrno>
#include <ctime>

#include "mrskin/driver/atomic_raise.hpp"

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

void SimulatedClock::sleep_until(TimePoint t) noexcept { atomic_raise(now_ns_, t.count()); }

}  // namespace mrskin
