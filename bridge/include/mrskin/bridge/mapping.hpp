// From the slave's workspace to the skin: where on the MR skin a contact on the tissue is
// rendered. The slave reports its contact point in its tissue frame (x, y on the tissue surface,
// metres); the mapping takes it to the skin's cell coordinates (row, col; fractional; the skin's
// centre is ((rows - 1) / 2, (cols - 1) / 2)):
//   (u, v) = R(rotation) * (mirror_x ? -1 : 1, mirror_y ? -1 : 1) * (p - origin) * cells_per_m
//   col = centre_col + u, row = centre_row + v
// All of it is configuration (TOML [mapping], BridgeOptions::mapping).
#pragma once

#include <cmath>

namespace mrskin::bridge {

struct CellPoint {
  double row = 0.0;
  double col = 0.0;
};

struct WorkspaceMapping {
  double origin_x_m = 0.0;  // the workspace point rendered at the skin's centre
  double origin_y_m = 0.0;
  double cells_per_m = 100.0;  // scale: 10 mm of tissue per skin cell
  double rotation_rad = 0.0;   // about the surface normal, after mirroring
  bool mirror_x = false;
  bool mirror_y = false;

  [[nodiscard]] bool valid() const noexcept {
    return std::isfinite(origin_x_m) && std::isfinite(origin_y_m) && std::isfinite(rotation_rad) &&
           cells_per_m > 0.0 && std::isfinite(cells_per_m);
  }
  [[nodiscard]] CellPoint to_cell(double x_m, double y_m, int rows, int cols) const noexcept {
    const double dx = (x_m - origin_x_m) * (mirror_x ? -1.0 : 1.0) * cells_per_m;
    const double dy = (y_m - origin_y_m) * (mirror_y ? -1.0 : 1.0) * cells_per_m;
    const double c = std::cos(rotation_rad);
    const double s = std::sin(rotation_rad);
    return {0.5 * (rows - 1) + s * dx + c * dy, 0.5 * (cols - 1) + c * dx - s * dy};
  }
  // A length on the tissue (a tip radius) in cell units.
  [[nodiscard]] double to_cells(double length_m) const noexcept { return length_m * cells_per_m; }
};

}  // namespace mrskin::bridge
