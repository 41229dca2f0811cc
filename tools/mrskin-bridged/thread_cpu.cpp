#include "thread_cpu.hpp"

#include <unistd.h>

#include <algorithm>
#include <charconv>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <sstream>
#include <system_error>

namespace mrskin::bridged {

namespace {

std::string read_text(const std::filesystem::path& path) {
  std::ifstream in(path);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

}  // namespace

bool parse_thread_cpu(const std::string& stat_text, const std::string& schedstat_text, long clock_ticks_per_s,
                      std::string& name, double& cpu_s) {
  // "TID (comm) S ppid ...": comm may hold spaces and parentheses, so it ends at the last ')'.
  const std::size_t open = stat_text.find('(');
  const std::size_t close = stat_text.rfind(')');
  if (open == std::string::npos || close == std::string::npos || close < open) {
    return false;
  }
  name = stat_text.substr(open + 1, close - open - 1);
  // schedstat: time on the CPU (ns), time waiting to run (ns), timeslices.
  std::uint64_t run_ns = 0;
  const char* first = schedstat_text.data();
  const char* last = first + schedstat_text.size();
  if (!schedstat_text.empty() && std::from_chars(first, last, run_ns).ec == std::errc{}) {
    cpu_s = static_cast<double>(run_ns) * 1e-9;
    return true;
  }
  // stat after the comm: state is field 3, utime and stime fields 14 and 15 (proc(5)).
  std::istringstream rest(stat_text.substr(close + 1));
  std::string field;
  std::uint64_t utime = 0;
  std::uint64_t stime = 0;
  for (int k = 3; k <= 15 && rest >> field; ++k) {
    if (k == 14 || k == 15) {
      std::uint64_t v = 0;
      if (std::from_chars(field.data(), field.data() + field.size(), v).ec != std::errc{}) {
        return false;
      }
      (k == 14 ? utime : stime) = v;
      if (k == 15) {
        cpu_s = static_cast<double>(utime + stime) / static_cast<double>(std::max(1L, clock_ticks_per_s));
        return true;
      }
    }
  }
  return false;
}

void ThreadCpuMeter::sample() {
  const long ticks_per_s = ::sysconf(_SC_CLK_TCK);
  std::error_code ec;
  for (const std::filesystem::directory_entry& task :
       std::filesystem::directory_iterator("/proc/self/task", ec)) {
    std::int64_t tid = 0;
    const std::string id = task.path().filename().string();
    if (std::from_chars(id.data(), id.data() + id.size(), tid).ec != std::errc{}) {
      continue;
    }
    std::string name;
    double cpu_s = 0.0;
    if (!parse_thread_cpu(read_text(task.path() / "stat"), read_text(task.path() / "schedstat"), ticks_per_s,
                          name, cpu_s)) {
      continue;  // the thread ended while we read it
    }
    auto [it, added] = by_tid_.try_emplace(tid);
    Reading& r = it->second;
    r.name = name;  // a thread names itself after it starts
    if (added) {
      r.baseline_s = started_ ? 0.0 : cpu_s;
    }
    r.last_s = std::max(r.last_s, cpu_s);
  }
  started_ = true;
}

std::vector<bridge::BridgeStats::ThreadCpu> ThreadCpuMeter::totals() const {
  std::vector<bridge::BridgeStats::ThreadCpu> out;
  for (const auto& entry : by_tid_) {
    const Reading& r = entry.second;
    const auto same = std::find_if(out.begin(), out.end(), [&](const auto& t) { return t.name == r.name; });
    const double used_s = std::max(0.0, r.last_s - r.baseline_s);
    if (same == out.end()) {
      out.push_back({r.name, 1, used_s});
    } else {
      ++same->count;
      same->cpu_s += used_s;
    }
  }
  std::sort(out.begin(), out.end(), [](const auto& a, const auto& b) { return a.cpu_s > b.cpu_s; });
  return out;
}

}  // namespace mrskin::bridged
