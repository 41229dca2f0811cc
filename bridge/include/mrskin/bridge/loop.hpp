// The real-time loop runner: calls a tick on its own thread at absolute deadlines of the
// injected clock (start + k * period, never drifting), wakes early when the I/O side calls
// notify(), skips missed periods instead of bursting, and asks for SCHED_FIFO and mlockall,
// warning once (never from the tick thread) with the fix when they are not permitted.
// See docs/loop.md.
#pragma once

#include <atomic>
#include <cstdint>
#include <memory>
#include <string>

#include "mrskin/bridge/export.hpp"
#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/histogram.hpp"

namespace mrskin::bridge {

// What the loop runs. tick(now) gets the loop clock's time at wake-up.
class MRSKIN_BRIDGE_API Tickable {
 public:
  Tickable() = default;
  Tickable(const Tickable&) = delete;
  Tickable& operator=(const Tickable&) = delete;
  Tickable(Tickable&&) = delete;
  Tickable& operator=(Tickable&&) = delete;
  virtual ~Tickable() = default;
  virtual ResultCode tick(TimePoint now) noexcept = 0;
};
// The same as a plain function pointer plus context (no allocation, no std::function).
using TickFunction = ResultCode (*)(void* context, TimePoint now) noexcept;

// How the loop waits between ticks: until a deadline on the loop's clock, or earlier when
// notified. Waits come from the loop thread only; notify() from any thread.
class MRSKIN_BRIDGE_API Waiter {
 public:
  enum class Wake : std::uint8_t { deadline, notified };
  Waiter() = default;
  Waiter(const Waiter&) = delete;
  Waiter& operator=(const Waiter&) = delete;
  Waiter(Waiter&&) = delete;
  Waiter& operator=(Waiter&&) = delete;
  virtual ~Waiter() = default;
  // Returns deadline once the clock has reached it (consuming any pending notification: that
  // tick reads the new sample too), or notified when notify() was called since the last wait.
  virtual Wake wait_until(TimePoint deadline) noexcept = 0;
  virtual void notify() noexcept = 0;
  // Drops a pending notification (at start).
  virtual void clear() noexcept = 0;
};

// For MonotonicClock: a one-shot timerfd armed at the absolute deadline on CLOCK_MONOTONIC
// and an eventfd for notify(), polled together. notify() is one write(2): lock-free and
// async-signal-safe. Throws Error when the descriptors cannot be made.
class MRSKIN_BRIDGE_API MonotonicWaiter final : public Waiter {
 public:
  MonotonicWaiter();
  MonotonicWaiter(const MonotonicWaiter&) = delete;
  MonotonicWaiter& operator=(const MonotonicWaiter&) = delete;
  MonotonicWaiter(MonotonicWaiter&&) = delete;
  MonotonicWaiter& operator=(MonotonicWaiter&&) = delete;
  ~MonotonicWaiter() override;
  Wake wait_until(TimePoint deadline) noexcept override;
  void notify() noexcept override;
  void clear() noexcept override;

 private:
  int event_fd_ = -1;
  int timer_fd_ = -1;
  TimePoint armed_{-1};  // deadline the timer is armed for; -1: disarmed
};

// Any clock: clock.sleep_until(deadline). A notification pending when the wait begins wakes
// at once; one arriving during the sleep waits for the deadline. On a SimulatedClock the sleep
// jumps the clock, which makes a loop stepped with run_once() exactly repeatable.
class MRSKIN_BRIDGE_API SleepWaiter final : public Waiter {
 public:
  explicit SleepWaiter(Clock& clock) noexcept : clock_(clock) {}
  Wake wait_until(TimePoint deadline) noexcept override;
  void notify() noexcept override { pending_.store(true, std::memory_order_release); }
  void clear() noexcept override { pending_.store(false, std::memory_order_release); }

