// A statistics count that its writer thread(s) bump and any thread reads: the transports' and
// the sources' counters, the mock's injected faults, the tick's counts mirrored for the console.
#pragma once

#include <atomic>
#include <cstdint>

namespace mrskin {

// Relaxed is right because each count stands alone: no other data is published through it, so a
// reader needs an untorn, eventually current value, not an order against other memory. A count
// that does publish (RealtimeLoop's tick count: who sees it sees that tick's stats) needs
// release/acquire instead. Wait-free and allocation-free: fit for the tick.
class RelaxedCounter {
 public:
  // Adds n; returns the count before it (0: this was the first).
  std::uint64_t bump(std::uint64_t n = 1) noexcept { return count_.fetch_add(n, std::memory_order_relaxed); }
  // Mirrors a count its one writer keeps in a plain variable (or resets it).
  void set(std::uint64_t value) noexcept { count_.store(value, std::memory_order_relaxed); }
  [[nodiscard]] std::uint64_t value() const noexcept { return count_.load(std::memory_order_relaxed); }

 private:
  std::atomic<std::uint64_t> count_{0};
};

}  // namespace mrskin
