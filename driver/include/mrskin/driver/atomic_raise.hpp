// Raising an atomic to a value unless it already holds as much, from any number of threads
// without a lock: the strongest pending request wins (Bridge::request, the daemon's requests:
// an e-stop is never overwritten by an enable), and a simulated clock never runs backwards.
#pragma once

#include <atomic>

namespace mrskin {

// Leaves a at max(a, wanted). Acquires what the thread that last raised it released, whether or
// not this call raises it (a sleeper on a simulated clock sees what was written before the advance).
template <class T>
void atomic_raise(std::atomic<T>& a, T wanted) noexcept {
  T current = a.load(std::memory_order_acquire);
  while (wanted > current && !a.compare_exchange_weak(current, wanted, std::memory_order_acq_rel)) {
  }
}

}  // namespace mrskin
