#include "mrskin/sim/fingertip.hpp"

#include <algorithm>

namespace mrskin::sim {

void press_fingertip(const GridLayout& layout, double row, double col, double depth_m,
                     std::span<double> indentation_m) noexcept {
  const auto& cells = layout.fluid_cells();
  const std::size_t n = std::min(indentation_m.size(), cells.size());
  for (std::size_t i = 0; i < n; ++i) {
    const double dr = cells[i].row - row;
    const double dc = cells[i].col - col;
    const double share = 1.0 - (dr * dr + dc * dc) / (kFingertipRadius_cells * kFingertipRadius_cells);
    indentation_m[i] = share > 0.0 ? depth_m * share : 0.0;
  }
}

}  // namespace mrskin::sim
