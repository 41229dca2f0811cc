// The real-time loop runner: deadlines, early wakes, overruns, scheduling set-up, start/stop
// and allocation, all on a simulated clock or an injected waiter (exact counts, no wall-clock
// timing). The real-clock tests only check that ticks happen and stop works.
#include "mrskin/bridge/loop.hpp"

#include <gtest/gtest.h>
#include <sched.h>

#include <array>
#include <atomic>
#include <cerrno>
#include <condition_variable>
#include <cstdint>
#include <cstdio>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "counting_new.hpp"

namespace mrskin::bridge {
namespace {

using std::chrono::microseconds;
using std::chrono::milliseconds;

// Records tick times into a fixed array; optionally advances the simulated clock inside the tick
// (a slow tick) or notifies the loop from inside it (a sample arriving during the tick).
class Recorder final : public Tickable {
 public:
  explicit Recorder(SimulatedClock* clock = nullptr) noexcept : clock_(clock) {}
  ResultCode tick(TimePoint now) noexcept override {
    if (count_ < times_.size()) {
      times_[count_] = now;
    }
    ++count_;
    if (clock_ != nullptr && count_ == slow_tick_) {
      clock_->advance(slow_by_);
    }
    return result_;
  }
  [[nodiscard]] std::size_t count() const noexcept { return count_; }
  [[nodiscard]] TimePoint at(std::size_t i) const noexcept { return times_.at(i); }
  void make_slow(std::size_t nth, Duration by) noexcept {
    slow_tick_ = nth;
    slow_by_ = by;
  }
  void set_result(ResultCode rc) noexcept { result_ = rc; }

 private:
  SimulatedClock* clock_;
  std::array<TimePoint, 64> times_{};
  std::size_t count_ = 0;
  std::size_t slow_tick_ = 0;
  Duration slow_by_{};
  ResultCode result_ = ResultCode::ok;
};

// Blocks until the test moves the simulated clock to the deadline or notifies: a loop thread in
// lockstep with the test.
class ManualWaiter final : public Waiter {
 public:
  explicit ManualWaiter(SimulatedClock& clock) noexcept : clock_(clock) {}
  Wake wait_until(TimePoint deadline) noexcept override {
    std::unique_lock lock(mutex_);
    cv_.wait(lock, [&] { return pending_ || clock_.now() >= deadline; });
    const bool early = clock_.now() < deadline;
    pending_ = false;
    return early ? Wake::notified : Wake::deadline;
  }
  void notify() noexcept override {
    {
      const std::lock_guard lock(mutex_);
      pending_ = true;
    }
    cv_.notify_all();
  }
  void clear() noexcept override {
    const std::lock_guard lock(mutex_);
    pending_ = false;
  }
  void advance(Duration d) {
    {
      const std::lock_guard lock(mutex_);
      clock_.advance(d);
    }
    cv_.notify_all();
  }

 private:
  SimulatedClock& clock_;
  std::mutex mutex_;
  std::condition_variable cv_;
  bool pending_ = false;
};

// Refuses (or grants) the real-time calls.
class FakeOs final : public RealtimeOs {
 public:
  int fifo_result = EPERM;
  int lock_result = EPERM;
  int fifo_calls = 0;
  int lock_calls = 0;
  int set_fifo(int priority) noexcept override {
    ++fifo_calls;
    if (fifo_result == 0) {
      policy_ = SCHED_FIFO;
      priority_ = priority;
    }
    return fifo_result;
  }
  int lock_memory() noexcept override {
    ++lock_calls;
    return lock_result;
  }
  int pin_result = 0;
  int pinned_cpu = -1;
  int pin_calls = 0;
  int pin_cpu(int cpu) noexcept override {
    ++pin_calls;
    pinned_cpu = pin_result == 0 ? cpu : pinned_cpu;
    return pin_result;
  }
  void query(int& policy, int& priority) noexcept override {
    policy = policy_;
    priority = priority_;
  }

