#include "mrskin/bridge/scene.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <numbers>
#include <string>
#include <utility>
#include <vector>

#include "mrskin/driver/errors.hpp"

namespace mrskin::bridge {
namespace {

constexpr std::array<std::string_view, 11> kSceneNames = {
    "demo", "hand", "neck", "abdomen", "thigh", "back", "stomach", "sweep", "tumour", "step", "force_step"};

constexpr double kTipRadius_m = 3e-3;
constexpr double kStepHoldDepth_m = 1.5e-3;  // scene "step": the hold before the step

double smoothstep(double u) noexcept {
  u = std::clamp(u, 0.0, 1.0);
  return u * u * (3.0 - 2.0 * u);
}

double smoothstep_slope(double u) noexcept {
  u = std::clamp(u, 0.0, 1.0);
  return 6.0 * u * (1.0 - u);
}

class DemoScene final : public Scene {
 public:
  explicit DemoScene(const WorkspaceMapping& mapping) noexcept : mapping_(mapping) {}

  [[nodiscard]] std::string_view name() const noexcept override { return "demo"; }
  [[nodiscard]] double cycle_s() const noexcept override { return kCycle_s; }

  [[nodiscard]] const WorkspaceMapping& mapping() const noexcept override { return mapping_; }

  bool latest(TimePoint now, SlaveSample& out) noexcept override {
    const SlaveTruth s = slave_truth(to_seconds(now - start()));
    out.stamp = now;
    out.indentation_m = s.indentation_m;
    out.force_N = s.force_N;
    out.contact_x_m = s.contact_x_m;  // the mapping's origin: the skin's centre, under the finger
    out.contact_y_m = s.contact_y_m;
    out.tip_radius_m = kTipRadius_m;
    out.valid = true;
    return true;
  }

  [[nodiscard]] TissueModel tissue_at(double /*x_m*/, double /*y_m*/) const noexcept override {
    return TissueModel::kelvin_voigt(kStiffness_N_per_m, kDamping_N_s_per_m);
  }

  [[nodiscard]] SlaveTruth slave_truth(double t_s) const noexcept override {
    const double x = depth_m(t_s);
    const double v = (depth_m(t_s + 1e-4) - depth_m(t_s - 1e-4)) / 2e-4;
    return {.contact_x_m = mapping_.origin_x_m,
            .contact_y_m = mapping_.origin_y_m,
            .indentation_m = x,
            .rate_m_per_s = v,
            .force_N = x > 0.0 ? std::max(0.0, kStiffness_N_per_m * x + kDamping_N_s_per_m * v) : 0.0};
  }

 private:
  static constexpr double kCycle_s = 3.5;
  static constexpr double kDepth_m = 4e-3;
  static constexpr double kStiffness_N_per_m = 300.0;
  static constexpr double kDamping_N_s_per_m = 0.5;

