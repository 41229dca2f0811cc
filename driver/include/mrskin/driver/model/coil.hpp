// The valve coil as an R-L load under a current-mode driver, and the eddy-current lag of the
// field behind the coil current.
//
//   current loop:  dI/dt = w_bw (I_cmd - I), w_bw = 2 pi f_bw, limited by the supply:
//                  |L dI/dt + R I| <= V_supply (slew-limited segments follow dI/dt = (+-V - R I)/L)
//   field:         dI_f/dt = (I - I_f) / tau_eddy   (I_f: the current the gap field "sees")
//
// The fluid itself answers in 1-2 ms; what limits the valve is the current loop and the eddy
// currents in a solid core (5-20 ms). Both are integrated exactly for piecewise-constant
// commands (the eddy lag with a first-order hold on I).
#pragma once

#include "mrskin/driver/export.hpp"
#include "mrskin/driver/model/common.hpp"

namespace mrskin::model {

struct CoilParams {
  double resistance_ohm = 1.0;
  double inductance_H = 1e-3;
  double supply_voltage_V = 12.0;
  double max_current_A = 0.5;            // highest allowed current; currents are 0..max
  double current_resolution_A = 125e-6;  // one count of the driver (and of the wire protocol)
  double driver_bandwidth_Hz = 500.0;    // closed-loop bandwidth of the current-mode driver
  double eddy_time_constant_s = 5e-3;    // field lag behind the coil current
};

struct CoilState {
  double current_A = 0.0;        // coil current
  double field_current_A = 0.0;  // eddy-lagged current that sets the gap field
};

// Advances the coil by dt under a constant command in [-max_current_A, max_current_A] (negative:
// a bipolar driver reversing the field, as a degauss does; hosts command 0..max).
MRSKIN_DRIVER_API Result<CoilState> coil_step(const CoilParams& c, const CoilState& s, double command_A,
                                              double dt_s) noexcept;

// The two decays of a step of dt_s (the current loop's, e^{-2 pi f_bw dt}, and the eddy lag's,
// e^{-dt / tau_eddy}), for a caller that steps many coils by the same dt: computed once, they save
// two exponentials a coil.
struct CoilDecay {
  double dt_s = 0.0;
  double loop = 1.0;
  double eddy = 1.0;
};
MRSKIN_DRIVER_API CoilDecay coil_decay(const CoilParams& c, double dt_s) noexcept;
// coil_step by decay.dt_s with the decays precomputed: the same result, bit for bit.
MRSKIN_DRIVER_API Result<CoilState> coil_step(const CoilParams& c, const CoilState& s, double command_A,
                                              const CoilDecay& decay) noexcept;

// Current-loop time constant 1 / (2 pi f_bw), s.
MRSKIN_DRIVER_API double current_loop_time_constant_s(const CoilParams& c) noexcept;
// The profile's coil time constant used for settling figures: current loop + eddy lag, s.
MRSKIN_DRIVER_API double coil_time_constant_s(const CoilParams& c) noexcept;
// Open-loop L/R, s (what a voltage driver would give).
MRSKIN_DRIVER_API double open_loop_time_constant_s(const CoilParams& c) noexcept;

// Empty string when the parameters make sense, otherwise "field: reason".
MRSKIN_DRIVER_API const char* check_coil(const CoilParams& c) noexcept;

}  // namespace mrskin::model
