// The hand-off from the tick to Python: a TickWatcher that, every `decimation`-th rendered tick,
// copies the tick's targets and forces into a preallocated slot and queues the slot's index.
// The tick never allocates, locks or touches Python; a consumer thread (holding the GIL) takes
// the slots and gives them back. Two SPSC queues of slot indices: filled (tick -> consumer) and
// free (consumer -> tick); with no free slot the tick drops the sample and counts it.
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/driver/force_truth.hpp"
#include "mrskin/driver/spsc_queue.hpp"

namespace mrskin::python {

class TickRecorder final : public bridge::TickWatcher {
 public:
  // inner: called first on every tick (the truth scorer, or nullptr); truth: the mock's (or
  // nullptr on hardware). Setup: allocates every slot.
  TickRecorder(bridge::TickWatcher* inner, const ForceTruth* truth, std::size_t cells,
               std::uint64_t decimation, std::size_t slots);
  void on_tick(const bridge::TickView& tick, bridge::BridgeStats& stats) noexcept override;

  // One recorded tick, valid until give_back(slot).
  struct Sample {
    double t_s = 0.0;
    std::span<const double> target_N;
    std::span<const double> observed_force_N;
    std::span<const double> true_force_N;  // empty without a truth
  };
  // Consumer side: the oldest filled slot, or false.
  bool take(std::uint32_t& slot) noexcept { return filled_.try_pop(slot); }
  [[nodiscard]] Sample sample(std::uint32_t slot) const noexcept;
  void give_back(std::uint32_t slot) noexcept { (void)free_.try_push(slot); }

  [[nodiscard]] bool has_truth() const noexcept { return truth_ != nullptr; }
  [[nodiscard]] std::size_t pending() const noexcept { return filled_.size_approx(); }
  [[nodiscard]] std::size_t slots() const noexcept { return slots_; }
  [[nodiscard]] std::uint64_t recorded() const noexcept { return recorded_.load(std::memory_order_relaxed); }
  [[nodiscard]] std::uint64_t dropped() const noexcept { return dropped_.load(std::memory_order_relaxed); }

 private:
  bridge::TickWatcher* inner_;
  const ForceTruth* truth_;
  std::size_t cells_;
  std::uint64_t decimation_;
  std::size_t slots_;
  std::size_t stride_;  // doubles per slot: time, then three rows of cells
  std::vector<double> pool_;
  SpscQueue<std::uint32_t> filled_;
  SpscQueue<std::uint32_t> free_;
  std::uint64_t ticks_ = 0;  // tick thread only
  std::atomic<std::uint64_t> recorded_{0};
  std::atomic<std::uint64_t> dropped_{0};
};

}  // namespace mrskin::python
