#include "mrskin/driver/layout.hpp"

#include <string>

#include "mrskin/driver/errors.hpp"

namespace mrskin {

GridLayout::GridLayout(int rows, int cols) : rows_(rows), cols_(cols) {
  if (rows < 1 || rows > 255 || cols < 1 || cols > 255) {
    throw InvalidArgument("grid " + std::to_string(rows) + " x " + std::to_string(cols) +
                          " is outside 1..255 x 1..255: fix rows/cols in the device profile");
  }
  std::vector<int> fluid_index(static_cast<std::size_t>(rows) * static_cast<std::size_t>(cols), -1);
  for (int r = 0; r < rows; ++r) {
    for (int c = 0; c < cols; ++c) {
      if ((r + c) % 2 == 0) {
        fluid_index[static_cast<std::size_t>(r) * static_cast<std::size_t>(cols) +
                    static_cast<std::size_t>(c)] = static_cast<int>(fluid_.size());
        fluid_.push_back({r, c});
      } else {
        valves_.push_back({r, c});
      }
    }
  }
  cells_of_valve_.resize(valves_.size());
  valves_of_cell_.resize(fluid_.size());
  for (std::size_t v = 0; v < valves_.size(); ++v) {
    const GridCell g = valves_[v];
    const int dr[] = {-1, 1, 0, 0};
    const int dc[] = {0, 0, -1, 1};
    for (int k = 0; k < 4; ++k) {
      const int r = g.row + dr[k];
      const int c = g.col + dc[k];
      if (r < 0 || r >= rows || c < 0 || c >= cols) {
        continue;
      }
      const int f = fluid_index[static_cast<std::size_t>(r) * static_cast<std::size_t>(cols) +
                                static_cast<std::size_t>(c)];
      cells_of_valve_[v].push_back(static_cast<std::size_t>(f));
      valves_of_cell_[static_cast<std::size_t>(f)].push_back(v);
    }
  }
}

}  // namespace mrskin
