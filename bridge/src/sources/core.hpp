// Shared machinery of the network sources: counters, ordering, robot-clock mapping, the SPSC hand
// over to the tick, and small POSIX socket helpers. Private to the bridge library.
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <memory>
#include <string>
#include <string_view>

#include "mrskin/bridge/sources.hpp"

namespace mrskin::bridge::sources {

enum class Drop : unsigned char {
  malformed,
  oversized,
  non_finite,
  out_of_range,
  out_of_order,
  duplicate,
  queue_full,
  unsupported,
};

struct AtomicStats {
  std::atomic<std::uint64_t> accepted{0};
  std::array<std::atomic<std::uint64_t>, 8> drops{};  // by Drop
  std::atomic<std::uint64_t> restarts{0};
  std::atomic<std::uint64_t> connections{0};
  std::atomic<std::uint64_t> disconnects{0};
  void count(Drop reason) noexcept {
    drops[static_cast<std::size_t>(reason)].fetch_add(1, std::memory_order_relaxed);
  }
  [[nodiscard]] std::uint64_t count_of(Drop reason) const noexcept {
    return drops[static_cast<std::size_t>(reason)].load(std::memory_order_relaxed);
  }
  [[nodiscard]] SourceStats snapshot() const noexcept;
};

// Robot stamps (ns) outside 0..2^62 (146 years) are out of range: the clock arithmetic stays far
// from overflow whatever a peer sends.
inline constexpr std::int64_t kMaxStampNs = std::int64_t{1} << 62;
[[nodiscard]] inline bool stamp_ok(std::int64_t ns) noexcept { return ns >= 0 && ns <= kMaxStampNs; }

// Checks a sample's fields against the options: non_finite, out_of_range, or nothing.
[[nodiscard]] bool values_ok(const SlaveSample& s, const SourceOptions& o, AtomicStats& stats) noexcept;

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

 protected:
  // I/O thread. Queues s; when the queue is full it is held and replaces any sample held before
  // (counted queue_full), so the newest always gets through.
  void publish(const SlaveSample& s) noexcept;
  // I/O thread: retries a held sample; true when nothing is held any more.
  bool flush_pending() noexcept;
  [[nodiscard]] bool has_pending() const noexcept { return pending_valid_; }
  [[nodiscard]] TimePoint now() const noexcept { return clock_->now(); }

  SourceOptions options_;
  AtomicStats stats_;

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
std::unique_ptr<StreamSource> open_igtl(const Endpoint& where, bool listen, const SourceOptions& options,
                                        Clock* clock);

}  // namespace mrskin::bridge::sources
