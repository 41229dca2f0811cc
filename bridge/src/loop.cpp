#include "mrskin/bridge/loop.hpp"

#include <linux/capability.h>
#include <poll.h>
#include <pthread.h>
#include <pwd.h>
#include <sched.h>
#include <sys/eventfd.h>
#include <sys/mman.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <sys/timerfd.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cerrno>
#include <cmath>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <system_error>
#include <thread>

#include "mrskin/driver/relaxed_counter.hpp"

namespace mrskin::bridge {

namespace {

constexpr std::int64_t kNsPerS = 1'000'000'000;

timespec to_timespec(TimePoint t) noexcept {
  timespec ts{};
  ts.tv_sec = static_cast<time_t>(t.count() / kNsPerS);
  ts.tv_nsec = static_cast<long>(t.count() % kNsPerS);
  return ts;
}

void drain(int fd) noexcept {
  std::uint64_t value = 0;
  const ssize_t got = read(fd, &value, sizeof value);  // non-blocking: EAGAIN when empty
  static_cast<void>(got);
}

std::string errno_text(int error) { return std::error_code(error, std::generic_category()).message(); }

bool has_cap_ipc_lock() noexcept {
  __user_cap_header_struct header{};
  header.version = _LINUX_CAPABILITY_VERSION_3;
  std::array<__user_cap_data_struct, _LINUX_CAPABILITY_U32S_3> data{};
  // glibc has no capget wrapper; libcap is not worth a dependency for one bit.
  if (syscall(SYS_capget, &header, data.data()) != 0) {  // NOLINT(cppcoreguidelines-pro-type-vararg)
    return false;
  }
  return (data[CAP_TO_INDEX(CAP_IPC_LOCK)].effective & CAP_TO_MASK(CAP_IPC_LOCK)) != 0;
}

std::string limit_text(int resource, const char* unit_suffix, std::uint64_t divisor) {
  rlimit lim{};
  if (getrlimit(resource, &lim) != 0) {
    return "unknown";
  }
  if (lim.rlim_cur == RLIM_INFINITY) {
    return "unlimited";
  }
  return std::to_string(static_cast<std::uint64_t>(lim.rlim_cur) / divisor) + unit_suffix;
}

std::string executable_path() {
  std::array<char, 4096> buf{};
  const ssize_t n = readlink("/proc/self/exe", buf.data(), buf.size() - 1);
  return n > 0 ? std::string(buf.data(), static_cast<std::size_t>(n)) : std::string("BINARY");
}

std::string user_name() {
  passwd entry{};
  passwd* found = nullptr;
  std::array<char, 4096> buf{};
  if (getpwuid_r(geteuid(), &entry, buf.data(), buf.size(), &found) == 0 && found != nullptr) {
    return found->pw_name;
  }
  return "USER";
}

#if defined(MRSKIN_SANITIZED) || defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
constexpr bool kSanitized = true;
#else
constexpr bool kSanitized = false;
#endif

}  // namespace

// --- waiters ------------------------------------------------------------------------------

MonotonicWaiter::MonotonicWaiter()
    : event_fd_(eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC)),
      timer_fd_(timerfd_create(CLOCK_MONOTONIC, TFD_NONBLOCK | TFD_CLOEXEC)) {
  if (event_fd_ < 0 || timer_fd_ < 0) {
    const int error = errno;
    if (event_fd_ >= 0) {
      close(event_fd_);
    }
    if (timer_fd_ >= 0) {
      close(timer_fd_);
    }
    throw Error("real-time loop: cannot create its eventfd/timerfd (" + errno_text(error) +
                "); raise the open-file limit (ulimit -n)");
  }
}

MonotonicWaiter::~MonotonicWaiter() {
  close(event_fd_);
  close(timer_fd_);
}

