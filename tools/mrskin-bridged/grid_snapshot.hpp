// What the daemon's tick and mrskinctl monitor know per cell and per valve, beyond the scalars:
// a host-side coil temperature estimate, and a seqlock that hands fixed-size arrays from the
// tick to the control thread without a lock. Header-only (mrskinctl uses the estimate too).
#pragma once

#include <array>
#include <atomic>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

#include "mrskin/sim/mock_device.hpp"

namespace mrskin::bridged {

// The protocol reports no coil temperature (only the derated flag and an overtemperature fault),
// so the host estimates it: the first-order thermal model of the mock's firmware,
// C dT/dt = R I^2 - (T - T_ambient) / R_th, with the profile's coil resistance, the mock's thermal
// constants (MockOptions: 0.5 J/K, 20 K/W, 25 C) and the currents the host commanded. It cannot
// see heat the host did not cause (the mock's overheat fault). Allocation-free after reset().
class CoilThermalEstimate {
 public:
  void reset(std::size_t valves, double resistance_ohm) {
    const sim::MockOptions mock{};
    resistance_ohm_ = resistance_ohm;
    thermal_resistance_K_per_W_ = mock.coil_thermal_resistance_K_per_W;
    time_constant_s_ = mock.coil_heat_capacity_J_per_K * mock.coil_thermal_resistance_K_per_W;
    ambient_C_ = mock.ambient_C;
    temperature_C_.assign(valves, ambient_C_);
  }
  // current_A held over dt_s (released valves: pass released = true, no current flows).
  void step(std::span<const double> current_A, bool released, double dt_s) noexcept {
    if (!(dt_s > 0.0) || time_constant_s_ <= 0.0) {
      return;
    }
    const double a = -std::expm1(-dt_s / time_constant_s_);  // exact for a constant current
    for (std::size_t v = 0; v < temperature_C_.size(); ++v) {
      const double i_A = released || v >= current_A.size() ? 0.0 : current_A[v];
      const double steady_C = ambient_C_ + resistance_ohm_ * i_A * i_A * thermal_resistance_K_per_W_;
      temperature_C_[v] += (steady_C - temperature_C_[v]) * a;
    }
  }
  [[nodiscard]] std::span<const double> temperature_C() const noexcept { return temperature_C_; }

 private:
  double resistance_ohm_ = 0.0;
  double thermal_resistance_K_per_W_ = 0.0;
  double time_constant_s_ = 0.0;
  double ambient_C_ = 25.0;
  std::vector<double> temperature_C_;
};

// The grid arrays, one writer (the tick) and any number of readers. A seqlock over
// atomics: the writer bumps the sequence to odd, stores the values with release, bumps it to
// even; a reader copies between two loads of the sequence and retries when they differ or are
// odd. The writer never waits; arrays are sized once at setup.
class GridSeqlock {
 public:
  // sensor: the raw readings in the sensors' SI unit (what mrskinctl record --bridge writes).
  // true_n: the mock's true contact force per cell (NaN on hardware). law_n: the tissue law,
  // not clamped; floor_n, ceiling_n: the envelope the target was clamped into (NaN: not loaded).
  enum Array : std::uint8_t {
    force_n,
    displacement_m,
    target_n,
    current_a,
    temperature_c,
    sensor,
    true_n,
    law_n,
    floor_n,
    ceiling_n,
    kArrays
  };
  GridSeqlock() = default;
  GridSeqlock(std::size_t cells, std::size_t valves, std::size_t sensors = 0) {
    for (std::size_t a = 0; a < kArrays; ++a) {
      const std::size_t n = a == current_a || a == temperature_c ? valves : a == sensor ? sensors : cells;
      arrays_.at(a) = std::vector<std::atomic<double>>(n);
    }
  }
  [[nodiscard]] std::size_t size(Array a) const noexcept { return arrays_.at(a).size(); }

  // Tick thread.
  void begin_write(std::int64_t t_ns) noexcept {
    const std::uint64_t s = seq_.load(std::memory_order_relaxed);
    seq_.store(s + 1, std::memory_order_relaxed);
    t_ns_.store(t_ns, std::memory_order_release);  // release: the odd sequence is seen first
  }
  void write(Array a, std::span<const double> values) noexcept {
    std::vector<std::atomic<double>>& dst = arrays_.at(a);
    for (std::size_t i = 0; i < dst.size(); ++i) {
      dst[i].store(i < values.size() ? values[i] : NAN, std::memory_order_release);
    }
  }
  void end_write() noexcept {
    seq_.store(seq_.load(std::memory_order_relaxed) + 1, std::memory_order_release);
  }

  // Any other thread: copies a consistent snapshot into out (resized; allocates on the reader's
  // side only). False when nothing was published yet or every attempt overlapped a write.
  struct Copy {
    std::int64_t t_ns = 0;
    std::array<std::vector<double>, kArrays> arrays;
  };
  bool read(Copy& out, int attempts = 1000) const {
    for (int k = 0; k < attempts; ++k) {
      const std::uint64_t s1 = seq_.load(std::memory_order_acquire);
      if (s1 == 0) {
        return false;
      }
      if ((s1 & 1U) != 0) {
        continue;
      }
      out.t_ns = t_ns_.load(std::memory_order_acquire);
      for (std::size_t a = 0; a < kArrays; ++a) {
        const std::vector<std::atomic<double>>& src = arrays_.at(a);
        std::vector<double>& dst = out.arrays.at(a);
        dst.resize(src.size());
        for (std::size_t i = 0; i < src.size(); ++i) {
          dst[i] = src[i].load(std::memory_order_acquire);
        }
      }
      if (seq_.load(std::memory_order_acquire) == s1) {
        return true;
      }
    }
    return false;
  }

 private:
  std::atomic<std::uint64_t> seq_{0};
  std::atomic<std::int64_t> t_ns_{0};
  std::array<std::vector<std::atomic<double>>, kArrays> arrays_;
};

}  // namespace mrskin::bridged
