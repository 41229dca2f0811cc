// The skin's grid: a rows x cols checkerboard of fluid cells (row + col even) and valve
// cells (row + col odd). A valve joins the fluid cells it shares an edge with.
#pragma once

#include <cstddef>
#include <vector>

#include "mrskin/driver/export.hpp"

namespace mrskin {

struct GridCell {
  int row = 0;
  int col = 0;
};

class MRSKIN_DRIVER_API GridLayout {
 public:
  GridLayout(int rows, int cols);  // throws InvalidArgument for rows or cols outside 1..255

  [[nodiscard]] int rows() const noexcept { return rows_; }
  [[nodiscard]] int cols() const noexcept { return cols_; }
  [[nodiscard]] std::size_t fluid_cell_count() const noexcept { return fluid_.size(); }
  [[nodiscard]] std::size_t valve_count() const noexcept { return valves_.size(); }
  [[nodiscard]] const std::vector<GridCell>& fluid_cells() const noexcept { return fluid_; }
  [[nodiscard]] const std::vector<GridCell>& valves() const noexcept { return valves_; }
  // Fluid-cell indices a valve joins, and valve indices a fluid cell touches.
  [[nodiscard]] const std::vector<std::size_t>& cells_of_valve(std::size_t v) const {
    return cells_of_valve_.at(v);
  }
  [[nodiscard]] const std::vector<std::size_t>& valves_of_cell(std::size_t c) const {
    return valves_of_cell_.at(c);
  }

 private:
  int rows_;
  int cols_;
  std::vector<GridCell> fluid_;
  std::vector<GridCell> valves_;
  std::vector<std::vector<std::size_t>> cells_of_valve_;
  std::vector<std::vector<std::size_t>> valves_of_cell_;
};

}  // namespace mrskin