Waiter::Wake MonotonicWaiter::wait_until(TimePoint deadline) noexcept {
  if (armed_ != deadline) {
    itimerspec spec{};
    // A zero it_value would disarm the timer: the earliest absolute time is 1 ns.
    spec.it_value = to_timespec(std::max(deadline, TimePoint{1}));
    timerfd_settime(timer_fd_, TFD_TIMER_ABSTIME, &spec, nullptr);
    armed_ = deadline;
  }
  std::array<pollfd, 2> fds{{{timer_fd_, POLLIN, 0}, {event_fd_, POLLIN, 0}}};
  for (;;) {
    if (poll(fds.data(), fds.size(), -1) < 0) {
      if (errno == EINTR) {
        continue;
      }
      // Cannot happen with two valid descriptors; keep the period rather than spin.
      MonotonicClock{}.sleep_until(deadline);
      armed_ = TimePoint{-1};
      drain(event_fd_);
      return Wake::deadline;
    }
    if ((fds[0].revents & POLLIN) != 0) {
      drain(timer_fd_);
      armed_ = TimePoint{-1};  // a one-shot timer disarms when it fires
      drain(event_fd_);
      return Wake::deadline;
    }
    if ((fds[1].revents & POLLIN) != 0) {
      drain(event_fd_);
      return Wake::notified;
    }
  }
}

void MonotonicWaiter::notify() noexcept {
  const std::uint64_t one = 1;
  const ssize_t put = write(event_fd_, &one, sizeof one);  // EAGAIN only at 2^64-2 pending
  static_cast<void>(put);
}

void MonotonicWaiter::clear() noexcept { drain(event_fd_); }

Waiter::Wake SleepWaiter::wait_until(TimePoint deadline) noexcept {
  if (clock_.now() < deadline) {
    if (pending_.exchange(false, std::memory_order_acq_rel)) {
      return Wake::notified;
    }
    clock_.sleep_until(deadline);
  }
  pending_.store(false, std::memory_order_release);
  return Wake::deadline;
}

// --- scheduling ---------------------------------------------------------------------------

bool SchedulerState::fifo() const noexcept { return policy == SCHED_FIFO; }

const char* SchedulerState::policy_name() const noexcept {
  switch (policy) {
    case SCHED_OTHER:
      return "SCHED_OTHER";
    case SCHED_FIFO:
      return "SCHED_FIFO";
    case SCHED_RR:
      return "SCHED_RR";
    case SCHED_BATCH:
      return "SCHED_BATCH";
    case SCHED_IDLE:
      return "SCHED_IDLE";
    default:
      return "unknown";
  }
}

int RealtimeOs::set_fifo(int priority) noexcept {
  sched_param param{};
  param.sched_priority = priority;
  return pthread_setschedparam(pthread_self(), SCHED_FIFO, &param);
}

int RealtimeOs::lock_memory() noexcept {
  if (kSanitized) {
    return ENOTSUP;
  }
  rlimit lim{};
  if (getrlimit(RLIMIT_MEMLOCK, &lim) == 0 && lim.rlim_cur != RLIM_INFINITY && !has_cap_ipc_lock()) {
    return ENOMEM;
  }
  return mlockall(MCL_CURRENT | MCL_FUTURE) == 0 ? 0 : errno;
}

int RealtimeOs::pin_cpu(int cpu) noexcept {
  cpu_set_t set;
  CPU_ZERO(&set);
  CPU_SET(static_cast<std::size_t>(cpu), &set);
  return pthread_setaffinity_np(pthread_self(), sizeof(set), &set);
}

void RealtimeOs::query(int& policy, int& priority) noexcept {
  sched_param param{};
  if (pthread_getschedparam(pthread_self(), &policy, &param) != 0) {
    policy = SCHED_OTHER;
    param.sched_priority = 0;
  }
  priority = param.sched_priority;
}

RealtimeOs& system_realtime_os() noexcept {
  static RealtimeOs os;
  return os;
}

