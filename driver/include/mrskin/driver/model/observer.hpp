// Per-fluid-cell indentation, rate and force, estimated from the profile's sensors through the
// network model. The default 5 x 5 has 12 displacement sensors (one under each valve cell, reading
// the mean pad depth of the fluid cells that valve joins) for 13 fluid cells, so the readings
// alone do not fix the cells' depths (the averaging map has a null space). Three facts do:
//   - depths are never negative (a finger presses, it does not pull): for presses on one or a
//     few cells the non-negative solution is unique;
//   - fewer pressed cells are likelier than a spread of small depths (an L1 weight);
//   - depths move continuously (a prior at the previous estimate plus rate * dt).
// Each tick solves that bounded least-squares problem by projected coordinate descent (warm
// started, a fixed number of sweeps, no allocation). Sensors at fluid cells enter as rows of
// their own. The rate is the filtered difference of the estimates (or, opt-in, a line since the
// last detected change in rate: RateEstimator::segmented_line). The force comes from the
// nominal network model (NetworkSimulation with the fast stepper), driven by the estimated
// depths and the commanded currents through the nominal coil lag and yield curve: the
// observer never sees the plant's parameters.
//
// Cost (skip what the scene does not need). The fit stops once no depth moves more
// than sweep_tolerance_m in a sweep. On grids above network_max_cells it visits only the cells
// with depth and those sharing a sensor with a changed reading (more than
// reading_deadband_sigma from the reading last used) or with a cell that moved. A coil whose command has not
// changed and that has settled is not stepped. The force model is chosen per grid
// (ObserverForceModel::automatic):
//   - network (grids of at most network_max_cells fluid cells): the whole network is stepped,
//     a step every network_step_s spread over its ticks (skip_settled_network skips it at rest);
//   - local (larger grids): each contacted cell's force is the quasi-static cell law
//     (DeviceModel::cell_force_at_valve_pressure, the law CellInverse inverts; its valves'
//     pressure from the inverse's tables, CellInverse::valve_pressure_Pa, or the exact law where
//     the inverse refuses the graph) at its depth and filtered rate (rates within
//     hold_rate_m_per_s count as holding), each valve at its own yield stress: a holding cell is
//     held by its weakest valve, so the current a neighbour's press puts on a shared valve is
//     not read as this cell's force while any valve of the cell is off; cells without contact
//     cost nothing and have no force. It keeps no fluid history
//     (no trapped volume, no refill after a release), so it is less accurate than the network
//     (tests/plant/observer_test.cpp prints both), but its cost grows with the contacted cells,
//     not with the grid.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>

#include "mrskin/driver/export.hpp"
#include "mrskin/driver/model/common.hpp"
#include "mrskin/driver/model/device_model.hpp"
#include "mrskin/driver/model/network.hpp"

