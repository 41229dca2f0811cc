// The hand-off of the device session between the tick and the control thread (a fault dump, a
// device lease). A Dekker handshake on two seq_cst flags: the tick announces itself and steps
// only while no reader is in; a reader announces itself and waits until the tick is out. The
// tick never blocks and never touches the session while a reader holds it; a reader waits at
// most its deadline. One reader at a time: the control thread.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <thread>

#include "mrskin/driver/relaxed_counter.hpp"

namespace mrskin::bridged {

class SessionGate {
 public:
  // Tick side: true when the tick may use the session (end_tick() after), false while a reader
  // holds it (the tick skips its step).
  bool try_tick() noexcept {
    in_tick_.store(true, std::memory_order_seq_cst);
    if (reader_.load(std::memory_order_seq_cst)) {
      in_tick_.store(false, std::memory_order_seq_cst);
      gated_ticks_.bump();
      return false;
    }
    return true;
  }
  void end_tick() noexcept { in_tick_.store(false, std::memory_order_seq_cst); }

  // Reader side: true once the tick is out (end_read() after); false when it did not yield
  // within wait (the reader is out again). Yields while it waits: at most a tick or two.
  bool try_read(std::chrono::steady_clock::duration wait) noexcept {
    reader_.store(true, std::memory_order_seq_cst);
    const auto give_up = std::chrono::steady_clock::now() + wait;
    while (in_tick_.load(std::memory_order_seq_cst)) {
      if (std::chrono::steady_clock::now() > give_up) {
        reader_.store(false, std::memory_order_seq_cst);
        return false;
      }
      std::this_thread::yield();
    }
    return true;
  }
  void end_read() noexcept { reader_.store(false, std::memory_order_seq_cst); }

  // Ticks skipped because a reader held the session.
  [[nodiscard]] std::uint64_t gated_ticks() const noexcept { return gated_ticks_.value(); }

 private:
  std::atomic<bool> in_tick_{false};
  std::atomic<bool> reader_{false};
  RelaxedCounter gated_ticks_;
};

}  // namespace mrskin::bridged
