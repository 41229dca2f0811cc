// Loop statistics: plain data, filled without allocation on the tick thread.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "mrskin/bridge/drop_reason.hpp"
#include "mrskin/bridge/export.hpp"
#include "mrskin/driver/histogram.hpp"

namespace mrskin::bridge {

using mrskin::DurationHistogram;

// Relative errors from 0 to 100 % in 0.1 % bins (the last bin holds everything above): a fixed
// array, so the tick can fill it.
class MRSKIN_BRIDGE_API RelativeErrorHistogram {
 public:
  void add(double relative) noexcept;
  // Upper edge of the bin holding quantile q; 0 when empty.
  [[nodiscard]] double percentile(double q) const noexcept;
  [[nodiscard]] std::uint64_t count() const noexcept { return count_; }

 private:
  static constexpr std::size_t kBins = 1001;
  static constexpr double kBinWidth = 1e-3;
  std::array<std::uint64_t, kBins> bins_{};
  std::uint64_t count_ = 0;
};

// Forces from 1 mN to 100 N in bins 1 % wide (smaller forces in the first bin, larger in the
// last), with the exact maximum: a fixed array, so the tick can fill it.
class MRSKIN_BRIDGE_API ForceHistogram {
 public:
  void add(double force_N) noexcept;
  // Upper edge of the bin holding quantile q (0 for the first bin, the exact maximum for the
  // last); 0 when empty.
  [[nodiscard]] double percentile_N(double q) const noexcept;
  [[nodiscard]] double max_N() const noexcept { return max_N_; }
  [[nodiscard]] std::uint64_t count() const noexcept { return count_; }

