// The simulated unit's finger: a fingertip pad pressing the skin, the mock's finger input
// (MockDevice::set_finger_indentation) for a press centred anywhere on the grid.
#pragma once

#include <span>

#include "mrskin/driver/layout.hpp"
#include "mrskin/sim/export.hpp"

namespace mrskin::sim {

// The pad's radius, cell pitches: on the 5 x 5 a press centred on a fluid cell touches it alone.
inline constexpr double kFingertipRadius_cells = 1.2;

// Each fluid cell's indentation, m, under a fingertip centred at (row, col) in cell units (any
// real position, off the grid too) pressed depth_m deep at its centre: depth_m (1 - r^2 / R^2)
// out to R = kFingertipRadius_cells, 0 beyond. Writes min(size, fluid cells) values.
MRSKIN_SIM_API void press_fingertip(const GridLayout& layout, double row, double col, double depth_m,
                                    std::span<double> indentation_m) noexcept;

}  // namespace mrskin::sim