 private:
  Clock& clock_;
  std::atomic<bool> pending_{false};
};

// The scheduling the loop thread actually has.
struct MRSKIN_BRIDGE_API SchedulerState {
  int policy = 0;              // SCHED_OTHER, SCHED_FIFO, ... as sched_getscheduler(2)
  int priority = 0;            // sched_priority (0 unless real-time)
  bool memory_locked = false;  // mlockall(MCL_CURRENT | MCL_FUTURE) succeeded
  int cpu = -1;                // the one CPU the thread is pinned to, -1: not pinned
  [[nodiscard]] bool fifo() const noexcept;
  [[nodiscard]] const char* policy_name() const noexcept;  // "SCHED_FIFO", "SCHED_OTHER", ...
};

// The OS calls of the real-time set-up, a seam so tests can refuse them. Each returns 0 or
// an errno value, for the calling thread (memory locking is process-wide).
class MRSKIN_BRIDGE_API RealtimeOs {
 public:
  RealtimeOs() = default;
  RealtimeOs(const RealtimeOs&) = delete;
  RealtimeOs& operator=(const RealtimeOs&) = delete;
  RealtimeOs(RealtimeOs&&) = delete;
  RealtimeOs& operator=(RealtimeOs&&) = delete;
  virtual ~RealtimeOs() = default;
  virtual int set_fifo(int priority) noexcept;
  // mlockall(MCL_CURRENT | MCL_FUTURE). Refused (ENOMEM) without calling it when the memlock
  // limit is finite and CAP_IPC_LOCK is missing: MCL_FUTURE would make later allocations fail
  // once past the limit. Refused (ENOTSUP) in sanitizer builds, whose shadow memory is huge.
  virtual int lock_memory() noexcept;
  // sched_setaffinity(2) of the calling thread to the one CPU.
  virtual int pin_cpu(int cpu) noexcept;
  virtual void query(int& policy, int& priority) noexcept;
};
MRSKIN_BRIDGE_API RealtimeOs& system_realtime_os() noexcept;

// Whether this process may run on `cpu` (its sched_getaffinity mask): -1 (no pinning) always
// may; when the kernel does not tell, any CPU below CPU_SETSIZE may (the pin itself then fails
// at start with a warning). allowed_cpus() lists the mask as "0,1,3", or "unknown".
MRSKIN_BRIDGE_API bool cpu_allowed(int cpu) noexcept;
MRSKIN_BRIDGE_API std::string allowed_cpus();

struct LoopOptions {
  double rate_hz = 1000.0;  // 1 Hz .. 20 kHz
  bool realtime = true;     // ask for SCHED_FIFO (and mlockall) on the loop thread
  int priority = 80;        // SCHED_FIFO priority, 1..99
  bool lock_memory = true;  // mlockall when realtime
  // Pin the loop thread to this CPU (with or without realtime): one the process may run on
  // (sched_getaffinity), else the loop's constructor throws InvalidArgument. -1: not pinned.
  // docs/loop.md: what pinning measured, and isolating the CPU (isolcpus, nohz_full, IRQs).
  int cpu = -1;
  Waiter* waiter = nullptr;  // nullptr: MonotonicWaiter for a MonotonicClock, else SleepWaiter
  RealtimeOs* os = nullptr;  // nullptr: system_realtime_os()
};

// Plain data filled on the loop thread without allocation. Reset by start().
struct LoopStats {
  std::uint64_t ticks = 0;            // every tick, periodic or early
  std::uint64_t early_wakes = 0;      // ticks run by notify() before their deadline
  std::uint64_t refused_wakes = 0;    // notifications too soon after a tick or ahead of the rate (no tick)
  std::uint64_t overruns = 0;         // ticks that ended after their period's deadline
  std::uint64_t skipped_periods = 0;  // deadlines passed during an overrun: never ticked
  std::uint64_t tick_errors = 0;      // ticks that returned other than ok
  ResultCode last_error = ResultCode::ok;
  DurationHistogram wake_latency;  // periodic ticks: wake-up time minus deadline
  DurationHistogram tick_time;     // tick duration on the loop's clock
  SchedulerState scheduler;
};

// Applies what options ask (SCHED_FIFO at options.priority, mlockall) to the calling thread and
// returns what it obtained. warning gets one message naming what was refused and how to allow
// it (limits.d or setcap), or stays empty. Setup only: allocates.
MRSKIN_BRIDGE_API SchedulerState apply_realtime(const LoopOptions& options, RealtimeOs& os,
                                                std::string& warning);

class MRSKIN_BRIDGE_API RealtimeLoop {
 public:
  // Throws InvalidArgument for a rate outside 1 Hz .. 20 kHz or a priority outside 1..99.
  RealtimeLoop(Clock& clock, Tickable& tickable, LoopOptions options = {});
  RealtimeLoop(Clock& clock, TickFunction tick, void* context, LoopOptions options = {});
  RealtimeLoop(const RealtimeLoop&) = delete;
  RealtimeLoop& operator=(const RealtimeLoop&) = delete;
  RealtimeLoop(RealtimeLoop&&) = delete;
  RealtimeLoop& operator=(RealtimeLoop&&) = delete;
  ~RealtimeLoop();

  // Control thread. Spawns the loop thread and returns once it has set up its scheduling
  // (stats().scheduler). Returns the one warning of this loop's life when real-time was asked
  // for and refused (empty otherwise, and on later starts). The caller logs it. No-op while
  // running. The first tick runs at once; deadlines follow at start + k * period.
  std::string start();
  // Control thread: wakes the loop, joins it. Idempotent; the destructor calls it. From the
  // tick itself it only asks the loop to end (the next start() or the destructor joins).
  void stop() noexcept;
  [[nodiscard]] bool running() const noexcept;

  // Any thread (the I/O side when a sample arrives): wake the loop for a tick now. The periodic
  // grid does not move. Notifications before the wake coalesce into one tick.
  void notify() noexcept;

  // Without start(): one wait and tick on the calling thread (no scheduling set-up). Returns
  // false, doing nothing, once stop() was requested (until start()). For tests and callers
  // owning the thread.
  bool run_once() noexcept;

  // After stop(), or from inside the tick. live_*() from any thread.
  [[nodiscard]] const LoopStats& stats() const noexcept;
  [[nodiscard]] std::uint64_t live_ticks() const noexcept;
  [[nodiscard]] std::uint64_t live_overruns() const noexcept;
  [[nodiscard]] Duration period() const noexcept;
  // The k-th deadline of the current run's grid (k = 0 is the first tick).
  [[nodiscard]] TimePoint deadline(std::uint64_t k) const noexcept;
  [[nodiscard]] bool early_tick_allowed(TimePoint woke) const noexcept;

 private:
  // Everything else lives behind one pointer: a console linked against this header keeps its
  // ABI when the loop's state changes (docs/api.md, "ABI").
  class Impl;
  std::unique_ptr<Impl> impl_;
};

// Scheduler baseline (what cyclictest measures), to print beside a benchmark's tick percentiles
// taken in the same run: an empty tick at options.rate_hz on a MonotonicClock for at least
// `ticks` ticks, with the loop's own set-up; stats().wake_latency is the baseline.
MRSKIN_BRIDGE_API LoopStats measure_baseline(const LoopOptions& options, std::uint64_t ticks);

}  // namespace mrskin::bridge
