// Shared machinery of the network sources: counters, ordering, robot-clock mapping, the SPSC hand
// over to the tick, and small POSIX socket helpers. Private to the bridge library.
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <deque>
#include <memory>
#include <mutex>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "mrskin/bridge/sources.hpp"
#include "mrskin/driver/relaxed_counter.hpp"

namespace mrskin::bridge::sources {

// The counters, written by an I/O thread (or a loader) and read from any thread.
struct AtomicStats {
  RelaxedCounter accepted;
  std::array<RelaxedCounter, kDropReasonCount> drops{};  // by DropReason
  RelaxedCounter poses;
  RelaxedCounter restarts;
  RelaxedCounter connections;
  RelaxedCounter disconnects;
  RelaxedCounter connect_failures;
  // Counts a drop; true for the first of its reason (the caller then says why, once).
  bool count(DropReason reason) noexcept { return drops.at(static_cast<std::size_t>(reason)).bump() == 0; }
  [[nodiscard]] std::uint64_t count_of(DropReason reason) const noexcept {
    return drops.at(static_cast<std::size_t>(reason)).value();
  }
  [[nodiscard]] SourceStats snapshot() const noexcept;
};

// The operator's side of a source: events for the log, the latest warning for the status line.
// Written off the tick (I/O thread, loader); a mutex guards the text, a counter says when to look.
class SourceEvents {
 public:
  // Out of memory, the event is lost, never the I/O thread: both are noexcept.
  void add(bool warning, std::string_view text) noexcept;
  // make_text() is called, and its text added, only the first time key (< 64) is given: one line
  // per reason, not per message.
  template <class MakeText>
  void once(unsigned key, bool warning, MakeText&& make_text) noexcept {
    const std::uint64_t bit = std::uint64_t{1} << key;
    if ((seen_.fetch_or(bit, std::memory_order_relaxed) & bit) != 0) {
      return;
    }
    try {
      add(warning, make_text());
    } catch (...) {  // NOLINT(bugprone-empty-catch): an event lost to a full heap
    }
  }
  [[nodiscard]] bool seen(unsigned key) const noexcept {
    return (seen_.load(std::memory_order_relaxed) & (std::uint64_t{1} << key)) != 0;
  }
  [[nodiscard]] std::vector<SourceEvent> after(std::uint64_t seq) const;
  [[nodiscard]] std::uint64_t count() const noexcept { return count_.load(std::memory_order_acquire); }
  [[nodiscard]] std::string last_warning() const;

 private:
  static constexpr std::size_t kKept = 64;
  mutable std::mutex mutex_;
  std::deque<SourceEvent> events_;
  std::string last_warning_;
  std::atomic<std::uint64_t> count_{0};
  std::atomic<std::uint64_t> seen_{0};
};

// Keys for SourceEvents::once beyond the drop reasons (0..kDropReasonCount-1).
enum class EventKey : unsigned { device_force = 32, device_pose, device_map, pose_tool, dds_type };

// Robot stamps (ns) outside 0..2^62 (146 years) are out of range: the clock arithmetic stays far
// from overflow whatever a peer sends.
inline constexpr std::int64_t kMaxStampNs = std::int64_t{1} << 62;
[[nodiscard]] inline bool stamp_ok(std::int64_t ns) noexcept { return ns >= 0 && ns <= kMaxStampNs; }

// Checks a sample's fields against the options: non_finite, out_of_range, or nothing.
// The drop is counted, and the first of its reason explained in events.
[[nodiscard]] bool values_ok(const SlaveSample& s, const SourceOptions& o, AtomicStats& stats,
                             SourceEvents& events) noexcept;
// Counts a drop and, the first time for its reason, adds make_text() (why, and the fix).
template <class MakeText>
void drop(AtomicStats& stats, SourceEvents& events, DropReason reason, MakeText&& make_text) noexcept {
  stats.count(reason);
  events.once(static_cast<unsigned>(reason), true, std::forward<MakeText>(make_text));
}

// Per-channel ordering on robot stamps: equal is a duplicate, older is out of order; a run of
// options.restart_after_out_of_order older stamps means the robot restarted.
class OrderGate {
 public:
  enum class Verdict : unsigned char { accept, duplicate, out_of_order, restart };
  explicit OrderGate(std::uint32_t restart_after) noexcept : restart_after_(restart_after) {}
  Verdict check(std::int64_t stamp_ns) noexcept;
  void reset() noexcept { have_ = false; }

 private:
  std::uint32_t restart_after_;
  std::uint32_t backwards_ = 0;
  std::int64_t last_ns_ = 0;
  bool have_ = false;
};

class ClockMapper;
// Applies gate's verdict on robot_ns: a duplicate or an older stamp is dropped and counted (the
// first of each explained by what, "a message" or so), a restart counted and the clock mapping
// reset. True when the sample is taken.
bool admit(OrderGate& gate, std::int64_t robot_ns, ClockMapper& mapper, AtomicStats& stats,
           SourceEvents& events, std::string_view what) noexcept;

// Robot stamp -> host clock: offset = min(arrival - stamp), rising at most drift s/s (follows a
// robot clock that runs slow). The mapped stamp is never later than the arrival.
class ClockMapper {
 public:
  explicit ClockMapper(double drift_s_per_s) noexcept : drift_(drift_s_per_s) {}
  TimePoint map(std::int64_t robot_ns, TimePoint arrival) noexcept;
  void reset() noexcept { have_ = false; }