  WorkspaceMapping mapping_;  // the slave palpates its origin, the skin's centre

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

// ---- scripted scenes -------------------------------------------------------------------------

// A keyframe of the slave's script: at t_s the instrument is at (x_m, y_m) from the mapping's
// origin, depth_m into the tissue. The segment that ends here starts and stops smoothly, or
// runs at constant speed (linear: a slide).
struct Key {
  double t_s = 0.0;
  double x_m = 0.0;
  double y_m = 0.0;
  double depth_m = 0.0;
  bool linear = false;
};

struct Pose {
  double x_m = 0.0;
  double y_m = 0.0;
  double depth_m = 0.0;
  double rate_m_per_s = 0.0;
};

// The scene's tissue: base everywhere, times inclusion_scale inside the inclusion, blended to
// base across its rim (smoothstep in the distance), as a buried lump loads the tissue around it.
struct Tissue {
  TissueModel base{};
  double inclusion_scale = 1.0;  // 1: homogeneous
  double inclusion_x_m = 0.0;    // from the mapping's origin
  double inclusion_y_m = 0.0;
  double inclusion_radius_m = 0.0;
  double rim_m = 0.0;
};

// Slave-side force noise: a pure function of (seed, sample index), so a scene replays exactly
// whatever the caller's tick rate.
std::uint64_t splitmix64(std::uint64_t x) noexcept {
  x += 0x9e3779b97f4a7c15ULL;
  x = (x ^ (x >> 30U)) * 0xbf58476d1ce4e5b9ULL;
  x = (x ^ (x >> 27U)) * 0x94d049bb133111ebULL;
  return x ^ (x >> 31U);
}

double standard_normal(std::uint64_t seed, std::uint64_t index) noexcept {
  const std::uint64_t a = splitmix64(seed ^ splitmix64(index));
  const std::uint64_t b = splitmix64(a);
  const double u1 = (static_cast<double>(a >> 11U) + 1.0) * 0x1.0p-53;  // (0, 1]: log is finite
  const double u2 = static_cast<double>(b >> 11U) * 0x1.0p-53;
  return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * std::numbers::pi * u2);  // Box-Muller
}

class ScriptedScene final : public Scene {
 public:
  ScriptedScene(std::string_view name, const WorkspaceMapping& mapping, std::vector<Key> keys,
                const Tissue& tissue, std::uint64_t seed)
      : name_(name), mapping_(mapping), keys_(std::move(keys)), tissue_(tissue), seed_(seed) {}

  [[nodiscard]] std::string_view name() const noexcept override { return name_; }
  [[nodiscard]] double cycle_s() const noexcept override { return keys_.back().t_s; }

  [[nodiscard]] const WorkspaceMapping& mapping() const noexcept override { return mapping_; }

  bool latest(TimePoint now, SlaveSample& out) noexcept override {
    const std::int64_t elapsed_ns = (now - start()).count();
    if (elapsed_ns < 0) {
      return false;  // the robot has not started
    }
    const std::int64_t k = elapsed_ns / kSlavePeriod_ns;
    const SlaveTruth s = slave_truth(static_cast<double>(k) * kSlavePeriod_s);
    const double noisy_N = s.force_N + kForceNoise_N * standard_normal(seed_, static_cast<std::uint64_t>(k));
    out.stamp = start() + Duration{k * kSlavePeriod_ns};
    out.received = TimePoint{};
    out.force_N = s.indentation_m > 0.0 ? std::max(0.0, noisy_N) : 0.0;
    out.indentation_m = s.indentation_m;
    out.contact_x_m = s.contact_x_m;
    out.contact_y_m = s.contact_y_m;
    out.tip_radius_m = kTipRadius_m;
    out.valid = true;
    return true;
  }

  [[nodiscard]] TissueModel tissue_at(double x_m, double y_m) const noexcept override {
    if (tissue_.inclusion_scale == 1.0) {
      return tissue_.base;
    }
    const double r_m = std::hypot(x_m - (mapping_.origin_x_m + tissue_.inclusion_x_m),
                                  y_m - (mapping_.origin_y_m + tissue_.inclusion_y_m));
    const double inside = 1.0 - smoothstep((r_m - tissue_.inclusion_radius_m) / tissue_.rim_m);
    return tissue_.base.scaled(1.0 + (tissue_.inclusion_scale - 1.0) * inside);
  }

  [[nodiscard]] SlaveTruth slave_truth(double t_s) const noexcept override {
    const Pose p = pose(t_s);
    const double x_m = mapping_.origin_x_m + p.x_m;
    const double y_m = mapping_.origin_y_m + p.y_m;
    return {.contact_x_m = x_m,
            .contact_y_m = y_m,
            .indentation_m = p.depth_m,
            .rate_m_per_s = p.rate_m_per_s,
            .force_N = tissue_at(x_m, y_m).force_N(p.depth_m, p.rate_m_per_s)};
  }

