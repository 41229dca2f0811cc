// A network between the slave robot and the bridge, simulated: each sample of an inner source is
// delivered after a random delay (uniform in delay +- jitter) or lost (probability loss), with a
// fixed seed. With jitter, samples can arrive out of order; the bridge must stay consistent and
// passive anyway (50 ms +- 20 ms and 5 % loss, as the product must survive). Allocation-free after
// construction.
#pragma once

#include <cstdint>
#include <random>
#include <vector>

#include "mrskin/bridge/export.hpp"
#include "mrskin/bridge/scene.hpp"

namespace mrskin::bridge {

struct ImpairmentOptions {
  double delay_s = 0.05;
  double jitter_s = 0.02;  // delay uniform in [delay_s - jitter_s, delay_s + jitter_s]
  double loss = 0.05;      // probability a sample never arrives
  std::uint64_t seed = 1;
  std::size_t capacity = 256;  // samples in flight: (delay + jitter) x sample rate, with room
};

struct ImpairmentStats {
  std::uint64_t sent = 0;
  std::uint64_t lost = 0;
  std::uint64_t delivered = 0;
  std::uint64_t reordered = 0;   // delivered after a newer sample had been delivered
  std::uint64_t overflowed = 0;  // more in flight than capacity: dropped
};

class MRSKIN_BRIDGE_API ImpairedSource final : public SlaveSource {
 public:
  // Throws InvalidArgument for a negative delay, jitter above delay, loss outside [0, 1) or zero
  // capacity.
  ImpairedSource(SlaveSource& inner, const ImpairmentOptions& options);
  // Takes the inner source's newest sample (once per new stamp) into the network, and returns the
  // sample that arrived last at or before now (its `received` set to its arrival time).
  bool latest(TimePoint now, SlaveSample& out) noexcept override;
  [[nodiscard]] const ImpairmentStats& stats() const noexcept { return stats_; }

 private:
  struct InFlight {
    SlaveSample sample;
    TimePoint arrival{};
  };
  SlaveSource& inner_;
  ImpairmentOptions options_;
  std::mt19937_64 rng_;
  std::vector<InFlight> flight_;  // unordered pool; slot used when arrival != kFree
  std::size_t in_flight_ = 0;
  SlaveSample last_sent_{};
  SlaveSample delivered_{};
  TimePoint newest_delivered_stamp_{};
  ImpairmentStats stats_{};
};

}  // namespace mrskin::bridge
