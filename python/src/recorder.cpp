#include "recorder.hpp"

#include <algorithm>

namespace mrskin::python {

TickRecorder::TickRecorder(bridge::TickWatcher* inner, const ForceTruth* truth, std::size_t cells,
                           std::uint64_t decimation, std::size_t slots)
    : inner_(inner),
      truth_(truth),
      cells_(cells),
      decimation_(std::max<std::uint64_t>(decimation, 1)),
      slots_(slots),
      stride_(1 + 3 * cells),
      pool_(slots * stride_, 0.0),
      filled_(slots),
      free_(slots) {
  for (std::uint32_t s = 0; s < slots_; ++s) {
    (void)free_.try_push(s);
  }
}

void TickRecorder::on_tick(const bridge::TickView& tick, bridge::BridgeStats& stats) noexcept {
  if (inner_ != nullptr) {
    inner_->on_tick(tick, stats);
  }
  if (ticks_++ % decimation_ != 0) {
    return;
  }
  std::uint32_t slot = 0;
  if (!free_.try_pop(slot)) {
    dropped_.fetch_add(1, std::memory_order_relaxed);  // the consumer fell behind
    return;
  }
  double* row = pool_.data() + slot * stride_;
  row[0] = tick.since_start_s();
  const auto copy = [this](std::span<const double> from, double* to) {
    std::copy_n(from.begin(), std::min(from.size(), cells_), to);
  };
  copy(tick.target_N(), row + 1);
  copy(tick.observed_force_N(), row + 1 + cells_);
  if (truth_ != nullptr) {
    truth_->true_forces(std::span<double>(row + 1 + 2 * cells_, cells_));
  }
  (void)filled_.try_push(slot);  // never full: it holds every slot
  recorded_.fetch_add(1, std::memory_order_relaxed);
}

TickRecorder::Sample TickRecorder::sample(std::uint32_t slot) const noexcept {
  const double* row = pool_.data() + slot * stride_;
  Sample s;
  s.t_s = row[0];
  s.target_N = {row + 1, cells_};
  s.observed_force_N = {row + 1 + cells_, cells_};
  if (truth_ != nullptr) {
    s.true_force_N = {row + 1 + 2 * cells_, cells_};
  }
  return s;
}

}  // namespace mrskin::python
