// The laws of one profile, assembled: valve law, magnetic circuit, contact patch, the
// hydraulic branches of every fluid cell, and a tabulated yield curve tau_y(I) for the loop.
//
// Construction (setup) may throw mrskin::InvalidArgument. Every other member is noexcept,
// allocation-free and returns a Result: these are the functions the real-time path may call.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

#include "mrskin/driver/export.hpp"
#include "mrskin/driver/layout.hpp"
#include "mrskin/driver/model/cell.hpp"
#include "mrskin/driver/model/profile.hpp"

namespace mrskin::model {

class MRSKIN_DRIVER_API DeviceModel {
 public:
  explicit DeviceModel(DeviceProfile profile);

  [[nodiscard]] const DeviceProfile& profile() const noexcept { return profile_; }
  [[nodiscard]] const GridLayout& layout() const noexcept { return layout_; }
  [[nodiscard]] const ValveLaw& valve_law() const noexcept { return valve_; }
  [[nodiscard]] const ContactPatch& contact() const noexcept { return patch_; }

  // Index of the fluid cell at (row, col): out_of_range if outside the grid or a valve cell.
  [[nodiscard]] Result<std::size_t> fluid_cell_index(int row, int col) const noexcept;

  // Exact magnetic circuit (anhysteretic) at a coil current, any sign.
  [[nodiscard]] Result<GapField> gap_field(double current_A) const noexcept;
  // Tabulated tau_y(I) for I in [0, max_current_A] (monotone cubic, 512 segments);
  // out_of_range outside. Its largest error against the exact circuit is measured at
  // construction: yield_table_max_error_Pa().
  [[nodiscard]] Result<double> yield_stress_at_current_Pa(double current_A) const noexcept;
  [[nodiscard]] double yield_table_max_error_Pa() const noexcept { return yield_table_error_Pa_; }

  // Pressure of a cell driving a flow Q >= 0 out through its valves (sinks at p0), with every
  // valve's yield stress given (size valve_count()); Q = 0 gives the breakaway threshold.
  [[nodiscard]] Result<double> valve_network_pressure_Pa(
      std::size_t cell, double flow_m3_per_s, std::span<const double> valve_yield_Pa) const noexcept;
  // Same with one yield stress on every valve.
  [[nodiscard]] Result<double> valve_network_pressure_uniform_Pa(std::size_t cell, double flow_m3_per_s,
                                                                 double yield_stress_Pa) const noexcept;

  // Force on a fluid cell at indentation d (m, <= 0: no contact), rate v (m/s) and coil
  // currents (A, one per valve, each in [0, max_current_A]).
  [[nodiscard]] Result<CellLoad> cell_force(std::size_t cell, double indentation_m, double velocity_m_per_s,
                                            std::span<const double> valve_current_A) const noexcept;
  // Same with every valve at one current.
  [[nodiscard]] Result<CellLoad> cell_force_uniform(std::size_t cell, double indentation_m,
                                                    double velocity_m_per_s, double current_A) const noexcept;
  // Same with every valve at one yield stress (bypasses the coil).
  [[nodiscard]] Result<CellLoad> cell_force_at_yield(std::size_t cell, double indentation_m,
                                                     double velocity_m_per_s,
                                                     double yield_stress_Pa) const noexcept;
  // Same with the valves' network standing at valve_pressure_Pa (>= 0) for the cell's flow
  // |area v|, as valve_network_pressure_Pa gives it: for a caller with a faster law of its own.
  [[nodiscard]] Result<CellLoad> cell_force_at_valve_pressure(std::size_t cell, double indentation_m,
                                                              double velocity_m_per_s,
                                                              double valve_pressure_Pa) const noexcept;
  // F_min (valves open: zero current) and F_max (valves at max_current_A) at (d, v).
  [[nodiscard]] Result<CellEnvelope> envelope(std::size_t cell, double indentation_m,
                                              double velocity_m_per_s) const noexcept;
  // The uniform current that renders a force while loading (bisection on the monotone
  // force-current curve); out_of_range if the force is outside the envelope.
  [[nodiscard]] Result<double> current_for_force_A(std::size_t cell, double indentation_m,
                                                   double velocity_m_per_s, double force_N) const noexcept;

  // Number of hydraulic branches leaving a cell (for tests and docs).
  [[nodiscard]] std::size_t branch_count(std::size_t cell) const noexcept;

  // How long a cell's own bulge takes to empty through one open passage: its compliance
  // (1 / bulge_linear_Pa_per_m3) over the passage's conductance without yield; infinity unless
  // both are positive. An order of magnitude of the network's fastest mode: 1.7 s on the default
  // 5x5, 3.5 us on fingertip-16x16 and 7.6 us on palm-64x64, whose cells are stiff.
  [[nodiscard]] double cell_open_drain_time_s() const noexcept;

 private:
  struct Branch {
    std::uint32_t inlet = 0;      // link index
    std::uint32_t out_begin = 0;  // into outlets_
    std::uint32_t out_end = 0;    // == out_begin: the inlet ends in a sink
  };
  template <class TauOf>
  Result<double> network_pressure(std::size_t cell, double flow, const TauOf& tau_of) const noexcept;
  template <class TauOf>
  Result<FlowPoint> branch_flow(const Branch& b, double p, const TauOf& tau_of) const noexcept;
  template <class TauOf>
  Result<CellLoad> load(std::size_t cell, double d, double v, const TauOf& tau_of) const noexcept;
  Result<CellLoad> load_at_pressure(double d, double v, double pv_Pa) const noexcept;

  DeviceProfile profile_;
  GridLayout layout_;
  ValveLaw valve_;
  ContactPatch patch_;
  std::vector<Branch> branches_;
  std::vector<std::uint32_t> outlets_;
  std::vector<std::uint32_t> cell_branch_begin_;  // fluid_cell_count() + 1 entries
  std::vector<std::int32_t> link_valve_;          // link -> valve (-1: unmagnetised)
  std::vector<double> table_tau_Pa_;              // at I_k = k * step
  std::vector<double> table_slope_Pa_per_A_;
  double table_step_A_ = 0.0;
  double yield_table_error_Pa_ = 0.0;
};

}  // namespace mrskin::model