 private:
  static constexpr std::int64_t kSlavePeriod_ns = 1'000'000;  // the robot streams at 1 kHz
  static constexpr double kSlavePeriod_s = 1e-3;
  static constexpr double kForceNoise_N = 0.005;  // RMS

  // Before the start: the first key (out of contact).
  [[nodiscard]] Pose pose(double t_s) const noexcept {
    const double t = t_s > 0.0 ? std::fmod(t_s, cycle_s()) : 0.0;
    for (std::size_t i = 1; i < keys_.size(); ++i) {
      const Key& b = keys_[i];
      if (t < b.t_s) {
        const Key& a = keys_[i - 1];
        const double span_s = b.t_s - a.t_s;
        const double u = (t - a.t_s) / span_s;
        const double e = b.linear ? u : smoothstep(u);
        const double de_du = b.linear ? 1.0 : smoothstep_slope(u);
        return {.x_m = a.x_m + (b.x_m - a.x_m) * e,
                .y_m = a.y_m + (b.y_m - a.y_m) * e,
                .depth_m = a.depth_m + (b.depth_m - a.depth_m) * e,
                .rate_m_per_s = (b.depth_m - a.depth_m) * de_du / span_s};
      }
    }
    const Key& last = keys_.back();
    return {.x_m = last.x_m, .y_m = last.y_m, .depth_m = last.depth_m};
  }

