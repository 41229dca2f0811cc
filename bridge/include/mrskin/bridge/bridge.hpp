// The bridge loop: slave stream -> tissue model -> per-cell targets inside the renderable
// envelope -> valve currents -> frames. step(now) is the tick; it never allocates, locks,
// blocks, logs or throws.
#pragma once

#include <atomic>
#include <cstdint>
#include <span>
#include <thread>
#include <vector>

#include "mrskin/bridge/scene.hpp"
#include "mrskin/bridge/stats.hpp"
#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/plant.hpp"
#include "mrskin/driver/session.hpp"

namespace mrskin::bridge {

struct BridgeOptions {
  double rate_hz = 1000.0;
  double contact_threshold_m = 50e-6;  // a cell deeper than this is in contact
  double max_force_N = 2.0;            // device range
  double stale_hold_s = 0.1;           // hold the last tissue model this long...
  double stale_fade_s = 0.2;           // ...then fade to released over this long
  double stiffness_filter_s = 0.02;    // time constant of the online stiffness estimate
  double rate_filter_s = 0.02;         // time constant of the indentation-rate filter
  double unload_rate_m_per_s = 2e-3;   // faster withdrawal than this counts as unloading
  int allocation_sweeps = 8;           // coordinate-descent sweeps per tick
  PlaceholderParams model{};           // nominal device model the controller inverts
};

// Ground truth for scoring (the mock's true contact forces); optional.
class ForceTruth {
 public:
  ForceTruth() = default;
  ForceTruth(const ForceTruth&) = delete;
  ForceTruth& operator=(const ForceTruth&) = delete;
  ForceTruth(ForceTruth&&) = delete;
  ForceTruth& operator=(ForceTruth&&) = delete;
  virtual ~ForceTruth() = default;
  virtual void true_forces(std::span<double> out_N) const noexcept = 0;
};

class Bridge {
 public:
  // Setup: allocates everything the tick needs. Throws InvalidArgument on bad options.
  Bridge(DeviceSession& session, SlaveSource& source, BridgeOptions options = {});
  Bridge(const Bridge&) = delete;
  Bridge& operator=(const Bridge&) = delete;
  Bridge(Bridge&&) = delete;
  Bridge& operator=(Bridge&&) = delete;
  ~Bridge();

  void set_force_truth(const ForceTruth* truth) noexcept { truth_ = truth; }
  // Enables the device (call before the first step).
  ResultCode enable() noexcept;

  // One tick at time now. Real-time safe.
  ResultCode step(TimePoint now) noexcept;

  // Or let the library run the loop on its own thread at rate_hz against clock.
  void start(Clock& clock);
  void stop() noexcept;
  [[nodiscard]] bool running() const noexcept { return running_.load(std::memory_order_acquire); }

  // Statistics; read after stop() or from the tick thread. live_*() are safe from any thread.
  [[nodiscard]] const BridgeStats& stats() const noexcept { return stats_; }
  [[nodiscard]] std::uint64_t live_ticks() const noexcept {
    return live_ticks_.load(std::memory_order_relaxed);
  }
  [[nodiscard]] double live_rms_error_N() const noexcept {
    return live_rms_N_.load(std::memory_order_relaxed);
  }
  [[nodiscard]] double live_stiffness_N_per_m() const noexcept {
    return live_stiffness_.load(std::memory_order_relaxed);
  }
  [[nodiscard]] std::span<const double> targets_N() const noexcept { return target_N_; }
  [[nodiscard]] double tick_period_s() const noexcept { return 1.0 / options_.rate_hz; }
  void set_perf_clock(const Clock* clock) noexcept { perf_clock_ = clock; }

 private:
  void compute_targets(TimePoint now) noexcept;
  void allocate_currents() noexcept;
  void score() noexcept;

  DeviceSession& session_;
  SlaveSource& source_;
  BridgeOptions options_;
  GridLayout layout_;
  const ForceTruth* truth_ = nullptr;
  const Clock* perf_clock_ = nullptr;
  MonotonicClock default_perf_clock_;
  std::vector<double> indentation_m_;
  std::vector<double> target_N_;
  std::vector<double> demand_N_;
  std::vector<double> current_A_;
  std::vector<double> valve_yield_N_;
  std::vector<double> residual_N_;
  std::vector<double> truth_N_;
  std::vector<std::uint8_t> contact_;
  std::vector<std::uint8_t> loading_;
  std::vector<double> previous_indentation_m_;
  std::vector<double> rate_m_per_s_;
  SlaveSample slave_{};
  double stiffness_N_per_m_ = 0.0;
  double damping_N_s_per_m_ = 0.0;
  double model_gain_ = 0.0;  // 1 fresh, fading to 0 when stale
  TimePoint last_tick_{};
  bool have_last_tick_ = false;
  BridgeStats stats_;
  std::atomic<std::uint64_t> live_ticks_{0};
  std::atomic<double> live_rms_N_{0.0};
  std::atomic<double> live_stiffness_{0.0};
  std::atomic<bool> running_{false};
  std::thread thread_;
};

}  // namespace mrskin::bridge