namespace mrskin::model {

enum class ObserverForceModel : unsigned char {
  automatic,  // network up to ObserverOptions::network_max_cells fluid cells, local above
  network,    // the nominal NetworkSimulation over the whole grid
  local,      // the quasi-static cell law, contacted cells only
};

// When an observed cell counts as touched: deeper than depth_m with an estimated force above
// force_N (a membrane sucked in after a release reads as depth with no force on it), and rates
// within +-hold_rate_m_per_s as holding (the observer's rate noise must not release a hold). The
// one definition for every impedance loop on observed cells: the bridge's defaults
// (BridgeOptions) and a device's own loop (the mock's firmware).
struct ContactThresholds {
  double depth_m = 50e-6;
  double force_N = 0.03;
  double hold_rate_m_per_s = 2e-3;
  [[nodiscard]] bool touched(double observed_depth_m, double observed_force_N) const noexcept {
    return observed_depth_m > depth_m && observed_force_N > force_N;
  }
};

// How the observer turns fitted depths into rates.
enum class RateEstimator : unsigned char {
  filtered_difference,  // a first-order filter on the depth's difference (rate_filter_time_constant_s)
  segmented_line,       // a line since the last detected change in rate, blended with that filter
};

struct ObserverOptions {
  // Expected depth change per tick not explained by the rate (the prior's spread), m.
  double prior_spread_m = 50e-6;
  // L1 weight on depth: a spread of this many metres over the grid costs as much as one
  // sensor standard deviation of misfit.
  double sparsity_scale_m = 2e-3;
  int sweeps = 12;
  double rate_filter_time_constant_s = 4e-3;
  RateEstimator rate_estimator = RateEstimator::filtered_difference;
  // segmented_line: the line's memory (s) and the CUSUM threshold on its prediction error, in
  // standard deviations of the cell's fitted depth.
  double rate_memory_s = 0.02;
  double rate_change_threshold_sigma = 5.0;
  Stepper force_stepper = Stepper::linearly_implicit_regularised;
  // Depths below this are no contact for the force model: with a precharged reservoir (p0 > 0)
  // the contact force jumps from 0 to p0 A_eff at first touch, so sensor noise on an untouched
  // cell must not read as a touch. Above the noise (2-3 um RMS, ~20 um max on the mock).
  double contact_threshold_m = 25e-6;
  ObserverForceModel force_model = ObserverForceModel::automatic;
  std::size_t network_max_cells = 64;  // automatic: the network up to this many fluid cells
  // The fit stops when no depth moved more than this in a sweep, m (at most `sweeps` sweeps).
  // 0.3 um, a seventh of the 5 x 5's sensor noise: from 0.01 um it cut the 5 x 5's idle tick by
  // 3.0k instructions and a held one by 4.1k, every scene's mean error over seeds 1-8 within
  // 0.0005 N and 0.1 points p95 (docs/bridge.md, "Cost per tick").
  double sweep_tolerance_m = 3e-7;
  // Grids of at most network_max_cells: while no depth was above contact_threshold_m last tick
  // and no reading is more than this many standard deviations from zero, the fit is skipped and
  // the depths are zero. Noise alone spread micrometres of depth over a few cells and relaxed
  // them for up to `sweeps` sweeps a tick: the 5 x 5's idle tick fell from 17.5k to 12.7k
  // instructions, every scene's figures unchanged over seeds 1-8 (docs/bridge.md, "Cost per
  // tick"). Larger grids apply it row by row: a changed reading within it moves none of its cells
  // at zero depth (the idle palm 866k -> 705k instructions a tick; docs/bridge.md, "The rest gate
  // row by row"). 0: off.
  double rest_gate_sigma = 3.0;
  // Grids of at most network_max_cells: when no depth was above contact_threshold_m last tick and
  // the largest reading is past the rest gate but within twice it (noise, on about 8 % of the
  // 5 x 5's idle ticks; a touch reads far above), the fit sweeps at most this many times instead
  // of `sweeps`: the twelve went on the null space's slow convergence, micrometres below the
  // contact threshold. Only the cells under a reading past the gate, and those the prior gives
  // depth, are relaxed; the others stay at zero (docs/bridge.md, "Cost per tick"). At least 1.
  int rest_sweeps = 2;
  // Grids of at most network_max_cells: at most this many sweeps a tick (and `sweeps`, the lesser).
  // The fit starts from the last tick's depths, so what a capped tick leaves is taken up the next;
  // the 5 x 5's worst held tick fell from 60.7k to 54.9k instructions with every scene's error
  // over seeds 1-8 within its seed-to-seed noise (docs/bridge.md, "Cost per tick"); 4 took about
  // 870 more off a held tick (2.0-2.5k off the one-cell maxima) within the same noise ("Fewer
  // sweeps"). The large grids keep `sweeps`: their sparse fit capped at 6 cost more (palm, 5 %
  // loading, +10 %). At least 1.
  int small_grid_sweeps = 4;
  // Grids above network_max_cells: a sensor whose reading (in its standard deviations) is within
  // this of the reading last used counts as unchanged.
  double reading_deadband_sigma = 2.0;
  // Grids above network_max_cells: the L1 weight is at least this many standard deviations of
  // the least noisy sensor per unit of weighted reading, so a cell stays at zero depth until its
  // sensors read more than noise can (a cell under four sensors that each average four cells:
  // about 4 x this sigmas of depth, a bias of that much on a pressed depth; 4 um on the 16x16).
  // Without it, noise spread micrometres of depth over the whole grid: each idle tick refitted
  // most cells and the inverse solved contact that was not there (palm-64x64, instructions per
  // tick: idle 4.0M -> 1.8M, a 5 % patch 16.2M -> 3.3M; docs/bridge.md). 0: the sparsity_scale_m
  // weight alone, as on small grids.
  double noise_floor_sigma = 2.0;
  // Grids above network_max_cells: the fit carries its residual (H d - y) over from one tick to
  // the next, updated by what moved, and computes it afresh every this many ticks (and after a
  // reset or a sensor's exclusion) so round-off cannot build up. 1: afresh every tick, as small
  // grids do (about 0.11M more instructions a tick on the idle palm-64x64; the two differ by
  // round-off, docs/bridge.md "Cost per tick").
  std::uint32_t residual_refresh_ticks = 1024;
  // Local force model: filtered rates within +-this count as holding (the rate's noise is
  // ~0.5 mm/s RMS on the 5 x 5), m/s.
  double hold_rate_m_per_s = 1.5e-3;
  // Network model: skip the step while its inputs are unchanged, its forces moved less than 1 uN
  // in the last one and no link flows more than 0.1 nL/s. The flow test matters: on forces alone
  // a released skin that still refills looks settled (docs/bridge.md, "What the tuning measured").
  // Untouched on unchanged inputs, it also steps several ticks at once (at most 64) while its
  // largest link moves at most 1 nL in the ticks the step runs ahead: a released skin's slow
  // tail (docs/bridge.md, "Cost per tick"). Off: the network takes a step every network_step_s.
  bool skip_settled_network = true;
  // Network model: each step of the network covers this long, in whole ticks (at most 64, at
  // least one), and its work is spread evenly over them (NetworkSimulation::begin_step, 8
  // phases: 2 a tick at 1 kHz): the inputs of the tick it begins on, each touched cell's depth
  // carried on at its rate to the step's last tick; between steps each touched cell's force is
  // its undrained law at its depth now, its fluid moved on through its valves as they are now.
  // The hydraulics' time constants (85-95 ms) allow it: every scene's figures over seeds 1-8
  // stay within their seed-to-seed spread, and a held 5 x 5 tick costs about 16k instructions
  // less (docs/bridge.md, "The network in phases"). 4 ms: 4 ticks at 1 kHz, 1 at 200 Hz. 0: a
  // whole step every tick.
  double network_step_s = 4e-3;
  // Network model: a step whose one linear solve is off the laws by more than this fraction of
  // the pressure scale is refused (NetworkOptions::linearisation_tolerance) and taken again as
  // the shorter step of the ticks before the refusal (network_steps_refused() counts them).
  // Lower it only to test that path; > 0.
  double network_linearisation_tolerance = 0.25;
  // The steel's hysteresis (the profile's coercivity, the plant's play operator, tabulated):
  // after any current a valve keeps a remanent yield at 0 A. Off: the anhysteretic yield curve.
  bool steel_hysteresis = true;
};

class MRSKIN_DRIVER_API CellObserver {
 public:
  // The nominal model (not copied: it must outlive the observer). Throws InvalidArgument when the
  // profile has no displacement sensor.
  CellObserver(const DeviceModel& nominal, const ObserverOptions& options);
  ~CellObserver();
  CellObserver(const CellObserver&) = delete;
  CellObserver& operator=(const CellObserver&) = delete;
  CellObserver(CellObserver&&) = delete;
  CellObserver& operator=(CellObserver&&) = delete;