  std::string_view name_;  // one of kSceneNames: static storage
  WorkspaceMapping mapping_;
  std::vector<Key> keys_;
  Tissue tissue_;
  std::uint64_t seed_;
};

// Light then deep palpation of the origin: to the preset's lower force, then to its upper one.
std::vector<Key> organ_keys(const TissuePreset& preset) {
  const double light_N = preset.force_min_N > 0.0 ? preset.force_min_N : 0.5 * preset.force_max_N;
  const double light_m = preset.model.depth_for_force_m(light_N);
  const double deep_m = preset.reference_depth_m;
  return {{.t_s = 0.0},
          {.t_s = 0.8, .depth_m = light_m},
          {.t_s = 1.3, .depth_m = light_m},
          {.t_s = 1.8, .depth_m = deep_m},
          {.t_s = 2.8, .depth_m = deep_m},
          {.t_s = 3.8},
          {.t_s = 4.3}};
}

// Press in at (-20 mm, y), slide at 10 mm/s to (+20 mm, y), release, return lifted.
std::vector<Key> sweep_keys(double y_m, double depth_m) {
  constexpr double kFrom_m = -20e-3;
  constexpr double kTo_m = 20e-3;
  return {{.t_s = 0.0, .x_m = kFrom_m, .y_m = y_m},
          {.t_s = 1.0, .x_m = kFrom_m, .y_m = y_m, .depth_m = depth_m},
          {.t_s = 1.5, .x_m = kFrom_m, .y_m = y_m, .depth_m = depth_m},
          {.t_s = 5.5, .x_m = kTo_m, .y_m = y_m, .depth_m = depth_m, .linear = true},
          {.t_s = 6.0, .x_m = kTo_m, .y_m = y_m, .depth_m = depth_m},
          {.t_s = 7.0, .x_m = kTo_m, .y_m = y_m},
          {.t_s = 7.5, .x_m = kFrom_m, .y_m = y_m, .linear = true}};
}

// Press, hold, then load again at a constant 5 mm/s from a standstill: the tissue's damping makes
// the target force step up at the start of the second press (a settling test), and step down
// where it stops.
std::vector<Key> step_keys() {
  return {{.t_s = 0.0},
          {.t_s = 0.6, .depth_m = kStepHoldDepth_m},
          {.t_s = 1.0, .depth_m = kStepHoldDepth_m},
          {.t_s = 1.6, .depth_m = 4.5e-3, .linear = true},
          {.t_s = 2.0, .depth_m = 4.5e-3},
          {.t_s = 3.0},
          {.t_s = 3.5}};
}

// Two force steps of about 1 N for the settling figure (docs/bridge.md, Settling): up, a quick
// press from a hold to a deeper hold (the elastic force); down, a press at a constant speed that
// stops (the damping's force leaves).
std::vector<Key> force_step_keys() {
  return {{.t_s = 0.0},
          {.t_s = 0.6, .depth_m = 1.5e-3},
          {.t_s = 1.0, .depth_m = 1.5e-3},
          {.t_s = 1.35, .depth_m = 4.8e-3},
          {.t_s = 1.95, .depth_m = 4.8e-3},
          {.t_s = 2.55},
          {.t_s = 2.95},
          {.t_s = 3.45, .depth_m = 1.0e-3},
          {.t_s = 3.75, .depth_m = 1.0e-3},
          {.t_s = 3.826, .depth_m = 2.9e-3, .linear = true},
          {.t_s = 4.426, .depth_m = 2.9e-3},
          {.t_s = 5.026},
          {.t_s = 5.45}};
}

std::string name_list() {
  std::string s;
  for (const std::string_view n : kSceneNames) {
    s += s.empty() ? "" : ", ";
    s += n;
  }
  return s;
}

}  // namespace

std::span<const std::string_view> scene_names() noexcept { return kSceneNames; }

std::unique_ptr<Scene> make_scene(std::string_view name, const WorkspaceMapping& mapping) {
  if (name.starts_with("scene://")) {
    name.remove_prefix(8);
  }
  const auto* const it = std::find(kSceneNames.begin(), kSceneNames.end(), name);
  if (it == kSceneNames.end()) {
    throw InvalidArgument("unknown scene '" + std::string(name) + "': available scenes are: " + name_list());
  }
  if (!mapping.valid()) {
    throw InvalidArgument(
        "scene '" + std::string(name) +
        "': the workspace mapping is not valid (finite origin and rotation, cells_per_m > 0)");
  }
  const std::string_view scene = *it;  // static storage, unlike name
  const auto seed = 0x5CE7E000ULL + static_cast<std::uint64_t>(it - kSceneNames.begin());
  if (scene == "demo") {
    return std::make_unique<DemoScene>(mapping);
  }
  if (scene == "sweep") {
    return std::make_unique<ScriptedScene>(scene, mapping, sweep_keys(0.0, 3e-3),
                                           Tissue{.base = *find_preset("stomach_linear")}, seed);
  }
  if (scene == "step") {
    // k x + lambda x x': 0.15 N held at 1.5 mm, 0.45 N the moment it moves on at 5 mm/s.
    return std::make_unique<ScriptedScene>(
        scene, mapping, step_keys(), Tissue{.base = TissueModel::hunt_crossley(100.0, 1.0, 4.0e4)}, seed);
  }
  if (scene == "force_step") {
    // k x + lambda x x': 0.45 N held at 1.5 mm, 1.44 N at 4.8 mm; 1.89 N pressing on at 25 mm/s at
    // 2.9 mm, 0.87 N once it stops there (scene.hpp).
    return std::make_unique<ScriptedScene>(scene, mapping, force_step_keys(),
                                           Tissue{.base = TissueModel::hunt_crossley(300.0, 1.0, 1.4e4)},
                                           seed);
  }
  if (scene == "tumour") {
    const Tissue tissue{.base = *find_preset("abdomen"),
                        .inclusion_scale = 4.0,
                        .inclusion_x_m = 10e-3,
                        .inclusion_y_m = 10e-3,
                        .inclusion_radius_m = 5e-3,
                        .rim_m = 3e-3};
    return std::make_unique<ScriptedScene>(scene, mapping, sweep_keys(10e-3, 2e-3), tissue, seed);
  }
  const TissuePreset* preset = find_tissue_preset(scene);  // an organ: every other name is one
  return std::make_unique<ScriptedScene>(scene, mapping, organ_keys(*preset), Tissue{.base = preset->model},
                                         seed);
}

}  // namespace mrskin::bridge
