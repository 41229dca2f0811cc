// The bridge loop: slave stream -> tissue model -> per-cell impedance targets -> the inverse's
// one allocation over the shared valves (targets clamped into the renderable envelope) ->
// valve currents -> frames. The cells' indentation and rate come from the observer, which reads
// the device's sensors through the nominal network model of the profile read from the device.
// step(now) is the tick; it never allocates, locks, blocks, logs or throws.
#pragma once

#include <cstdint>
#include <memory>
#include <span>
#include <string>

#include "mrskin/bridge/export.hpp"
#include "mrskin/bridge/loop.hpp"
#include "mrskin/bridge/mapping.hpp"
#include "mrskin/bridge/scene.hpp"
#include "mrskin/bridge/sensor_faults.hpp"
#include "mrskin/bridge/stats.hpp"
#include "mrskin/bridge/tissue.hpp"
#include "mrskin/driver/bus_budget_check.hpp"
#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/force_truth.hpp"
#include "mrskin/driver/model/inverse.hpp"
#include "mrskin/driver/model/observer.hpp"
#include "mrskin/driver/model/profile.hpp"
#include "mrskin/driver/session.hpp"

namespace mrskin::bridge {

// The estimator's defaults for the bridge: Hunt-Crossley fitted online, a soft prior (rendered
// until the fit is confident), hold 0.1 s then fade over 0.2 s when the stream stops.
MRSKIN_BRIDGE_API TissueEstimatorOptions default_estimator_options() noexcept;

struct BridgeOptions {
  double rate_hz = 1000.0;
  double contact_threshold_m = model::ContactThresholds{}.depth_m;  // a cell deeper than this is in contact
  double max_force_N = 2.0;                                         // device range
  // The online tissue estimate: the law fitted, its prior, and the stale policy (hold, then fade
  // to released: hold_s, fade_s).
  TissueEstimatorOptions estimator = default_estimator_options();
  // Where on the skin a slave contact renders (TOML [mapping]), and how far around the mapped
  // contact point the cells take the current estimate (cell pitches; at least the tip radius).
  WorkspaceMapping mapping{};
  double footprint_cells = 1.5;
  // The passivity observer integrates F dx on the observed depth, whose noise (~3 um RMS, ~20 um
  // peaks) at up to 2 N swings the energy by tens of uJ without any energy being made: deficits
  // within this count as passive.
  double passivity_tolerance_J = 50e-6;
  double unload_rate_m_per_s = model::ContactThresholds{}.hold_rate_m_per_s;  // rates within +-this hold...
  double load_exit_rate_m_per_s = 0.5e-3;  // ...but a loading cell loads until its rate is below this
  double unload_retreat_m = 30e-6;         // a cell unloads after retreating this far from its peak...
  double unload_filter_s = 5e-3;           // ...on its depth smoothed with this time constant
  double contact_force_N = model::ContactThresholds{}.force_N;  // estimated force below this: no finger
  // Integral feedback on the observer's force, 1/s: corrects what the quasi-static inverse does
  // not know (the cell's fluid history, coil lag); frozen while the target is clamped.
  double feedback_gain_per_s = 30.0;
  bool freeze_feedback_while_holding = false;
  // A cell whose passages let out less than this (the observer's network flows) is sealed: more
  // current cannot raise its force, so the feedback does not wind up asking for it (the surplus
  // pressurised the next press). The regularised network's creep through a locked passage is
  // ~1e-10 m^3/s; a flowing press moves ~1e-6.
  double sealed_outflow_m3_per_s = 1e-9;
  // Currents moved along the steel's play (the observer's model) so each valve reaches the yield
  // the inverse asked for on the anhysteretic curve: the band's upper edge going up, its lower
  // edge coming down.
  bool compensate_hysteresis = true;
  // A loading cell whose observed force is below its request holds its valves at the request's
  // threshold until the force gets there (the quasi-static feed-forward assumes the compliance
  // has filled). docs/bridge.md, "What the tuning measured".
  bool lock_while_short = true;
  // With lock_while_short: a loading cell is short below its law too (at most the envelope's
  // ceiling; by more than one period of a sealed cell's rise, 4 /s x the law), not only below its
  // request. The request is the law plus the feedback's correction, which holds wind down where
  // the unit's valves hold more than the model says (-0.06 N on `thigh`, seed 2); below its law
  // but above that request, the cell leaked through the feed-forward's currents as the finger
  // slowed into its next hold, and a semi-active cell cannot win that force back. Over seeds 1-8
  // every organ scene's RMS and p95 fell (hand 0.0162 -> 0.0123 N, 3.3 -> 2.2 %); docs/bridge.md,
  // "Short of the law".
  bool lock_short_of_law = true;
  // A holding cell whose force is above its target by more than this fraction drains with every
  // valve open and is sealed (highest allowed current) once it gets there, until the finger
  // moves: the settling figure after a fast press (docs/bridge.md, Settling). Only on a unit
  // whose cell takes at least a tick to empty through an open passage (the default 5x5: 1.7 s);
  // fingertip-16x16 and palm-64x64 empty in microseconds, so a drain there ends at the open
  // floor before it can be sealed (docs/bridge.md, "Where the 16x16's hold goes").
  bool drain_then_seal = true;
  double drain_open_fraction = 0.05;
  // With drain_then_seal: a loading cell whose observed force is above the law at its observed
  // state by more than this fraction has every valve open that tick. Over seeds 1-8 it lowered
  // every organ scene's RMS (hand 0.020 -> 0.016 N, force_step 0.053 -> 0.042 N) and raised no
  // organ scene's p95 (docs/bridge.md, "Opening a loading cell above its law"). Infinity: off.
  double loading_open_fraction = 0.2;
  // A holding cell's valves stay at least this fraction above the threshold of its target, so
  // model error does not leak the trapped volume away. Off: slow loading that reads as a hold
  // then overshoots (docs/bridge.md, "What the tuning measured").
  double hold_margin = 0.0;
  bool realtime = true;           // SCHED_FIFO + mlockall on the library's loop thread (start())
  double resend_period_s = 0.05;  // unchanged currents are sent again only this often
  int rt_priority = 80;
  int loop_cpu = -1;  // the library's loop thread pinned to this CPU (LoopOptions::cpu); -1: not pinned
  double feedback_limit_N = 0.5;
  model::ObserverOptions observer{};
  // One Gauss-Newton step a tick on every component (small_component_steps; the library's default
  // solves a small one whole).
  model::InverseOptions inverse{.small_component_steps = 1};
  // Stuck, noisy and offset sensors (sensor_faults.hpp): a faulty sensor leaves the observer's
  // fit; when a fluid cell is left with no healthy sensor the bridge releases the valves and
  // disables the device, and refuses enable until it is rebuilt.
  SensorFaultOptions sensor_faults{};
  // The unit's bus budget at rate_hz (mrskin/driver/bus_budget_check.hpp): refused with
  // BusOverloaded when the traffic does not fit the transport's bus; off only to measure what a
  // bus does with traffic that does not fit (the mock's bus model tests).
  bool check_bus_budget = true;
  // Scoring (eval::TruthScorer): relative errors count where the target is at least this.
  double relative_error_floor_N = 0.3;
  // The lengths and forces above, and the scenes' tissue laws, are stated for the reference
  // design (the default 5x5: 2 N at 5 mm). On a unit of another design point (profile [design])
  // the bridge renders them at its own: lengths times indentation_m / 5 mm, forces times
  // force_range_N / 2 N (design_scale; 1 and 1 on the default unit). unload_retreat_m, a noise
  // threshold as much as a length, stays at least half its reference number of sensor noise
  // sigmas (30 um is 15 of the reference's 2 um; fingertip-16x16: 3.75 um, not 1.8 um), and
  // observer.contact_threshold_m, left unscaled by the design, at most its reference number
  // (25 um is 12.5 sigmas; fingertip-16x16: 6.25 um). Off: taken as they are.
  bool scale_to_design = true;
};

// A unit's design point against the reference design (2 N at 5 mm): what BridgeOptions'
// lengths and forces, and a tissue law's, are multiplied by on it.
struct DesignScale {
  double length = 1.0;
  double force = 1.0;
};
inline constexpr double kReferenceDesignForce_N = 2.0;
inline constexpr double kReferenceDesignIndentation_m = 5e-3;
MRSKIN_BRIDGE_API DesignScale design_scale(const model::DesignPoint& design) noexcept;
// options with its lengths, rates and forces scaled (what the Bridge renders with; identity for
// a scale of 1 and 1).
MRSKIN_BRIDGE_API BridgeOptions scaled_to_design(BridgeOptions options, DesignScale scale) noexcept;

// What a running bridge can change without losing its state (Bridge::retune): a reload of these
// is bumpless.
struct BridgeTuning {
  double rate_hz = 1000.0;
  double feedback_gain_per_s = 30.0;
  double footprint_cells = 1.5;
  double resend_period_s = 0.05;
  WorkspaceMapping mapping{};
  double stale_hold_s = 0.1;
  double stale_fade_s = 0.2;
  bool realtime = true;
  int rt_priority = 80;
  int loop_cpu = -1;
};

// Writes the tuning into options (the rest of options unchanged).
MRSKIN_BRIDGE_API void apply_tuning(const BridgeTuning& tuning, BridgeOptions& options) noexcept;

// A sensor found faulty, as the tick reports it (Bridge::take_sensor_fault).
struct SensorFaultEvent {
  std::size_t sensor = 0;
  SensorFault fault = SensorFault::none;
  double evidence = 0.0;                                     // SensorFaultMonitor::evidence()
  std::size_t healthy_left = 0;                              // displacement sensors still in the fit
  std::size_t unobservable_cell = SensorFaultMonitor::npos;  // npos: every cell still read
  double at_s = 0.0;                                         // since the bridge's first tick
};

// Ground truth for scoring (mrskin::sim::MockDeviceTruth on the mock; mrskin::eval::TruthScorer).
using ForceTruth = mrskin::ForceTruth;

// What a watcher sees of a rendered tick, right after it: valid during TickWatcher::on_tick only.
class MRSKIN_BRIDGE_API TickView {
 public:
  TickView() = default;
  TickView(const TickView&) = delete;
  TickView& operator=(const TickView&) = delete;
  TickView(TickView&&) = delete;
  TickView& operator=(TickView&&) = delete;
  virtual ~TickView() = default;
  [[nodiscard]] virtual double since_start_s() const noexcept = 0;  // since the bridge's first tick
  [[nodiscard]] virtual double period_s() const noexcept = 0;       // 1 / rate_hz
  // Per cell: the observer's force estimate; the law at the observed state, capped at
  // max_force_N; that law clamped into the envelope of this tick's solve (loaded cells, else 0).
  [[nodiscard]] virtual std::span<const double> observed_force_N() const noexcept = 0;
  [[nodiscard]] virtual std::span<const double> tissue_N() const noexcept = 0;
  [[nodiscard]] virtual std::span<const double> target_N() const noexcept = 0;
  // Per cell: the inverse's last solve (role, clamps, envelope).
  [[nodiscard]] virtual std::span<const model::CellSolution> solve() const noexcept = 0;
  // Every valve of the cell at or below 2 % of the unit's full current: its floor is the
  // observer's force (docs/bridge.md, "the envelope's floor").
  [[nodiscard]] virtual bool valves_open(std::size_t cell) const noexcept = 0;
  // The law rendered on the cell, at another state (for instance the truth's finger).
  [[nodiscard]] virtual double law_force_N(std::size_t cell, double depth_m,
                                           double rate_m_per_s) const noexcept = 0;
};

// Watches every rendered tick (not the halted ones) from the tick's thread, after the frame is
// sent: scoring against a truth, recording. Must not allocate, block or throw; writes what it
// measures into stats (the tick's time includes it).
class MRSKIN_BRIDGE_API TickWatcher {
 public:
  TickWatcher() = default;
  TickWatcher(const TickWatcher&) = delete;
  TickWatcher& operator=(const TickWatcher&) = delete;
  TickWatcher(TickWatcher&&) = delete;
  TickWatcher& operator=(TickWatcher&&) = delete;
  virtual ~TickWatcher() = default;
  virtual void on_tick(const TickView& tick, BridgeStats& stats) noexcept = 0;
};

class MRSKIN_BRIDGE_API Bridge {
 public:
  // Setup: allocates everything the tick needs. Throws InvalidArgument on bad options or when
  // the session has no profile (opened without reading the device's configuration).
  Bridge(DeviceSession& session, SlaveSource& source, BridgeOptions options = {});
  Bridge(const Bridge&) = delete;
  Bridge& operator=(const Bridge&) = delete;
  Bridge(Bridge&&) = delete;
  Bridge& operator=(Bridge&&) = delete;
  ~Bridge();

