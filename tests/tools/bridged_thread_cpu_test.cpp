// CPU time per thread (tools/mrskin-bridged/thread_cpu.hpp): /proc's text parsed as proc(5) gives
// it, and the meter charges each named thread what it spent since the baseline, ended or not.
#include <gtest/gtest.h>
#include <pthread.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <ctime>
#include <string>
#include <thread>

#include "thread_cpu.hpp"

namespace {

using mrskin::bridged::parse_thread_cpu;
using mrskin::bridged::ThreadCpuMeter;

// A stat line as the kernel writes it: utime 250 and stime 50 clock ticks (fields 14 and 15).
const std::string kStat =
    "4242 (a (b) c) S 1 4242 4242 0 -1 4194368 100 0 0 0 250 50 0 0 20 0 3 0 12345 1000 10 "
    "18446744073709551615 1 1 0 0 0 0 0 0 0 0 0 0 17 1 0 0 0 0 0";

TEST(ThreadCpu, SchedstatGivesNanoseconds) {
  std::string name;
  double cpu_s = 0.0;
  ASSERT_TRUE(parse_thread_cpu(kStat, "1500000000 20000 7\n", 100, name, cpu_s));
  EXPECT_EQ(name, "a (b) c");  // the name ends at the last parenthesis
  EXPECT_DOUBLE_EQ(cpu_s, 1.5);
}

TEST(ThreadCpu, WithoutSchedstatUtimePlusStimeInClockTicks) {
  std::string name;
  double cpu_s = 0.0;
  ASSERT_TRUE(parse_thread_cpu(kStat, "", 100, name, cpu_s));
  EXPECT_DOUBLE_EQ(cpu_s, 3.0);  // (250 + 50) / 100
}

TEST(ThreadCpu, MalformedTextIsRefused) {
  std::string name;
  double cpu_s = 0.0;
  EXPECT_FALSE(parse_thread_cpu("", "", 100, name, cpu_s));
  EXPECT_FALSE(parse_thread_cpu("4242 no parenthesis S 1", "", 100, name, cpu_s));
  EXPECT_FALSE(parse_thread_cpu("4242 (short) S 1 2 3", "", 100, name, cpu_s));
  EXPECT_FALSE(parse_thread_cpu("4242 (x) S 1 2 3 4 5 6 7 8 9 10 -5 7", "", 100, name, cpu_s));
}

// Spins until this thread has used `cpu` of processor time (its own clock, not the wall's: a
// loaded machine that preempts it makes the spin longer, never the CPU time shorter).
double thread_cpu_s() {
  timespec t{};
  (void)::clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return static_cast<double>(t.tv_sec) + 1e-9 * static_cast<double>(t.tv_nsec);
}
void spin_for(std::chrono::milliseconds cpu) {
  const double end_s = thread_cpu_s() + 1e-3 * static_cast<double>(cpu.count());
  volatile unsigned sink = 0;
  while (thread_cpu_s() < end_s) {
    sink = sink + 1;
  }
}

TEST(ThreadCpu, AnEndedThreadKeepsWhatItSpentAndTheBaselineIsNotCharged) {
  spin_for(std::chrono::milliseconds(100));  // the main thread's start-up: before the baseline
  ThreadCpuMeter meter;
  meter.sample();
  std::thread worker([&meter] {
    (void)::pthread_setname_np(::pthread_self(), "cpu-test-spin");
    spin_for(std::chrono::milliseconds(150));
    meter.sample();  // its last reading, from inside it (it ends before the next sample)
  });
  worker.join();
  meter.sample();
  const auto totals = meter.totals();
  const auto spin =
      std::find_if(totals.begin(), totals.end(), [](const auto& t) { return t.name == "cpu-test-spin"; });
  ASSERT_NE(spin, totals.end());
  EXPECT_EQ(spin->count, 1U);
  EXPECT_GE(spin->cpu_s, 0.14);  // it spun 150 ms of its own CPU time (stat: 10 ms ticks)
  EXPECT_LE(spin->cpu_s, 1.0);
  for (const auto& t : totals) {
    if (t.name != "cpu-test-spin") {
      EXPECT_LT(t.cpu_s, 0.09) << t.name << ": the 100 ms before the baseline is not the run's";
    }
  }
}

}  // namespace