 private:
  int policy_ = SCHED_OTHER;
  int priority_ = 0;
};

void wait_for_ticks(const RealtimeLoop& loop, std::uint64_t n) {
  while (loop.live_ticks() < n) {
    std::this_thread::yield();
  }
}

LoopOptions simulated_options(Waiter* waiter, RealtimeOs* os = nullptr) {
  LoopOptions options;
  options.waiter = waiter;
  options.os = os;
  options.realtime = os != nullptr;  // never SCHED_FIFO/mlockall the test process itself
  return options;
}

constexpr Duration kPeriod = milliseconds(1);

TEST(Loop, TicksOnTheAbsoluteGrid) {
  SimulatedClock clock(TimePoint{12'345});
  Recorder rec;
  RealtimeLoop loop(clock, rec);  // a SimulatedClock gets a SleepWaiter: stepping is exact
  const TimePoint start = clock.now();
  constexpr int kN = 50;
  for (int k = 0; k < kN; ++k) {
    ASSERT_TRUE(loop.run_once());
  }
  EXPECT_EQ(rec.count(), static_cast<std::size_t>(kN));
  for (std::size_t k = 0; k < static_cast<std::size_t>(kN); ++k) {
    EXPECT_EQ(rec.at(k), start + static_cast<std::int64_t>(k) * kPeriod) << k;
  }
  EXPECT_EQ(clock.now(), start + (kN - 1) * kPeriod);
  EXPECT_EQ(loop.stats().ticks, static_cast<std::uint64_t>(kN));
  EXPECT_EQ(loop.stats().overruns, 0U);
  EXPECT_EQ(loop.stats().skipped_periods, 0U);
  EXPECT_EQ(loop.stats().early_wakes, 0U);
  EXPECT_EQ(loop.stats().wake_latency.count(), static_cast<std::uint64_t>(kN));
  EXPECT_EQ(loop.stats().wake_latency.max_ns(), 0);
}

TEST(Loop, NonIntegralPeriodDoesNotDrift) {
  SimulatedClock clock;
  Recorder rec;
  LoopOptions options;
  options.rate_hz = 3000.0;  // 333333.33 ns
  RealtimeLoop loop(clock, rec, options);
  for (int k = 0; k < 3001; ++k) {
    ASSERT_TRUE(loop.run_once());
  }
  EXPECT_EQ(clock.now(), TimePoint{std::chrono::seconds(1)});  // tick 3000 lands on 1 s exactly
}

TEST(Loop, ThreadedLockstepTicksExactlyOncePerPeriod) {
  SimulatedClock clock;
  ManualWaiter waiter(clock);
  Recorder rec;
  RealtimeLoop loop(clock, rec, simulated_options(&waiter));
  const TimePoint start = clock.now();
  EXPECT_EQ(loop.start(), "");
  wait_for_ticks(loop, 1);  // the first tick runs at once
  constexpr std::uint64_t kN = 40;
  for (std::uint64_t k = 1; k < kN; ++k) {
    waiter.advance(kPeriod);
    wait_for_ticks(loop, k + 1);
  }
  loop.stop();
  ASSERT_EQ(rec.count(), kN);
  for (std::size_t k = 0; k < kN; ++k) {
    EXPECT_EQ(rec.at(k), start + static_cast<std::int64_t>(k) * kPeriod);
  }
  EXPECT_EQ(loop.stats().ticks, kN);
  EXPECT_EQ(loop.stats().overruns, 0U);
  EXPECT_EQ(loop.stats().early_wakes, 0U);
}

TEST(Loop, SlowTickCountsOverrunSkipsPeriodsAndNeverBursts) {
  SimulatedClock clock;
  Recorder rec(&clock);
  rec.make_slow(3, 3 * kPeriod + microseconds(500));  // tick 3 (at 2 ms) takes 3.5 periods
  RealtimeLoop loop(clock, rec);
  for (int k = 0; k < 6; ++k) {
    ASSERT_TRUE(loop.run_once());
  }
  // 0, 1, 2 (ends at 5.5 ms: deadlines 3, 4, 5 ms passed), then 6, 7, 8: no catch-up burst.
  const std::array<std::int64_t, 6> expected_ms{0, 1, 2, 6, 7, 8};
  for (std::size_t k = 0; k < expected_ms.size(); ++k) {
    EXPECT_EQ(rec.at(k), TimePoint{milliseconds(expected_ms[k])}) << k;
  }
  EXPECT_EQ(loop.stats().overruns, 1U);
  EXPECT_EQ(loop.stats().skipped_periods, 3U);
  EXPECT_EQ(loop.stats().ticks, 6U);
  EXPECT_EQ(loop.stats().tick_time.max_ns(), (3 * kPeriod + microseconds(500)).count());
  EXPECT_EQ(loop.live_overruns(), 1U);
}

TEST(Loop, TickEndingExactlyOnTheDeadlineIsNoOverrun) {
  SimulatedClock clock;
  Recorder rec(&clock);
  rec.make_slow(1, kPeriod);
  RealtimeLoop loop(clock, rec);
  for (int k = 0; k < 3; ++k) {
    ASSERT_TRUE(loop.run_once());
  }
  EXPECT_EQ(rec.at(1), TimePoint{milliseconds(1)});
  EXPECT_EQ(rec.at(2), TimePoint{milliseconds(2)});
  EXPECT_EQ(loop.stats().overruns, 0U);
  EXPECT_EQ(loop.stats().skipped_periods, 0U);
}

TEST(Loop, NotifyWakesEarlyAndTheGridFollowsTheTick) {
  SimulatedClock clock;
  Recorder rec;
  RealtimeLoop loop(clock, rec);
  ASSERT_TRUE(loop.run_once());  // tick at 0
  clock.advance(microseconds(600));
  loop.notify();
  loop.notify();                 // coalesces with the first
  ASSERT_TRUE(loop.run_once());  // early tick at 0.6 ms
  ASSERT_TRUE(loop.run_once());  // periodic, one period after it: 1.6 ms
  ASSERT_TRUE(loop.run_once());  // 2.6 ms
  EXPECT_EQ(rec.at(1), TimePoint{microseconds(600)});
  EXPECT_EQ(rec.at(2), TimePoint{microseconds(1600)});
  EXPECT_EQ(rec.at(3), TimePoint{microseconds(2600)});
  EXPECT_EQ(loop.stats().ticks, 4U);
  EXPECT_EQ(loop.stats().early_wakes, 1U);
  EXPECT_EQ(loop.stats().wake_latency.count(), 3U);  // periodic ticks only
  EXPECT_EQ(loop.stats().overruns, 0U);
}

TEST(Loop, AWakeWithinHalfAPeriodOfATickWaitsForTheDeadline) {
  SimulatedClock clock;
  Recorder rec;
  RealtimeLoop loop(clock, rec);
  ASSERT_TRUE(loop.run_once());  // tick at 0
  clock.advance(microseconds(300));
  loop.notify();
  ASSERT_TRUE(loop.run_once());  // not at 0.3 ms: the periodic tick at 1 ms reads the sample
  EXPECT_EQ(rec.at(1), TimePoint{milliseconds(1)});
  EXPECT_EQ(loop.stats().early_wakes, 0U);
  EXPECT_EQ(loop.stats().refused_wakes, 1U);
}

// A stream twice as fast as the loop, notifying at every sample: the loop ticks at most once per
// period over the run (one tick ahead at most), never at the stream's rate.
TEST(Loop, NotificationsFasterThanTheRateNeverRaiseIt) {
  SimulatedClock clock;
  Recorder rec;
  RealtimeLoop loop(clock, rec);
  ASSERT_TRUE(loop.run_once());
  const TimePoint start = clock.now();
  for (int k = 0; k < 2000; ++k) {
    clock.advance(microseconds(500));
    loop.notify();
    ASSERT_TRUE(loop.run_once());
    const double periods = static_cast<double>((clock.now() - start).count()) / 1e6;
    ASSERT_LE(static_cast<double>(loop.stats().ticks), std::floor(periods) + 2.0) << "at " << k;
  }
  EXPECT_GT(loop.stats().early_wakes, 0U);
  EXPECT_GT(loop.stats().refused_wakes, 0U);
}

TEST(Loop, NotifyFromAnotherThreadWakesABlockedLoop) {
  SimulatedClock clock;
  ManualWaiter waiter(clock);
  Recorder rec;
  RealtimeLoop loop(clock, rec, simulated_options(&waiter));
  EXPECT_EQ(loop.start(), "");
  wait_for_ticks(loop, 1);
  waiter.advance(microseconds(600));
  loop.notify();  // the clock never reaches 1 ms: only the notification can wake it
  wait_for_ticks(loop, 2);
  waiter.advance(microseconds(1000));
  wait_for_ticks(loop, 3);
  loop.stop();
  EXPECT_EQ(rec.at(1), TimePoint{microseconds(600)});
  EXPECT_EQ(rec.at(2), TimePoint{microseconds(1600)});
  EXPECT_EQ(loop.stats().early_wakes, 1U);
  EXPECT_EQ(loop.stats().ticks, 3U);
}

TEST(Loop, TickErrorsAreCounted) {
  SimulatedClock clock;
  Recorder rec;
  rec.set_result(ResultCode::device_fault);
  RealtimeLoop loop(clock, rec);
  ASSERT_TRUE(loop.run_once());
  ASSERT_TRUE(loop.run_once());
  EXPECT_EQ(loop.stats().tick_errors, 2U);
  EXPECT_EQ(loop.stats().last_error, ResultCode::device_fault);
}

TEST(Loop, FunctionPointerTick) {
  SimulatedClock clock;
  int calls = 0;
  RealtimeLoop loop(
      clock,
      [](void* context, TimePoint /*now*/) noexcept {
        ++*static_cast<int*>(context);
        return ResultCode::ok;
      },
      &calls);
  ASSERT_TRUE(loop.run_once());
  ASSERT_TRUE(loop.run_once());
  EXPECT_EQ(calls, 2);
}

TEST(Loop, RejectsRatesAndPrioritiesOutOfRange) {
  SimulatedClock clock;
  Recorder rec;
  for (const double rate : {0.5, 20'001.0, -1.0, std::nan("")}) {
    LoopOptions options;
    options.rate_hz = rate;
    EXPECT_THROW(RealtimeLoop(clock, rec, options), InvalidArgument) << rate;
  }
  LoopOptions options;
  options.priority = 0;
  EXPECT_THROW(RealtimeLoop(clock, rec, options), InvalidArgument);
  options.priority = 80;
  options.rate_hz = 20'000.0;
  EXPECT_NO_THROW(RealtimeLoop(clock, rec, options));
}

// The CPUs this process may run on (the test must not assume CPU 0 is one).
std::vector<int> allowed_cpus() {
  cpu_set_t set;
  CPU_ZERO(&set);
  std::vector<int> cpus;
  if (sched_getaffinity(0, sizeof(set), &set) == 0) {
    for (int c = 0; c < CPU_SETSIZE; ++c) {
      if (CPU_ISSET(static_cast<std::size_t>(c), &set)) {
        cpus.push_back(c);
      }
    }
  }
  return cpus;
}

TEST(Loop, RejectsACpuTheProcessMayNotRunOn) {
  SimulatedClock clock;
  Recorder rec;
  for (const int cpu : {-2, CPU_SETSIZE, CPU_SETSIZE + 5}) {
    LoopOptions options;
    options.cpu = cpu;
    try {
      RealtimeLoop loop(clock, rec, options);
      ADD_FAILURE() << "CPU " << cpu << " was taken";
    } catch (const InvalidArgument& e) {
      EXPECT_NE(std::string(e.what()).find("is not one this process may run on (allowed: "),
                std::string::npos)
          << e.what();
    }
  }
  LoopOptions options;
  options.cpu = allowed_cpus().front();
  EXPECT_NO_THROW(RealtimeLoop(clock, rec, options));
}

// --- scheduling set-up --------------------------------------------------------------------

TEST(LoopRealtime, PinsTheLoopThreadToTheCpuAskedEvenWithoutRealtime) {
  FakeOs os;
  LoopOptions options;
  options.realtime = false;
  options.cpu = 1;
  std::string warning = "stale";
  const SchedulerState state = apply_realtime(options, os, warning);
  EXPECT_EQ(warning, "");
  EXPECT_EQ(os.pin_calls, 1);
  EXPECT_EQ(os.pinned_cpu, 1);
  EXPECT_EQ(state.cpu, 1);
  EXPECT_EQ(os.fifo_calls + os.lock_calls, 0);
}

TEST(LoopRealtime, ARefusedPinIsNamedAndTheStatsSayNotPinned) {
  FakeOs os;
  os.fifo_result = 0;
  os.lock_result = 0;
  os.pin_result = EINVAL;
  LoopOptions options;
  options.cpu = 3;
  std::string warning;
  const SchedulerState state = apply_realtime(options, os, warning);
  EXPECT_EQ(state.cpu, -1);
  EXPECT_TRUE(state.fifo());
  EXPECT_NE(warning.find("could not be pinned to CPU 3"), std::string::npos) << warning;
  EXPECT_NE(warning.find("taskset -pc"), std::string::npos) << warning;
  EXPECT_EQ(warning.find("SCHED_FIFO priority"), std::string::npos) << warning;  // that part was granted
}

TEST(LoopThread, APinnedLoopTicksOnItsCpu) {
  // The real sched_setaffinity on the last CPU the process may use (not SCHED_FIFO: a test
  // process never asks for it).
  const int cpu = allowed_cpus().back();
  struct CpuRecorder final : Tickable {
    std::atomic<int> seen{-2};
    std::atomic<int> elsewhere{0};
    ResultCode tick(TimePoint /*now*/) noexcept override {
      const int c = sched_getcpu();
      seen.store(c);
      if (c != expected) {
        elsewhere.fetch_add(1);
      }
      return ResultCode::ok;
    }
    int expected = -1;
  } rec;
  rec.expected = cpu;
  MonotonicClock clock;
  LoopOptions options;
  options.rate_hz = 2'000.0;
  options.realtime = false;
  options.cpu = cpu;
  RealtimeLoop loop(clock, rec, options);
  EXPECT_EQ(loop.start(), "");
  wait_for_ticks(loop, 50);
  loop.stop();
  EXPECT_EQ(loop.stats().scheduler.cpu, cpu);
  EXPECT_EQ(rec.seen.load(), cpu);
  EXPECT_EQ(rec.elsewhere.load(), 0);
}

TEST(LoopRealtime, RefusedGivesExactlyOneWarningWithTheFix) {
  SimulatedClock clock;
  ManualWaiter waiter(clock);
  FakeOs os;
  Recorder rec;
  RealtimeLoop loop(clock, rec, simulated_options(&waiter, &os));
  const std::string warning = loop.start();
  loop.stop();
  EXPECT_NE(warning.find("SCHED_FIFO priority 80"), std::string::npos) << warning;
  EXPECT_NE(warning.find("/etc/security/limits.d/"), std::string::npos) << warning;
  EXPECT_NE(warning.find("rtprio   80"), std::string::npos) << warning;
  EXPECT_NE(warning.find("memlock  unlimited"), std::string::npos) << warning;
  EXPECT_NE(warning.find("setcap cap_sys_nice,cap_ipc_lock+ep /"), std::string::npos) << warning;
  EXPECT_EQ(loop.stats().scheduler.policy, SCHED_OTHER);
  EXPECT_STREQ(loop.stats().scheduler.policy_name(), "SCHED_OTHER");
  EXPECT_FALSE(loop.stats().scheduler.memory_locked);
  // Once per loop: a restart refused again says nothing more, but the stats still tell.
  EXPECT_EQ(loop.start(), "");
  loop.stop();
  EXPECT_EQ(os.fifo_calls, 2);
  EXPECT_FALSE(loop.stats().scheduler.fifo());
}

TEST(LoopRealtime, GrantedGivesNoWarningAndFifoInTheStats) {
  SimulatedClock clock;
  ManualWaiter waiter(clock);
  FakeOs os;
  os.fifo_result = 0;
  os.lock_result = 0;
  Recorder rec;
  LoopOptions options = simulated_options(&waiter, &os);
  options.priority = 42;
  RealtimeLoop loop(clock, rec, options);
  EXPECT_EQ(loop.start(), "");
  loop.stop();
  EXPECT_TRUE(loop.stats().scheduler.fifo());
  EXPECT_STREQ(loop.stats().scheduler.policy_name(), "SCHED_FIFO");
  EXPECT_EQ(loop.stats().scheduler.priority, 42);
  EXPECT_TRUE(loop.stats().scheduler.memory_locked);
  EXPECT_EQ(os.lock_calls, 1);
}

TEST(LoopRealtime, OnlyTheRefusedPartIsNamed) {
  FakeOs os;
  os.fifo_result = 0;
  os.lock_result = ENOMEM;
  LoopOptions options;
  std::string warning;
  const SchedulerState state = apply_realtime(options, os, warning);
  EXPECT_TRUE(state.fifo());
  EXPECT_FALSE(state.memory_locked);
  EXPECT_EQ(warning.find("SCHED_FIFO priority"), std::string::npos) << warning;
  EXPECT_NE(warning.find("memlock limit"), std::string::npos) << warning;
}

TEST(LoopRealtime, NotAskedMeansNoCallsAndNoWarning) {
  FakeOs os;
  LoopOptions options;
  options.realtime = false;
  std::string warning = "stale";
  const SchedulerState state = apply_realtime(options, os, warning);
  EXPECT_EQ(warning, "");
  EXPECT_EQ(os.fifo_calls + os.lock_calls, 0);
  EXPECT_FALSE(state.fifo());
}

// --- start / stop -------------------------------------------------------------------------

TEST(LoopThread, StopWakesALoopWaitingForItsDeadline) {
  SimulatedClock clock;
  ManualWaiter waiter(clock);  // the clock never moves: only stop() can end the wait
  Recorder rec;
  FakeOs os;
  RealtimeLoop loop(clock, rec, simulated_options(&waiter, &os));
  static_cast<void>(loop.start());
  wait_for_ticks(loop, 1);
  std::thread control([&] { loop.stop(); });
  control.join();
  EXPECT_FALSE(loop.running());
  EXPECT_EQ(rec.count(), 1U);
  loop.stop();  // idempotent
}

TEST(LoopThread, StartStopTwiceResetsTheRun) {
  SimulatedClock clock;
  ManualWaiter waiter(clock);
  Recorder rec;
  FakeOs os;
  RealtimeLoop loop(clock, rec, simulated_options(&waiter, &os));
  for (int run = 0; run < 2; ++run) {
    static_cast<void>(loop.start());
    EXPECT_TRUE(loop.running());
    static_cast<void>(loop.start());  // no-op while running
    wait_for_ticks(loop, 1);
    waiter.advance(kPeriod);
    wait_for_ticks(loop, 2);
    loop.stop();
    EXPECT_FALSE(loop.running());
    EXPECT_EQ(loop.stats().ticks, 2U) << run;  // stats are per run
  }
  EXPECT_EQ(rec.count(), 4U);
  // The second run's grid starts where it started, at 1 ms.
  EXPECT_EQ(rec.at(2), TimePoint{milliseconds(1)});
  EXPECT_EQ(rec.at(3), TimePoint{milliseconds(2)});
}

TEST(LoopThread, DestructorStops) {
  SimulatedClock clock;
  ManualWaiter waiter(clock);
  Recorder rec;
  FakeOs os;
  {
    RealtimeLoop loop(clock, rec, simulated_options(&waiter, &os));
    static_cast<void>(loop.start());
    wait_for_ticks(loop, 1);
  }
  EXPECT_EQ(rec.count(), 1U);
}

// A tick that ends the loop on its third tick of each run.
class StopsItself final : public Tickable {
 public:
  RealtimeLoop* loop = nullptr;
  ResultCode tick(TimePoint /*now*/) noexcept override {
    if (++count_ % 3 == 0) {
      loop->stop();
    }
    return ResultCode::ok;
  }

 private:
  int count_ = 0;
};

TEST(LoopThread, StopFromTheTickThenStartAgain) {
  SimulatedClock clock;  // free-running SleepWaiter: the loop jumps the clock
  StopsItself tick;
  RealtimeLoop loop(clock, tick, simulated_options(nullptr));
  tick.loop = &loop;
  for (int run = 0; run < 2; ++run) {
    static_cast<void>(loop.start());
    while (loop.running()) {
      std::this_thread::yield();
    }
    loop.stop();  // joins the thread that asked itself to stop
    EXPECT_EQ(loop.stats().ticks, 3U) << run;
  }
}

TEST(LoopThread, RealClockSmokeAt10kHz) {
  MonotonicClock clock;
  Recorder rec;
  LoopOptions options;
  options.rate_hz = 10'000.0;
  options.realtime = false;  // never SCHED_FIFO/mlockall a test process
  RealtimeLoop loop(clock, rec, options);
  EXPECT_EQ(loop.start(), "");
  wait_for_ticks(loop, 100);
  loop.notify();
  loop.stop();
  EXPECT_GE(loop.stats().ticks, 100U);
  EXPECT_EQ(loop.stats().ticks, loop.stats().wake_latency.count() + loop.stats().early_wakes);
}

TEST(LoopThread, MonotonicWaiterWakesOnNotifyAndOnItsDeadline) {
  MonotonicWaiter waiter;
  MonotonicClock clock;
  Waiter::Wake wake = Waiter::Wake::deadline;
  std::thread waiting([&] { wake = waiter.wait_until(clock.now() + std::chrono::hours(1)); });
  waiter.notify();
  waiting.join();
  EXPECT_EQ(wake, Waiter::Wake::notified);
  // A wait reaching its deadline consumes a pending notification.
  waiter.notify();
  EXPECT_EQ(waiter.wait_until(clock.now() - milliseconds(1)), Waiter::Wake::deadline);
  EXPECT_EQ(waiter.wait_until(clock.now() + microseconds(200)), Waiter::Wake::deadline);
  waiter.notify();
  waiter.clear();
  EXPECT_EQ(waiter.wait_until(clock.now() + microseconds(200)), Waiter::Wake::deadline);
}

// --- allocation ---------------------------------------------------------------------------

TEST(LoopAllocation, NoHeapAllocationPerTick) {
  SimulatedClock clock;
  Recorder rec(&clock);
  rec.make_slow(5000, 3 * kPeriod + microseconds(500));  // the overrun path too
  RealtimeLoop loop(clock, rec);
  ASSERT_TRUE(loop.run_once());
  const std::uint64_t before = test::allocation_count();
  for (int k = 0; k < 10'000; ++k) {
    if (k % 7 == 0) {
      clock.advance(microseconds(600));
      loop.notify();  // the early-wake path
    }
    ASSERT_TRUE(loop.run_once());
  }
  EXPECT_EQ(test::allocation_count() - before, 0U);
  EXPECT_EQ(loop.stats().ticks, 10'001U);
  EXPECT_EQ(loop.stats().overruns, 1U);
  EXPECT_GT(loop.stats().early_wakes, 0U);
}

TEST(LoopAllocation, NoHeapAllocationOnTheRealLoopThread) {
  MonotonicClock clock;
  Recorder rec;
  LoopOptions options;
  options.rate_hz = 20'000.0;
  options.realtime = false;
  RealtimeLoop loop(clock, rec, options);
  static_cast<void>(loop.start());
  wait_for_ticks(loop, 10);
  const std::uint64_t before = test::allocation_count();
  wait_for_ticks(loop, 10'010);  // this thread only spins: nothing else allocates
  const std::uint64_t after = test::allocation_count();
  loop.stop();
  EXPECT_EQ(after - before, 0U);
}

// Prints the scheduler baseline (wake-up latency of an empty tick). Not a gate: run by hand,
//   bridge_loop_test --gtest_also_run_disabled_tests --gtest_filter='*Baseline*'
TEST(LoopBaseline, DISABLED_PrintsWakeLatency) {
  for (const double rate : {1000.0, 10'000.0}) {
    for (const bool realtime : {false, true}) {
      LoopOptions options;
      options.rate_hz = rate;
      options.realtime = realtime;
      const LoopStats stats = measure_baseline(options, 10'000);
      const auto& lat = stats.wake_latency;
      std::printf(
          "baseline %.0f Hz %s prio %d locked %d: %llu ticks, wake latency p50 %.1f us p99 %.1f us "
          "p99.9 %.1f us max %.1f us, overruns %llu\n",
          rate, stats.scheduler.policy_name(), stats.scheduler.priority,
          stats.scheduler.memory_locked ? 1 : 0, static_cast<unsigned long long>(stats.ticks),
          lat.percentile_ns(0.5) / 1e3, lat.percentile_ns(0.99) / 1e3, lat.percentile_ns(0.999) / 1e3,
          static_cast<double>(lat.max_ns()) / 1e3, static_cast<unsigned long long>(stats.overruns));
      EXPECT_GE(stats.ticks, 10'000U);
    }
  }
}

}  // namespace
}  // namespace mrskin::bridge
