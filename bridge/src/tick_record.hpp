// The bridge tick's record: what each of its four stages (observe -> render -> allocate -> send)
// wrote, and what the watchers (scoring, statistics) read after the tick. docs/architecture.md.
// Private to the bridge library. Everything here is sized at setup; the tick only writes into it.
#pragma once

#include <cstddef>
#include <span>
#include <vector>

#include "mrskin/bridge/tissue.hpp"
#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/model/inverse.hpp"

namespace mrskin::bridge::detail {

// Observe: the cells as the observer estimates them from this tick's readings (views into the
// observer, valid until its next update).
struct Observation {
  std::span<const double> depth_m;
  std::span<const double> rate_m_per_s;
  std::span<const double> force_N;
  std::span<const double> outflow_m3_per_s;  // empty: the profile has the local force model
};

// Render, per cell, as arrays: the inverse takes the states and the targets as one span each.
struct Rendering {
  std::vector<model::CellState> state;             // in contact, else zero depth and rate
  std::vector<model::CellImpedanceTarget> target;  // the cell's law with the feedback's shift
  std::vector<double> tissue_N;                    // the law at the state, capped at the range
  std::vector<unsigned char> contact;              // the finger is on the cell
  std::size_t contact_cells = 0;                   // how many contact[] are set
  // Every cell was at rest this tick and the last: only the targets' validity moved.
  bool unchanged_at_rest = false;
  // This tick consumed a new slave sample (its arrival, for the latency figures).
  bool fresh_sample = false;
  TimePoint fresh_arrival{};
};

// Allocate, per valve and per cell. Carried over: a failed solve keeps the last good
// allocation, and its targets are the next tick's feedback error.
struct Allocation {
  std::vector<double> current_A;           // per valve: what send hands to the session
  std::vector<double> target_N;            // per cell: the law clamped into this solve's envelope
  std::vector<unsigned char> below_floor;  // per cell: the law is below the open-valve floor
  std::vector<double> floor_N;             // per cell: the envelope target_N was clamped into...
  std::vector<double> ceiling_N;           // ...(NaN where not loaded)
  std::vector<unsigned char> drain_held;   // per cell: drained or sealed after an overshoot
  bool solved = false;                     // this tick's solve succeeded
};

struct TickRecord {
  TimePoint now{};
  double since_start_s = 0.0;
  Observation observed;
  Rendering rendered;
  Allocation allocated;
};

// What render carries from tick to tick for one cell: named, so no tick reads another's leftovers.
struct CellMemory {
  // The direction latch (hysteresis in position): latched loading or release, the depth's peak
  // while loaded (trough while unloading), and the depth smoothed for it.
  unsigned char loading = 0;
  unsigned char unloading = 0;
  double extreme_m = 0.0;
  double smooth_depth_m = 0.0;
  double feedback_N = 0.0;  // the integral correction
  // The tissue mapped onto the cell once the instrument has been over it, and the law rendered
  // (the mapped one, changed passively while the finger is in the cell).
  TissueModel mapped_model{};
  unsigned char mapped = 0;
  PassiveTissueUpdate law{};
  // The law's target at rest (no contact, no passive change), kept while the law stays as it is:
  // an untouched cell of a large grid then costs a copy a tick, not the law's evaluation.
  model::CellImpedanceTarget rest_target{};
  double rest_ceiling_N = 0.0;  // the force ceiling it was made with
  // 0: none; 1: valid; 2: valid, and the cell's direction latch is kept while its pad is down
  // (looked at each tick until the pad is back).
  unsigned char rest_valid = 0;
};

}  // namespace mrskin::bridge::detail