  // Between ticks: the watcher called after each rendered tick (nullptr: none); it must outlive
  // its use. With one, live_rms_error_N() follows stats().force_rms_error_N().
  void set_tick_watcher(TickWatcher* watcher) noexcept;
  // Enables the device (call before the first step).
  ResultCode enable() noexcept;

  // From any thread (a control socket, a signal handler's flag): acted on at the start of the
  // next tick. estop: zero currents sent and the device's emergency stop requested in that tick,
  // then nothing is rendered until enable. disable: the same without the emergency stop. enable:
  // leaves either. The strongest pending request wins (estop over disable over enable).
  enum class Request : unsigned char { none = 0, enable = 1, disable = 2, estop = 3 };
  void request(Request r) noexcept;
  // True after an estop or disable until the next enable.
  [[nodiscard]] bool halted() const noexcept;

  // Between ticks, with the library's loop stopped: takes new tuning and keeps every state (the
  // observer's depths and fluid, the tissue fit, the feedback integrals, the cells' latches), so
  // a rate or gain change in the middle of a press renders on without a bump. Throws
  // InvalidArgument for a value out of range (nothing changed then) or while start()ed. Setup.
  void retune(const BridgeTuning& tuning);
  [[nodiscard]] BridgeTuning tuning() const noexcept;
  // The options the bridge renders with: as given, scaled to the unit's design point
  // (BridgeOptions::scale_to_design). A scorer takes these.
  [[nodiscard]] const BridgeOptions& options() const noexcept;
  [[nodiscard]] DesignScale scale() const noexcept;
  // The bus budget at the current rate, checked at construction and at every retune (limited is
  // false on a link without a limit); its warning (above 80 % of the bus) for the owner to log.
  [[nodiscard]] const BusBudgetCheck& bus_budget() const noexcept;