SchedulerState apply_realtime(const LoopOptions& options, RealtimeOs& os, std::string& warning) {
  warning.clear();
  SchedulerState state;
  std::string refused;
  if (options.realtime) {
    const int fifo_error = os.set_fifo(options.priority);
    if (fifo_error != 0) {
      refused += "SCHED_FIFO priority " + std::to_string(options.priority) + " (" + errno_text(fifo_error) +
                 "; rtprio limit " + limit_text(RLIMIT_RTPRIO, "", 1) + ")";
    }
    if (options.lock_memory) {
      const int lock_error = os.lock_memory();
      state.memory_locked = lock_error == 0;
      if (lock_error != 0) {
        refused += refused.empty() ? "" : " and ";
        refused += "locked memory (mlockall: ";
        refused += lock_error == ENOTSUP ? std::string("skipped in a sanitizer build")
                   : lock_error == ENOMEM
                       ? "memlock limit " + limit_text(RLIMIT_MEMLOCK, " KiB", 1024) + " without CAP_IPC_LOCK"
                       : errno_text(lock_error);
        refused += ")";
      }
    }
  }
  os.query(state.policy, state.priority);
  std::string pin_warning;
  if (options.cpu >= 0) {
    const int pin_error = os.pin_cpu(options.cpu);
    state.cpu = pin_error == 0 ? options.cpu : -1;
    if (pin_error != 0) {
      pin_warning =
          "mrskin: the loop thread could not be pinned to CPU " + std::to_string(options.cpu) + " (" +
          errno_text(pin_error) + "): it runs on any CPU the process may use. A cpuset or " +
          "systemd's CPUAffinity= may exclude it: pick a CPU from `taskset -pc $$`, or set cpu = -1.";
    }
  }
  if (!refused.empty()) {
    const std::string user = user_name();
    warning =
        "mrskin: the real-time loop runs without " + refused + ", so expect deadline misses under load. " +
        "To allow it, either raise the limits of user " + user +
        " in /etc/security/limits.d/99-mrskin.conf:\n" + "    " + user + "  -  rtprio   " +
        std::to_string(options.priority) + "\n" + "    " + user + "  -  memlock  unlimited\n" +
        "  and log in again (`ulimit -r -l` shows them), or give the binary the " +
        "capabilities:\n    sudo setcap cap_sys_nice,cap_ipc_lock+ep " + executable_path() + "\n" +
        "  (in a container: --cap-add SYS_NICE --cap-add IPC_LOCK). Or set realtime = false to run without.";
  }
  if (!pin_warning.empty()) {
    warning += warning.empty() ? pin_warning : "\n" + pin_warning;
  }
  return state;
}

// --- the loop -----------------------------------------------------------------------------

namespace {

ResultCode call_tickable(void* context, TimePoint now) noexcept {
  return static_cast<Tickable*>(context)->tick(now);
}

}  // namespace

// The loop's state, behind RealtimeLoop's one pointer (docs/api.md, "ABI").
class __attribute__((visibility("hidden"))) RealtimeLoop::Impl {
 public:
  Impl(Clock& clock, TickFunction tick, void* context, LoopOptions options);
  Impl(const Impl&) = delete;
  Impl& operator=(const Impl&) = delete;
  Impl(Impl&&) = delete;
  Impl& operator=(Impl&&) = delete;
  ~Impl();

  std::string start();
  void stop() noexcept;
  [[nodiscard]] bool running() const noexcept { return running_.load(std::memory_order_acquire); }
  void notify() noexcept { waiter_->notify(); }
  bool run_once() noexcept;
  [[nodiscard]] const LoopStats& stats() const noexcept { return stats_; }
  [[nodiscard]] std::uint64_t live_ticks() const noexcept {
    return live_ticks_.load(std::memory_order_acquire);
  }
  [[nodiscard]] std::uint64_t live_overruns() const noexcept { return live_overruns_.value(); }
  [[nodiscard]] Duration period() const noexcept;
  [[nodiscard]] TimePoint deadline(std::uint64_t k) const noexcept;
  [[nodiscard]] bool early_tick_allowed(TimePoint woke) const noexcept;