 private:
  static constexpr double kLow_N = 1e-3;
  static constexpr double kRatio = 1.01;
  static constexpr std::size_t kBins = 1160;  // 1 mN * 1.01^1158 > 100 N
  std::array<std::uint32_t, kBins> bins_{};
  std::uint64_t count_ = 0;
  double max_N_ = 0.0;
};

struct MRSKIN_BRIDGE_API BridgeStats {
  std::uint64_t ticks = 0;
  std::uint64_t overruns = 0;         // ticks whose work exceeded the period
  std::uint64_t skipped_periods = 0;  // periods skipped to catch up (never burst)
  std::uint64_t send_failures = 0;
  std::uint64_t unchanged_sends_skipped = 0;  // ticks whose currents equalled the last sent
  std::uint64_t slave_samples = 0;            // ticks that had a valid slave sample
  // Set by the owner of the source after the run (mrskin-bridged): samples the source took and
  // dropped (malformed, out of range, out of order, duplicate, ...; docs/sources.md).
  std::uint64_t samples_accepted = 0;
  std::uint64_t samples_dropped = 0;
  DropCounts samples_dropped_by_reason{};  // by DropReason (drop_reason.hpp)
  // The contact force the stream carried (each fresh sample, N): what the robot sent.
  ForceHistogram slave_force;
  std::uint64_t stale_ticks = 0;  // ticks rendering without fresh slave data
  DurationHistogram tick_time;
  // Processing latency: from the tick that consumes a new robot sample to the frame carrying
  // its effect handed to the transport. End to end: from the sample's arrival (its stamp on
  // the loop's clock) to that frame.
  DurationHistogram processing_latency;
  DurationHistogram end_to_end_latency;
  // Rendered-force error: the plant's true force minus the tissue law clamped into the
  // envelope, scored on cells the finger presses or holds (by the finger's true motion when
  // the truth knows it, else by the controller's role), deeper than the contact threshold.
  std::uint64_t force_samples = 0;
  double force_sq_error_sum_N2 = 0.0;
  double force_max_abs_error_N = 0.0;
  RelativeErrorHistogram relative_error;  // where the clamped target is >= 0.3 N
  // The same scored samples against the law at the finger's true depth and rate (truth only):
  // this also counts what the observer's depth and rate estimates get wrong (rate noise on a
  // heavily damped tissue, or the lag of filtering it), which the target above hides.
  double true_state_sq_error_sum_N2 = 0.0;
  RelativeErrorHistogram true_state_relative_error;
  // While the finger retreats: the true force minus the tissue law (semi-active valves can only
  // release, so this is reported apart from the loading/holding error).
  std::uint64_t release_samples = 0;
  double release_sq_error_sum_N2 = 0.0;
  // The same scored samples against the tissue law itself, not clamped into the envelope (only
  // capped at max_force_N, the device's range): what the tissue would have pushed (truth only).
  struct Unclamped {
    double sq_error_sum_N2 = 0.0;                      // at the observer's state
    RelativeErrorHistogram relative_error;             // where that law is >= 0.3 N
    double true_state_sq_error_sum_N2 = 0.0;           // at the finger's true state
    RelativeErrorHistogram true_state_relative_error;  // where that law is >= 0.3 N
  } unclamped;
  std::uint64_t target_cell_ticks = 0;   // loaded cell-ticks
  std::uint64_t clamped_cell_ticks = 0;  // ...whose target lay outside the envelope
  // The clamped cell-ticks by cause (docs/statistics.md, `clamped`): below the floor, the floor's
  // largest part; above the ceiling, the valves' highest allowed current. And the force between
  // the law and the clamped target: felt but not in the tissue (floor), in the tissue but not felt
  // (ceiling).
  struct ClampCauses {
    std::uint64_t floor_viscous = 0;   // drag of the flow through open valves, or the fluid's push
    std::uint64_t floor_membrane = 0;  // the pad membrane at the depth
    std::uint64_t floor_p0 = 0;        // the reservoir's pre-pressure on the pad
    std::uint64_t ceiling = 0;
    double floor_excess_sum_N = 0.0;
    double ceiling_missed_sum_N = 0.0;
  } clamp_causes;
  std::uint64_t observer_errors = 0;     // ticks whose observer update failed (estimate held)
  std::uint64_t inverse_errors = 0;      // ticks whose allocation failed (currents held)
  std::uint64_t inverse_cached = 0;      // ticks on which nothing was dirty: no allocation work
  std::uint64_t sensor_faults = 0;       // sensors found stuck, noisy or offset (left out of the fit)
  std::uint64_t sensor_fault_halts = 0;  // ...leaving a cell unread: valves released, device disabled
  double max_current_A = 0.0;            // largest valve current commanded
  double inverse_residual_sum_N = 0.0;   // per tick: the allocation's residual norm (fast model)
  // Passivity observer at the rendered ports (sum over cells of the integral of F v dt, with F
  // the target force and v the indentation rate): negative means the rendering gave energy.
  double passivity_energy_J = 0.0;
  double passivity_min_energy_J = 0.0;
  std::uint64_t active_ticks = 0;  // ticks on which the energy was below -passivity_tolerance_J
  // Bus load of the session's traffic (fraction of the bus), set by the caller after the run:
  // the busier direction of `bus` when the bus is modelled, else packets per 1 ms report.
  double bus_load = 0.0;
  // The bus measured on the mock's bus model (eval::fill_bus_stats), set after the run. kind is
  // "none" when nothing measured it (a real transport, or mock://?bus=none).
  struct Direction {
    double load = 0.0;          // fraction of the bus (docs/statistics.md, `bus`)
    std::uint64_t packets = 0;  // delivered
    std::uint64_t carried = 0;  // HID reports or CAN frames
    std::uint64_t bytes = 0;    // carried in them
    std::uint64_t dropped = 0;  // packets lost to the bus
    std::uint64_t unsent = 0;   // packets with no form on the bus's framing
    double max_wait_s = 0.0;    // longest from handed to the bus to delivered
  };
  struct Bus {
    const char* kind = "none";  // a string literal (sim::to_string(MockBusKind))
    Direction host_to_device;
    Direction device_to_host;
    std::uint64_t enobufs = 0;  // CAN host writes refused past txqueuelen (retried)
  } bus;
  std::uint64_t stream_stalls = 0;  // times the slave stream went from fresh to stale
  // Set by the owner of the session and the source after the run (mrskin-bridged): the link's
  // errors by kind (SessionCounters), the device's FAULT entries (e-stops included), and the
  // stream's connections, disconnections and restarts (SourceStats).
  struct Link {
    std::uint64_t sequence_gaps = 0;
    std::uint64_t duplicates = 0;
    std::uint64_t undecodable = 0;  // CRC failures included
    std::uint64_t crc = 0;
    std::uint64_t telemetry_timeouts = 0;
    std::uint64_t disconnects = 0;
    std::uint64_t reconnects = 0;
  } link;
  std::uint64_t device_faults = 0;
  std::uint64_t stream_connections = 0;
  std::uint64_t stream_disconnects = 0;
  std::uint64_t stream_restarts = 0;
  // CPU time per thread name over the run, busiest first, and the run's wall time it is a share
  // of: set by mrskin-bridged from /proc after the run (never on the tick thread); empty elsewhere.
  struct ThreadCpu {
    std::string name;         // as the thread named itself (mrskin-loop, mrskin-mock, ...)
    std::uint64_t count = 0;  // threads of that name
    double cpu_s = 0.0;
  };
  std::vector<ThreadCpu> threads;
  double threads_wall_s = 0.0;

  [[nodiscard]] double force_rms_error_N() const noexcept;
  [[nodiscard]] double release_rms_error_N() const noexcept;
  [[nodiscard]] double true_state_rms_error_N() const noexcept;
  [[nodiscard]] double clamped_fraction() const noexcept;
  [[nodiscard]] double unclamped_rms_error_N() const noexcept;
  [[nodiscard]] double unclamped_true_state_rms_error_N() const noexcept;
  // Mean over the clamped cell-ticks of |law - clamped target|: the force the surgeon missed.
  [[nodiscard]] double clamped_missed_force_mean_N() const noexcept;
};

// The statistics' JSON layout (docs/statistics.md): raised when a key changes meaning or goes;
// new keys may come without it.
inline constexpr int kStatisticsFormatVersion = 1;

// JSON text of the statistics (allocates: call off the tick thread). Every key: docs/statistics.md.
MRSKIN_BRIDGE_API std::string to_json(const BridgeStats& stats, double tick_period_s);

}  // namespace mrskin::bridge