 private:
  double drift_;
  std::int64_t offset_ns_ = 0;
  TimePoint last_arrival_{};
  bool have_ = false;
};

// A source fed by its own I/O thread. The I/O thread calls publish()/flush_pending(); the tick
// calls latest().
class QueuedSource : public StreamSource {
 public:
  QueuedSource(const SourceOptions& options, Clock* clock);
  bool latest(TimePoint now, SlaveSample& out) noexcept override;
  [[nodiscard]] SourceStats stats() const noexcept override { return stats_.snapshot(); }
  void set_arrival_hook(ArrivalHook hook, void* context) noexcept override;
  [[nodiscard]] std::vector<SourceEvent> events_after(std::uint64_t seq) const override {
    return events_.after(seq);
  }
  [[nodiscard]] std::uint64_t event_count() const noexcept override { return events_.count(); }
  [[nodiscard]] std::string last_warning() const override { return events_.last_warning(); }

 protected:
  // I/O thread. Queues s; when the queue is full it is held and replaces any sample held before
  // (counted queue_full), so the newest always gets through.
  void publish(const SlaveSample& s) noexcept;
  // The same without counting it accepted (a stream-ended marker, SlaveSample::ended).
  void enqueue(const SlaveSample& s) noexcept;
  // I/O thread: retries a held sample; true when nothing is held any more.
  bool flush_pending() noexcept;
  [[nodiscard]] bool has_pending() const noexcept { return pending_valid_; }
  [[nodiscard]] TimePoint now() const noexcept { return clock_->now(); }

  SourceOptions options_;
  AtomicStats stats_;
  SourceEvents events_;

 private:
  void notify() noexcept;
  std::unique_ptr<MonotonicClock> own_clock_;
  Clock* clock_;
  SpscQueue<SlaveSample> queue_;
  SlaveSample pending_{};
  bool pending_valid_ = false;
  std::atomic<ArrivalHook> hook_{nullptr};
  std::atomic<void*> hook_context_{nullptr};
  SlaveSample last_{};  // tick thread
};

// ---- sockets -------------------------------------------------------------------------------
struct Endpoint {
  std::string host;  // numeric or a name; "" when not given
  std::uint16_t port = 0;
};
// "HOST:PORT", "[V6]:PORT", ":PORT". Throws InvalidArgument naming the part.
Endpoint parse_endpoint(std::string_view text, std::string_view uri, bool need_host, bool allow_port_0);

// An owned file descriptor.
class Fd {
 public:
  Fd() = default;
  explicit Fd(int fd) noexcept : fd_(fd) {}
  Fd(const Fd&) = delete;
  Fd& operator=(const Fd&) = delete;
  Fd(Fd&& o) noexcept : fd_(o.release()) {}
  Fd& operator=(Fd&& o) noexcept;
  ~Fd() { reset(); }
  [[nodiscard]] int get() const noexcept { return fd_; }
  [[nodiscard]] bool valid() const noexcept { return fd_ >= 0; }
  int release() noexcept {
    const int fd = fd_;
    fd_ = -1;
    return fd;
  }
  void reset() noexcept;

 private:
  int fd_ = -1;
};

// Binds a socket (SOCK_DGRAM or SOCK_STREAM, non-blocking) to host:port; host "" is loopback
// (127.0.0.1). Streams also listen. Throws mrskin::Error naming the address and the OS error.
Fd bind_socket(const Endpoint& where, int type, std::string_view what);
std::uint16_t bound_port(int fd) noexcept;

// An eventfd that stops an I/O thread.
class StopSignal {
 public:
  StopSignal();
  void raise() noexcept;
  [[nodiscard]] int fd() const noexcept { return fd_.get(); }

 private:
  Fd fd_;
};

// ---- the sources ---------------------------------------------------------------------------
std::unique_ptr<StreamSource> open_replay(const std::string& path, const SourceOptions& options);
// dds://: the ROS 2 topics (absolute ROS names) of the wrench and the pose.
std::unique_ptr<StreamSource> open_dds(const std::string& wrench_topic, const std::string& pose_topic,
                                       const SourceOptions& options, Clock* clock);
// R v for a row-major 3 x 3 R.
[[nodiscard]] inline std::array<double, 3> rotate(const std::array<double, 9>& r, double x, double y,
                                                  double z) noexcept {
  return {r[0] * x + r[1] * y + r[2] * z, r[3] * x + r[4] * y + r[5] * z, r[6] * x + r[7] * y + r[8] * z};
}
std::unique_ptr<StreamSource> open_igtl(const Endpoint& where, bool listen, const SourceOptions& options,
                                        Clock* clock);

}  // namespace mrskin::bridge::sources