 private:
  void thread_main() noexcept;
  void reset_run() noexcept;

  Clock& clock_;
  TickFunction tick_;
  void* context_;
  LoopOptions options_;
  double period_ns_;
  std::unique_ptr<Waiter> own_waiter_;  // when options.waiter was nullptr
  Waiter* waiter_;
  RealtimeOs* os_;
  // Grid of the current run.
  bool grid_started_ = false;
  TimePoint start_{};  // the grid's origin: the run's start, or the last early tick
  std::uint64_t k_ = 0;
  TimePoint next_{};
  TimePoint run_start_{};  // the first tick: the tick budget counts from here
  TimePoint last_tick_{};
  LoopStats stats_;
  std::atomic<std::uint64_t> live_ticks_{0};  // release: a watcher that sees it sees the tick's stats
  RelaxedCounter live_overruns_;
  std::atomic<bool> stop_requested_{false};
  std::atomic<bool> running_{false};
  std::atomic<bool> setup_done_{false};
  std::string setup_warning_;
  bool warned_ = false;
  std::mutex control_;  // start/stop from several control threads
  std::thread thread_;
};

RealtimeLoop::Impl::Impl(Clock& clock, TickFunction tick, void* context, LoopOptions options)
    : clock_(clock),
      tick_(tick),
      context_(context),
      options_(options),
      period_ns_(1e9 / options.rate_hz),
      waiter_(options.waiter),
      os_(options.os != nullptr ? options.os : &system_realtime_os()) {
  if (!(options_.rate_hz >= 1.0 && options_.rate_hz <= 20'000.0)) {
    throw InvalidArgument("real-time loop: rate " + std::to_string(options_.rate_hz) +
                          " Hz is outside 1 Hz .. 20 kHz");
  }
  if (options_.priority < 1 || options_.priority > 99) {
    throw InvalidArgument("real-time loop: SCHED_FIFO priority " + std::to_string(options_.priority) +
                          " is outside 1..99");
  }
  if (tick_ == nullptr) {
    throw InvalidArgument("real-time loop: no tick function");
  }
  if (!cpu_allowed(options_.cpu)) {
    throw InvalidArgument("real-time loop: CPU " + std::to_string(options_.cpu) +
                          " is not one this process may run on (allowed: " + allowed_cpus() +
                          "); pick one of them, or -1 for no pinning");
  }
  if (waiter_ == nullptr) {
    if (dynamic_cast<MonotonicClock*>(&clock_) != nullptr) {
      own_waiter_ = std::make_unique<MonotonicWaiter>();
    } else {
      own_waiter_ = std::make_unique<SleepWaiter>(clock_);
    }
    waiter_ = own_waiter_.get();
  }
}

RealtimeLoop::Impl::~Impl() { stop(); }

bool cpu_allowed(int cpu) noexcept {
  if (cpu == -1) {
    return true;
  }
  if (cpu < 0 || cpu >= CPU_SETSIZE) {
    return false;
  }
  cpu_set_t set;
  CPU_ZERO(&set);
  return sched_getaffinity(0, sizeof(set), &set) != 0 || CPU_ISSET(static_cast<std::size_t>(cpu), &set);
}

std::string allowed_cpus() {
  cpu_set_t set;
  CPU_ZERO(&set);
  if (sched_getaffinity(0, sizeof(set), &set) != 0) {
    return "unknown";
  }
  std::string list;
  for (int c = 0; c < CPU_SETSIZE; ++c) {
    if (CPU_ISSET(static_cast<std::size_t>(c), &set)) {
      list += list.empty() ? "" : ",";
      list += std::to_string(c);
    }
  }
  return list;
}

Duration RealtimeLoop::Impl::period() const noexcept { return Duration{std::llround(period_ns_)}; }

TimePoint RealtimeLoop::Impl::deadline(std::uint64_t k) const noexcept {
  // From k, not by adding a rounded period: a non-integral period (3 kHz) does not drift either.
  return start_ + Duration{std::llround(static_cast<double>(k) * period_ns_)};
}

void RealtimeLoop::Impl::reset_run() noexcept {
  stats_ = LoopStats{};
  grid_started_ = false;
  k_ = 0;
  live_ticks_.store(0, std::memory_order_relaxed);
  live_overruns_.set(0);
  stop_requested_.store(false, std::memory_order_release);
  waiter_->clear();
}

bool RealtimeLoop::Impl::early_tick_allowed(TimePoint woke) const noexcept {
  // At least half a period after the last tick, and never more than one tick ahead of the
  // configured rate since the run began: early wakes never raise the tick rate.
  const auto since_last = static_cast<double>((woke - last_tick_).count());
  const auto elapsed = static_cast<double>((woke - run_start_).count());
  return since_last >= 0.5 * period_ns_ &&
         static_cast<double>(stats_.ticks + 1) <= std::floor(elapsed / period_ns_) + 2.0;
}

bool RealtimeLoop::Impl::run_once() noexcept {
  if (stop_requested_.load(std::memory_order_acquire)) {
    return false;
  }
  if (!grid_started_) {
    start_ = clock_.now();
    run_start_ = start_;
    k_ = 0;
    next_ = start_;
    grid_started_ = true;
  }
  TimePoint woke{};
  for (;;) {
    const Waiter::Wake wake = waiter_->wait_until(next_);
    if (stop_requested_.load(std::memory_order_acquire)) {
      return false;
    }
    woke = clock_.now();
    // A notification landing at or after the deadline is the periodic tick, not an early one.
    if (wake == Waiter::Wake::deadline || woke >= next_) {
      stats_.wake_latency.add(std::max<std::int64_t>(0, (woke - next_).count()));
      ++k_;
      next_ = deadline(k_);
      break;
    }
    if (early_tick_allowed(woke)) {
      // The tick moves forward to the sample and the grid follows it, so a stream at the loop's
      // rate is served as it arrives, once per period.
      ++stats_.early_wakes;
      start_ = woke;
      k_ = 1;
      next_ = deadline(k_);
      break;
    }
    // Too soon after the last tick, or ahead of the rate: the periodic tick takes the sample.
    ++stats_.refused_wakes;
  }
  last_tick_ = woke;
  const ResultCode rc = tick_(context_, woke);
  const TimePoint end = clock_.now();
  stats_.tick_time.add((end - woke).count());
  ++stats_.ticks;
  if (rc != ResultCode::ok) {
    ++stats_.tick_errors;
    stats_.last_error = rc;
  }
  if (end > next_) {
    // Overrun: skip every deadline already passed (no burst of catch-up ticks); the next tick
    // is the first grid point at or after now.
    ++stats_.overruns;
    std::uint64_t k =
        k_ + static_cast<std::uint64_t>(static_cast<double>((end - next_).count()) / period_ns_);
    while (deadline(k) < end) {
      ++k;
    }
    while (k > k_ + 1 && deadline(k - 1) >= end) {
      --k;
    }
    stats_.skipped_periods += k - k_;
    k_ = k;
    next_ = deadline(k_);
    live_overruns_.set(stats_.overruns);
  }
  // Last: a watcher that sees the count knows the tick's bookkeeping is done.
  live_ticks_.store(stats_.ticks, std::memory_order_release);
  return true;
}

void RealtimeLoop::Impl::thread_main() noexcept {
  // "mrskin-loop" in top -H, ps -L and /proc/PID/task/TID/comm (the service watchdog test finds
  // the tick thread by it).
  (void)::pthread_setname_np(::pthread_self(), "mrskin-loop");
  try {
    stats_.scheduler = apply_realtime(options_, *os_, setup_warning_);
  } catch (...) {  // out of memory for the warning text: run anyway, without it
    setup_warning_.clear();
  }
  setup_done_.store(true, std::memory_order_release);
  setup_done_.notify_all();
  while (run_once()) {
  }
}

std::string RealtimeLoop::Impl::start() {
  const std::lock_guard lock(control_);
  if (thread_.joinable()) {
    if (running_.load(std::memory_order_acquire)) {
      return {};
    }
    thread_.join();  // stopped from its own tick: it has left run_once()
  }
  reset_run();
  setup_done_.store(false, std::memory_order_relaxed);
  thread_ = std::thread([this] { thread_main(); });
  setup_done_.wait(false, std::memory_order_acquire);
  running_.store(true, std::memory_order_release);
  if (setup_warning_.empty() || warned_) {
    return {};
  }
  warned_ = true;
  return setup_warning_;
}

void RealtimeLoop::Impl::stop() noexcept {
  const std::lock_guard lock(control_);
  stop_requested_.store(true, std::memory_order_release);
  waiter_->notify();
  if (thread_.joinable() && thread_.get_id() != std::this_thread::get_id()) {
    thread_.join();
  }
  running_.store(false, std::memory_order_release);
}

// --- the public face: one pointer to the state ---------------------------------------------

RealtimeLoop::RealtimeLoop(Clock& clock, Tickable& tickable, LoopOptions options)
    : impl_(std::make_unique<Impl>(clock, &call_tickable, &tickable, options)) {}
RealtimeLoop::RealtimeLoop(Clock& clock, TickFunction tick, void* context, LoopOptions options)
    : impl_(std::make_unique<Impl>(clock, tick, context, options)) {}
RealtimeLoop::~RealtimeLoop() = default;
std::string RealtimeLoop::start() { return impl_->start(); }
void RealtimeLoop::stop() noexcept { impl_->stop(); }
bool RealtimeLoop::running() const noexcept { return impl_->running(); }
void RealtimeLoop::notify() noexcept { impl_->notify(); }
bool RealtimeLoop::run_once() noexcept { return impl_->run_once(); }
const LoopStats& RealtimeLoop::stats() const noexcept { return impl_->stats(); }
std::uint64_t RealtimeLoop::live_ticks() const noexcept { return impl_->live_ticks(); }
std::uint64_t RealtimeLoop::live_overruns() const noexcept { return impl_->live_overruns(); }
Duration RealtimeLoop::period() const noexcept { return impl_->period(); }
TimePoint RealtimeLoop::deadline(std::uint64_t k) const noexcept { return impl_->deadline(k); }
bool RealtimeLoop::early_tick_allowed(TimePoint woke) const noexcept {
  return impl_->early_tick_allowed(woke);
}

static_assert(sizeof(RealtimeLoop) == sizeof(void*),
              "RealtimeLoop is one pointer: its state lives in RealtimeLoop::Impl");

// --- baseline -----------------------------------------------------------------------------

namespace {

class EmptyTick final : public Tickable {
 public:
  explicit EmptyTick(std::uint64_t target) noexcept : target_(std::max<std::uint64_t>(target, 1)) {}
  ResultCode tick(TimePoint /*now*/) noexcept override {
    if (++count_ == target_) {
      done_.store(true, std::memory_order_release);
      done_.notify_all();
    }
    return ResultCode::ok;
  }
  void wait() const noexcept { done_.wait(false, std::memory_order_acquire); }

 private:
  std::uint64_t target_;
  std::uint64_t count_ = 0;
  std::atomic<bool> done_{false};
};

}  // namespace

LoopStats measure_baseline(const LoopOptions& options, std::uint64_t ticks) {
  MonotonicClock clock;
  EmptyTick empty(ticks);
  LoopOptions own = options;
  own.waiter = nullptr;
  RealtimeLoop loop(clock, empty, own);
  static_cast<void>(loop.start());
  empty.wait();
  loop.stop();
  return loop.stats();
}

}  // namespace mrskin::bridge
