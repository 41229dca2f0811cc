#pragma once

#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include "mrskin/bridge/stats.hpp"

namespace mrskin::bridged {

// CPU time per thread of this process over a run, read from /proc/self/task (each thread's
// schedstat, in ns; its stat's utime + stime, in clock ticks, where schedstat is missing). Call
// sample() from the main thread, off the tick: at the start, now and then (a thread that ends
// keeps its last reading) and at the end. Threads of the same name (a DDS stack's pool) add up.
class ThreadCpuMeter {
 public:
  // Reads every thread once; the first call is the run's baseline.
  void sample();
  // Per thread name, the CPU time since the baseline, busiest first.
  [[nodiscard]] std::vector<bridge::BridgeStats::ThreadCpu> totals() const;

 private:
  struct Reading {
    std::string name;
    double baseline_s = 0.0;  // at the first sample, or 0 for a thread started after it
    double last_s = 0.0;
  };
  std::map<std::int64_t, Reading> by_tid_;
  bool started_ = false;
};

// One thread's CPU time in seconds and its name, from the text of /proc/.../task/TID/stat and
// (may be empty) .../schedstat; false when the stat text does not parse. Exposed for the tests.
bool parse_thread_cpu(const std::string& stat_text, const std::string& schedstat_text, long clock_ticks_per_s,
                      std::string& name, double& cpu_s);

}  // namespace mrskin::bridged