  // One tick: readings in the profile's sensor order (SI units), the currents commanded to
  // each valve (A), and the tick (s). Errors (state kept): out_of_range (sizes, dt),
  // not_finite; the network model's own failure is passed through.
  Status update(std::span<const double> sensor_readings, std::span<const double> valve_current_A,
                double dt_s) noexcept;
  void reset() noexcept;
  // A unit's calibrated per-valve yield gains (true / nominal yield stress at a current), one per
  // valve; out_of_range for a wrong size or a gain that is not finite and positive. Setup only.
  Status set_valve_yield_gain(std::span<const double> gain) noexcept;

  [[nodiscard]] std::span<const double> indentation_m() const noexcept;
  [[nodiscard]] std::span<const double> velocity_m_per_s() const noexcept;
  [[nodiscard]] std::span<const double> force_N() const noexcept;
  // Network force model: each fluid cell's net flow out through its passages in the last step,
  // m^3/s (negative: inflow). Near zero while the finger presses, the cell's passages hold: more
  // current cannot raise its force. Empty for the local force model, which tracks no flows.
  [[nodiscard]] std::span<const double> outflow_m3_per_s() const noexcept;
  // The current that gives `valve` the yield stress the anhysteretic curve gives at current_A, as
  // this observer models the steel's play: the band's upper edge when that moves the play up,
  // its lower edge (at least 0 A) when down. current_A itself without hysteresis or at 0 A.
  [[nodiscard]] double hysteresis_compensated_current_A(std::size_t valve, double current_A) const noexcept;
  // Root-mean-square misfit of the displacement sensors the fit uses after the last update, m.
  [[nodiscard]] double sensor_misfit_m() const noexcept;
  // Per sensor of the profile (its order): the last reading less what the fitted depths predict,
  // in that sensor's standard deviations (its noise, at least its quantisation step). Computed
  // for excluded sensors too; 0 for sensors that are not displacement sensors.
  [[nodiscard]] std::span<const double> sensor_residual_sigma() const noexcept;
  // Takes a displacement sensor out of the fit (a fault) or back in. Real-time safe (no
  // allocation). out_of_range for an index that is not a displacement sensor of the fit.
  Status set_sensor_excluded(std::size_t sensor, bool excluded) noexcept;
  [[nodiscard]] std::size_t fluid_cell_count() const noexcept;
  // The force model in use (automatic resolved at construction).
  [[nodiscard]] ObserverForceModel force_model() const noexcept;
  // Network model: the steps the network refused since construction (its linearisation, mostly),
  // each taken again as a shorter step or, where none is shorter, reported as update()'s error.
  [[nodiscard]] std::size_t network_steps_refused() const noexcept;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace mrskin::model
