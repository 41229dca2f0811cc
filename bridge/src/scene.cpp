#include "mrskin/bridge/scene.hpp"

#include <algorithm>
#include <cmath>
#include <string>

#include "mrskin/driver/errors.hpp"

namespace mrskin::bridge {
namespace {

double smoothstep(double u) noexcept {
  u = std::clamp(u, 0.0, 1.0);
  return u * u * (3.0 - 2.0 * u);
}

class DemoScene final : public Scene {
 public:
  [[nodiscard]] std::string_view name() const noexcept override { return "demo"; }
  [[nodiscard]] double cycle_s() const noexcept override { return kCycle_s; }

  void finger(double t_s, const GridLayout& layout, std::span<double> indentation_m) const noexcept override {
    const double depth = depth_m(t_s);
    const double centre_row = 0.5 * (layout.rows() - 1);
    const double centre_col = 0.5 * (layout.cols() - 1);
    const auto& cells = layout.fluid_cells();
    const std::size_t n = std::min(indentation_m.size(), cells.size());
    for (std::size_t i = 0; i < n; ++i) {
      const double dr = cells[i].row - centre_row;
      const double dc = cells[i].col - centre_col;
      const double share = 1.0 - (dr * dr + dc * dc) / (kRadius_cells * kRadius_cells);
      indentation_m[i] = share > 0.0 ? depth * share : 0.0;
    }
  }

  bool latest(TimePoint now, SlaveSample& out) noexcept override {
    const double t = to_seconds(now - start());
    const double x = depth_m(t);
    const double v = (depth_m(t + 1e-4) - depth_m(t - 1e-4)) / 2e-4;
    out.stamp = now;
    out.indentation_m = x;
    out.force_N = x > 0.0 ? std::max(0.0, kStiffness_N_per_m * x + kDamping_N_s_per_m * v) : 0.0;
    out.contact_row = 2.0;
    out.contact_col = 2.0;
    out.contact_radius_cells = kRadius_cells;
    out.valid = true;
    return true;
  }

 private:
  static constexpr double kCycle_s = 3.5;
  static constexpr double kDepth_m = 4e-3;
  static constexpr double kRadius_cells = 1.2;
  static constexpr double kStiffness_N_per_m = 300.0;
  static constexpr double kDamping_N_s_per_m = 0.5;

  static double depth_m(double t_s) noexcept {
    if (t_s < 0.0) {
      return 0.0;
    }
    const double t = std::fmod(t_s, kCycle_s);
    if (t < 1.0) {
      return kDepth_m * smoothstep(t);
    }
    if (t < 2.0) {
      return kDepth_m;
    }
    if (t < 3.0) {
      return kDepth_m * (1.0 - smoothstep(t - 2.0));
    }
    return 0.0;
  }
};

}  // namespace

std::unique_ptr<Scene> make_scene(std::string_view name) {
  if (name.starts_with("scene://")) {
    name.remove_prefix(8);
  }
  if (name == "demo") {
    return std::make_unique<DemoScene>();
  }
  throw InvalidArgument("unknown scene '" + std::string(name) + "': available scenes are: demo");
}

}  // namespace mrskin::bridge