  // One tick at time now. Real-time safe.
  ResultCode step(TimePoint now) noexcept;

  // Or let the library run step() on a RealtimeLoop (bridge/loop.hpp) at rate_hz against clock.
  // Returns the one warning when SCHED_FIFO/mlockall were refused ("" otherwise): log it.
  // Setup: allocates.
  std::string start(Clock& clock);
  void stop() noexcept;
  [[nodiscard]] bool running() const noexcept;
  // Any thread, between start() and stop(): a slave sample arrived, tick now.
  void notify() noexcept;
  // Scheduler state, wake latency, early wakes, overruns of the library's loop; after stop().
  [[nodiscard]] const LoopStats* loop_stats() const noexcept;

  // Statistics; read after stop() or from the tick thread. live_*() are safe from any thread.
  [[nodiscard]] const BridgeStats& stats() const noexcept;
  [[nodiscard]] std::uint64_t live_ticks() const noexcept;
  [[nodiscard]] double live_rms_error_N() const noexcept;
  [[nodiscard]] double live_stiffness_N_per_m() const noexcept;
  [[nodiscard]] std::span<const double> targets_N() const noexcept;
  [[nodiscard]] std::span<const double> currents_A() const noexcept;
  // Per cell, from the tick thread (or after stop()): the tissue law at the observed state
  // (capped at max_force_N, not clamped), and the envelope its target was clamped into (the
  // floor is the observer's force when every valve of the cell is open); NaN where not loaded.
  [[nodiscard]] std::span<const double> law_N() const noexcept;
  [[nodiscard]] std::span<const double> envelope_floor_N() const noexcept;
  [[nodiscard]] std::span<const double> envelope_ceiling_N() const noexcept;
  [[nodiscard]] const model::CellObserver& observer() const noexcept;
  [[nodiscard]] const model::CellInverse& inverse() const noexcept;
  // Sensor faults: the monitor (setup data: cells_of_sensor, stuck_run_readings; its live state
  // from the tick thread only), and the faults found, from one other thread (never blocks; a
  // reader that falls 64 faults behind loses the oldest, the count stays in stats()).
  [[nodiscard]] const SensorFaultMonitor& sensor_fault_monitor() const noexcept;
  bool take_sensor_fault(SensorFaultEvent& out) noexcept;
  [[nodiscard]] std::uint64_t live_sensor_faults() const noexcept;
  [[nodiscard]] double tick_period_s() const noexcept;
  void set_perf_clock(const Clock* clock) noexcept;

 private:
  // Everything else lives behind one pointer: a console linked against this header keeps its
  // ABI when the tick's state changes (docs/api.md, "ABI").
  class Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace mrskin::bridge
