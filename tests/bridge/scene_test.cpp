// Built-in scenes (bridge/include/mrskin/bridge/scene.hpp): both sides of every scene stay in the
// skin's range, the slave stream is the scene's tissue law at the contact point, the organs reach
// their Table 2 forces, the sweep crosses the skin, the tumour stands out, and the finger goes
// where the workspace mapping puts the slave. Scene time only: no clocks, no timing.
#include "mrskin/bridge/scene.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <functional>
#include <numbers>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "mrskin/driver/errors.hpp"
#include "mrskin/eval/truth_scorer.hpp"

namespace {

using namespace mrskin;
using namespace mrskin::bridge;

constexpr double kMaxDepth_m = 5e-3;
constexpr double kMaxForce_N = 2.0;
constexpr double kNoiseBound_N = 0.025;  // 5 sigma of the slave's 5 mN force noise
constexpr std::int64_t kMs_ns = 1'000'000;

bool is_organ(std::string_view name) {
  return name != "demo" && name != "sweep" && name != "tumour" && name != "step" && name != "force_step";
}

TimePoint at_ms(std::int64_t k) { return TimePoint{k * kMs_ns}; }

int cycle_ms(const Scene& scene) { return static_cast<int>(std::lround(scene.cycle_s() * 1000.0)); }

// Depth-weighted centre of the finger's pad over the fluid cells; false when nothing is pressed.
bool pressed_centre(const GridLayout& layout, const std::vector<double>& depth_m, CellPoint& centre) {
  double w = 0.0;
  double row = 0.0;
  double col = 0.0;
  for (std::size_t i = 0; i < depth_m.size(); ++i) {
    w += depth_m[i];
    row += depth_m[i] * layout.fluid_cells()[i].row;
    col += depth_m[i] * layout.fluid_cells()[i].col;
  }
  if (!(w > 0.0)) {
    return false;
  }
  centre = {row / w, col / w};
  return true;
}

std::size_t deepest_cell(const std::vector<double>& depth_m) {
  return static_cast<std::size_t>(std::max_element(depth_m.begin(), depth_m.end()) - depth_m.begin());
}

double distance(CellPoint a, CellPoint b) { return std::hypot(a.row - b.row, a.col - b.col); }

// ---- factory -----------------------------------------------------------------------------------

TEST(SceneFactory, EveryNameMakesItsScene) {
  const std::vector<std::string_view> expected = {
      "demo", "hand", "neck", "abdomen", "thigh", "back", "stomach", "sweep", "tumour", "step", "force_step"};
  ASSERT_EQ(std::vector<std::string_view>(scene_names().begin(), scene_names().end()), expected);
  for (const std::string_view name : scene_names()) {
    EXPECT_EQ(make_scene(name)->name(), name);
    EXPECT_EQ(make_scene("scene://" + std::string(name))->name(), name);
    EXPECT_GT(make_scene(name)->cycle_s(), 1.0) << name;
  }
}

TEST(SceneFactory, UnknownNameThrowsWithTheList) {
  for (const std::string_view bad : {"", "scene://", "stomach_linear", "tumor", "DEMO", "scene://nope"}) {
    try {
      (void)make_scene(bad);
      ADD_FAILURE() << "no throw for '" << bad << "'";
    } catch (const InvalidArgument& e) {
      const std::string what = e.what();
      for (const std::string_view name : scene_names()) {
        EXPECT_NE(what.find(name), std::string::npos) << what;
      }
    }
  }
  WorkspaceMapping bad;
  bad.cells_per_m = 0.0;
  EXPECT_THROW((void)make_scene("sweep", bad), InvalidArgument);
  bad = {};
  bad.origin_x_m = std::nan("");
  EXPECT_THROW((void)make_scene("hand", bad), InvalidArgument);
}

// ---- every scene -------------------------------------------------------------------------------

TEST(Scenes, StayInTheSkinsRangeOverACycle) {
  for (const std::string_view name : scene_names()) {
    auto scene = make_scene(name);
    scene->set_start(TimePoint{0});
    for (const auto& layout : {GridLayout(5, 5), GridLayout(16, 16)}) {
      std::vector<double> finger(layout.fluid_cell_count(), -1.0);
      const int n = cycle_ms(*scene);
      double max_force_N = 0.0;
      double max_depth_m = 0.0;
      for (int k = 0; k <= n; ++k) {
        const double t_s = k * 1e-3;
        mrskin::eval::press_scene_finger(*scene, t_s, layout, finger);
        for (const double d : finger) {
          ASSERT_GE(d, 0.0) << name << " t " << t_s;
          ASSERT_LE(d, kMaxDepth_m) << name << " t " << t_s;
          max_depth_m = std::max(max_depth_m, d);
        }
        SlaveSample s;
        ASSERT_TRUE(scene->latest(at_ms(k), s)) << name;
        ASSERT_TRUE(s.valid);
        EXPECT_EQ(s.stamp, at_ms(k)) << name;
        ASSERT_GE(s.force_N, 0.0) << name << " t " << t_s;
        ASSERT_LE(s.force_N, kMaxForce_N) << name << " t " << t_s;
        ASSERT_GE(s.indentation_m, 0.0);
        ASSERT_LE(s.indentation_m, kMaxDepth_m);
        EXPECT_GT(s.tip_radius_m, 0.0);
        if (!(s.indentation_m > 0.0)) {
          ASSERT_EQ(s.force_N, 0.0) << name << " t " << t_s;  // no contact, no force
        }
        if (k == 0 || k == n) {  // a cycle starts and ends out of contact, finger lifted
          EXPECT_EQ(s.indentation_m, 0.0) << name;
          EXPECT_EQ(s.force_N, 0.0) << name;
          EXPECT_EQ(*std::max_element(finger.begin(), finger.end()), 0.0) << name;
        }
        max_force_N = std::max(max_force_N, s.force_N);
      }
      EXPECT_GT(max_force_N, 0.3) << name;  // every scene palpates something
      EXPECT_GT(max_depth_m, 1e-3) << name;
    }
  }
}

TEST(Scenes, RepeatEveryCycle) {
  const GridLayout layout(5, 5);
  for (const std::string_view name : scene_names()) {
    auto scene = make_scene(name);
    std::vector<double> a(layout.fluid_cell_count());
    std::vector<double> b(layout.fluid_cell_count());
    for (const double t_s : {0.25, 1.1, 2.05, 3.3, 5.0}) {
      mrskin::eval::press_scene_finger(*scene, t_s, layout, a);
      mrskin::eval::press_scene_finger(*scene, t_s + 2.0 * scene->cycle_s(), layout, b);
      for (std::size_t i = 0; i < a.size(); ++i) {
        EXPECT_NEAR(a[i], b[i], 1e-9) << name << " t " << t_s;
      }
      EXPECT_NEAR(scene->slave_truth(t_s).force_N, scene->slave_truth(t_s + 2.0 * scene->cycle_s()).force_N,
                  1e-6)
          << name;
    }
  }
}

TEST(Scenes, SlaveForceIsTheTissueLawAtTheContact) {
  for (const std::string_view name : scene_names()) {
    auto scene = make_scene(name);
    scene->set_start(at_ms(1000));
    SlaveSample before;
    EXPECT_EQ(scene->latest(at_ms(999), before), name == "demo") << "a sample before the start";
    const int n = 2 * cycle_ms(*scene);
    double residual_sq = 0.0;
    int in_contact = 0;
    SlaveSample prev;
    SlaveSample cur;
    ASSERT_TRUE(scene->latest(at_ms(1000), prev));
    ASSERT_TRUE(scene->latest(at_ms(1001), cur));
    for (int k = 1; k < n; ++k) {
      SlaveSample next;
      ASSERT_TRUE(scene->latest(at_ms(1001 + k), next));
      const double t_s = k * 1e-3;
      const SlaveTruth truth = scene->slave_truth(t_s);
      EXPECT_NEAR(cur.contact_x_m, truth.contact_x_m, 1e-12);
      EXPECT_NEAR(cur.contact_y_m, truth.contact_y_m, 1e-12);
      EXPECT_NEAR(cur.indentation_m, truth.indentation_m, 1e-12);  // demo: its own ns -> s rounding
      // The truth's rate is the indentation's derivative (central difference over the stream).
      const double rate_m_per_s = (next.indentation_m - prev.indentation_m) / 2e-3;
      // (Up to 1.2e-5 m/s where a smooth segment starts: the difference sees its quadratic start;
      // 5.5e-5 on force_step's 0.3 s press.) "step" changes speed at once where its finger moves
      // on (1.0 s) and stops (1.6 s), force_step where it presses on at 25 mm/s (3.75 s) and stops
      // (3.826 s): there the difference straddles the kink and sees half the change.
      const double in_cycle_s = std::fmod(t_s, scene->cycle_s());
      const auto near = [in_cycle_s](double at_s) { return std::fabs(in_cycle_s - at_s) < 1.5e-3; };
      const bool kink = (name == "step" && (near(1.0) || near(1.6))) ||
                        (name == "force_step" && (near(3.75) || near(3.826)));
      ASSERT_NEAR(truth.rate_m_per_s, rate_m_per_s,
                  kink                   ? (name == "step" ? 2.6e-3 : 12.6e-3)
                  : name == "demo"       ? 2e-4
                  : name == "force_step" ? 6e-5
                                         : 3e-5)
          << name << " t " << t_s;
      const double law_N =
          scene->tissue_at(cur.contact_x_m, cur.contact_y_m).force_N(cur.indentation_m, truth.rate_m_per_s);
      EXPECT_NEAR(truth.force_N, law_N, 1e-12) << name;
      ASSERT_NEAR(cur.force_N, law_N, kNoiseBound_N) << name << " t " << t_s;
      if (law_N > 0.05) {  // clear of the clamp at zero
        residual_sq += (cur.force_N - law_N) * (cur.force_N - law_N);
        ++in_contact;
      }
      prev = cur;
      cur = next;
    }
    ASSERT_GT(in_contact, 1000) << name;
    const double rms_N = std::sqrt(residual_sq / in_contact);
    if (name == "demo") {
      EXPECT_LT(rms_N, 1e-12);  // noiseless
    } else {
      EXPECT_NEAR(rms_N, 0.005, 0.0007) << name;  // the stated noise, and no bias hiding in it
    }
  }
}

TEST(Scenes, ReplayExactlyWhateverTheTickRate) {
  auto a = make_scene("abdomen");
  auto b = make_scene("abdomen");
  for (int k = 0; k < 4300; ++k) {
    SlaveSample sa;
    ASSERT_TRUE(a->latest(at_ms(k), sa));
    for (int sub = 0; sub < 10; ++sub) {  // a 10 kHz caller sees the same 1 kHz stream
      SlaveSample sb;
      ASSERT_TRUE(b->latest(at_ms(k) + Duration{sub * 100'000}, sb));
      ASSERT_EQ(sb.stamp, sa.stamp);
      ASSERT_EQ(sb.force_N, sa.force_N);
    }
  }
}

TEST(DemoScene, KeepsItsStream) {
  auto scene = make_scene("demo");
  const GridLayout layout(5, 5);
  std::vector<double> finger(layout.fluid_cell_count());
  mrskin::eval::press_scene_finger(*scene, 1.5, layout, finger);
  for (std::size_t i = 0; i < finger.size(); ++i) {
    const bool centre = layout.fluid_cells()[i].row == 2 && layout.fluid_cells()[i].col == 2;
    EXPECT_EQ(finger[i], centre ? 4e-3 : 0.0);
  }
  SlaveSample s;
  ASSERT_TRUE(scene->latest(TimePoint{1'500'000'123}, s));
  EXPECT_EQ(s.stamp, TimePoint{1'500'000'123});
  EXPECT_DOUBLE_EQ(s.force_N, 1.2);
  EXPECT_EQ(s.contact_x_m, 0.0);
  EXPECT_EQ(s.contact_y_m, 0.0);
  EXPECT_NEAR(scene->slave_truth(0.5).force_N, 300.0 * 2e-3 + 0.5 * 6e-3, 1e-9);
}

// ---- organs ------------------------------------------------------------------------------------

TEST(OrganScenes, ReachTheirPresetsTable2RangeAtTheHolds) {
  const GridLayout layout(5, 5);
  std::size_t centre_cell = 0;
  for (std::size_t i = 0; i < layout.fluid_cell_count(); ++i) {
    if (layout.fluid_cells()[i].row == 2 && layout.fluid_cells()[i].col == 2) {
      centre_cell = i;
    }
  }
  int organs = 0;
  for (const std::string_view name : scene_names()) {
    if (!is_organ(name)) {
      continue;
    }
    ++organs;
    const TissuePreset* preset = find_tissue_preset(name);
    ASSERT_NE(preset, nullptr) << name;
    const double light_N = preset->force_min_N > 0.0 ? preset->force_min_N : 0.5 * preset->force_max_N;
    auto scene = make_scene(name);
    int deep_hold_ms = 0;
    int light_hold_ms = 0;
    double max_N = 0.0;
    std::vector<double> finger(layout.fluid_cell_count());
    for (int k = 0; k <= cycle_ms(*scene); ++k) {
      const SlaveTruth s = scene->slave_truth(k * 1e-3);
      EXPECT_EQ(s.contact_x_m, 0.0);  // the origin: the skin's centre
      EXPECT_EQ(s.contact_y_m, 0.0);
      EXPECT_EQ(scene->tissue_at(0.03, -0.02).stiffness_N_per_m, preset->model.stiffness_N_per_m);
      max_N = std::max(max_N, s.force_N);
      if (s.rate_m_per_s == 0.0 && std::abs(s.force_N - preset->force_max_N) < 1e-9) {
        ++deep_hold_ms;
        EXPECT_EQ(s.indentation_m, preset->reference_depth_m);
        mrskin::eval::press_scene_finger(*scene, k * 1e-3, layout,
                                         finger);  // the finger holds the same depth, centre cell only
        EXPECT_EQ(finger[centre_cell], preset->reference_depth_m);
        EXPECT_EQ(std::count(finger.begin(), finger.end(), 0.0), static_cast<long>(finger.size() - 1));
      }
      if (s.rate_m_per_s == 0.0 && std::abs(s.force_N - light_N) < 1e-9) {
        ++light_hold_ms;
      }
    }
    EXPECT_GE(deep_hold_ms, 900) << name << ": the upper force, held";
    EXPECT_GE(light_hold_ms, 400) << name << ": the lower force, held";
    EXPECT_LE(max_N, 1.02 * preset->force_max_N) << name;  // damping adds little on the way in
    EXPECT_LE(preset->reference_depth_m, kMaxDepth_m);
  }
  EXPECT_EQ(organs, 6);
  // The numbers scene.hpp states.
  EXPECT_NEAR(find_tissue_preset("hand")->model.depth_for_force_m(0.6), 3.82e-3, 0.005e-3);
  EXPECT_NEAR(find_tissue_preset("stomach")->model.depth_for_force_m(0.6), 2.73e-3, 0.005e-3);
}

// ---- sweep -------------------------------------------------------------------------------------

TEST(SweepScene, FingerCrossesTheSkinWithTheSlave) {
  const WorkspaceMapping mapping;
  auto scene = make_scene("sweep", mapping);
  for (const auto& layout : {GridLayout(5, 5), GridLayout(16, 16)}) {
    std::vector<double> finger(layout.fluid_cell_count());
    std::set<std::size_t> deepest;
    std::set<std::size_t> pressed;
    double max_error_cells = 0.0;
    double min_x_m = 1.0;
    double max_x_m = -1.0;
    for (int k = 0; k <= cycle_ms(*scene); ++k) {
      const SlaveTruth s = scene->slave_truth(k * 1e-3);
      mrskin::eval::press_scene_finger(*scene, k * 1e-3, layout, finger);
      if (s.indentation_m < 0.5e-3) {
        continue;
      }
      CellPoint centre;
      ASSERT_TRUE(pressed_centre(layout, finger, centre));
      const CellPoint mapped = mapping.to_cell(s.contact_x_m, s.contact_y_m, layout.rows(), layout.cols());
      max_error_cells = std::max(max_error_cells, distance(centre, mapped));
      deepest.insert(deepest_cell(finger));
      for (std::size_t i = 0; i < finger.size(); ++i) {
        if (finger[i] > 0.0) {
          pressed.insert(i);
        }
      }
      min_x_m = std::min(min_x_m, s.contact_x_m);
      max_x_m = std::max(max_x_m, s.contact_x_m);
      EXPECT_NEAR(s.force_N, 0.9, s.rate_m_per_s == 0.0 ? 1e-12 : 0.9);  // 300 N/m x 3 mm
    }
    EXPECT_LE(max_error_cells, 1.0) << layout.rows();
    EXPECT_GE(deepest.size(), 3U) << layout.rows();  // the pad moves from cell to cell
    EXPECT_GE(pressed.size(), 6U) << layout.rows();
    EXPECT_NEAR(max_x_m - min_x_m, 40e-3, 1e-9);
    if (layout.rows() == 5) {  // edge to edge along the middle row
      for (const GridCell c : {GridCell{2, 0}, GridCell{2, 2}, GridCell{2, 4}}) {
        const auto it = std::find_if(layout.fluid_cells().begin(), layout.fluid_cells().end(),
                                     [&](const GridCell& f) { return f.row == c.row && f.col == c.col; });
        EXPECT_TRUE(deepest.contains(static_cast<std::size_t>(it - layout.fluid_cells().begin())))
            << c.row << "," << c.col;
      }
    }
  }
}

// ---- tumour ------------------------------------------------------------------------------------

TEST(TumourScene, ForceRisesOverTheInclusion) {
  auto scene = make_scene("tumour");
  const TissueModel soft = *find_preset("abdomen");
  // scene.hpp: 4 x abdomen within 5 mm of (10 mm, 10 mm), abdomen from 8 mm out.
  EXPECT_DOUBLE_EQ(scene->tissue_at(10e-3, 10e-3).stiffness_N_per_m, 4.0 * soft.stiffness_N_per_m);
  EXPECT_DOUBLE_EQ(scene->tissue_at(14.9e-3, 10e-3).stiffness_N_per_m, 4.0 * soft.stiffness_N_per_m);
  EXPECT_DOUBLE_EQ(scene->tissue_at(10e-3, 18.1e-3).stiffness_N_per_m, soft.stiffness_N_per_m);
  EXPECT_DOUBLE_EQ(scene->tissue_at(-10e-3, 10e-3).stiffness_N_per_m, soft.stiffness_N_per_m);

  const GridLayout layout(5, 5);
  std::vector<double> finger(layout.fluid_cell_count());
  double over_N = 0.0;
  double beside_N = 10.0;
  int over = 0;
  int beside = 0;
  double previous_N = 0.0;
  double max_step_N = 0.0;
  for (int k = 0; k <= cycle_ms(*scene); ++k) {
    const SlaveTruth s = scene->slave_truth(k * 1e-3);
    if (std::abs(s.indentation_m - 2e-3) > 1e-12) {
      previous_N = s.force_N;
      continue;
    }
    max_step_N = std::max(max_step_N, std::abs(s.force_N - previous_N));  // the rim is smooth
    previous_N = s.force_N;
    const double from_inclusion_m = std::hypot(s.contact_x_m - 10e-3, s.contact_y_m - 10e-3);
    if (from_inclusion_m < 1e-3) {
      ++over;
      over_N = std::max(over_N, s.force_N);
      mrskin::eval::press_scene_finger(*scene, k * 1e-3, layout, finger);
      EXPECT_EQ(layout.fluid_cells()[deepest_cell(finger)].row, 3);
      EXPECT_EQ(layout.fluid_cells()[deepest_cell(finger)].col, 3);
    } else if (from_inclusion_m > 10e-3) {
      ++beside;
      beside_N = std::min(beside_N, s.force_N);
    }
  }
  ASSERT_GT(over, 100);
  ASSERT_GT(beside, 100);
  EXPECT_GT(over_N, 3.0 * beside_N) << over_N << " vs " << beside_N;
  EXPECT_NEAR(over_N, 4.0 * soft.force_N(2e-3, 0.0), 0.02);
  EXPECT_NEAR(beside_N, soft.force_N(2e-3, 0.0), 1e-9);
  EXPECT_LT(max_step_N, 0.01);
}

// ---- mapping -----------------------------------------------------------------------------------

// Cell (r, c) of the 5x5 under `mapping` is the default mapping's cell `to_default(r, c)`.
// moves: whether the finger then presses elsewhere than under the default mapping.
void expect_finger_maps(std::string_view name, const WorkspaceMapping& mapping, bool moves,
                        const std::function<GridCell(int, int)>& to_default) {
  const GridLayout layout(5, 5);
  auto plain = make_scene(name);
  auto mapped = make_scene(name, mapping);
  std::vector<double> a(layout.fluid_cell_count());
  std::vector<double> b(layout.fluid_cell_count());
  int moved = 0;
  for (int k = 0; k <= cycle_ms(*plain); k += 7) {
    mrskin::eval::press_scene_finger(*plain, k * 1e-3, layout, a);
    mrskin::eval::press_scene_finger(*mapped, k * 1e-3, layout, b);
    for (std::size_t i = 0; i < b.size(); ++i) {
      const GridCell c = to_default(layout.fluid_cells()[i].row, layout.fluid_cells()[i].col);
      const auto& cells = layout.fluid_cells();
      const auto j = static_cast<std::size_t>(
          std::find_if(cells.begin(), cells.end(),
                       [&](const GridCell& f) { return f.row == c.row && f.col == c.col; }) -
          cells.begin());
      ASSERT_LT(j, a.size());
      ASSERT_NEAR(b[i], a[j], 1e-9) << name << " t " << k << " ms";
      moved += static_cast<int>(std::abs(b[i] - a[i]) > 1e-4);
    }
    EXPECT_EQ(plain->slave_truth(k * 1e-3).force_N, mapped->slave_truth(k * 1e-3).force_N);
  }
  if (moves) {
    EXPECT_GT(moved, 100) << name;
  } else {
    EXPECT_EQ(moved, 0) << name;
  }
}

TEST(SceneMapping, MirroredFingerMirrors) {
  WorkspaceMapping mirror_x;
  mirror_x.mirror_x = true;
  WorkspaceMapping mirror_y;
  mirror_y.mirror_y = true;
  const auto flip_cols = [](int r, int c) { return GridCell{r, 4 - c}; };
  const auto flip_rows = [](int r, int c) { return GridCell{4 - r, c}; };
  expect_finger_maps("sweep", mirror_x, true, flip_cols);
  expect_finger_maps("sweep", mirror_y, false, flip_rows);  // along the middle row: its own mirror
  expect_finger_maps("tumour", mirror_x, true, flip_cols);
  expect_finger_maps("tumour", mirror_y, true, flip_rows);  // row 3 -> row 1
  expect_finger_maps("back", mirror_x, false, flip_cols);   // the centre maps onto itself
  expect_finger_maps("demo", mirror_y, false, flip_rows);
}

TEST(SceneMapping, RotatedFingerRotates) {
  WorkspaceMapping quarter;
  quarter.rotation_rad = 0.5 * std::numbers::pi;  // +x on the tissue runs down the skin's rows
  for (const std::string_view name : {"sweep", "tumour"}) {
    expect_finger_maps(name, quarter, true, [](int r, int c) { return GridCell{4 - c, r}; });
  }
}

TEST(SceneMapping, FingerIsWhereTheMappingPutsTheSlaveUnderAnyMapping) {
  std::vector<WorkspaceMapping> mappings(6);
  mappings[1].mirror_x = true;
  mappings[2].rotation_rad = 0.52;
  mappings[3].origin_x_m = 0.3;  // the slave palpates around another point of its workspace
  mappings[3].origin_y_m = -0.1;
  mappings[4].cells_per_m = 60.0;
  mappings[5].mirror_y = true;
  mappings[5].rotation_rad = -2.0;
  mappings[5].cells_per_m = 130.0;
  for (const std::string_view name : scene_names()) {
    for (const WorkspaceMapping& mapping : mappings) {
      auto scene = make_scene(name, mapping);
      for (const auto& layout : {GridLayout(5, 5), GridLayout(16, 16)}) {
        std::vector<double> finger(layout.fluid_cell_count());
        int checked = 0;
        for (int k = 0; k <= cycle_ms(*scene); k += 3) {
          const SlaveTruth s = scene->slave_truth(k * 1e-3);
          const CellPoint mapped =
              mapping.to_cell(s.contact_x_m, s.contact_y_m, layout.rows(), layout.cols());
          mrskin::eval::press_scene_finger(*scene, k * 1e-3, layout, finger);
          CellPoint centre;
          const bool on_skin = mapped.row >= 0.0 && mapped.row <= layout.rows() - 1 && mapped.col >= 0.0 &&
                               mapped.col <= layout.cols() - 1;
          if (s.indentation_m < 0.5e-3 || !on_skin) {
            continue;
          }
          ASSERT_TRUE(pressed_centre(layout, finger, centre)) << name;
          ASSERT_LE(distance(centre, mapped), 1.0) << name << " t " << k << " ms";
          ++checked;
        }
        EXPECT_GT(checked, 100) << name;
      }
      if (is_organ(name) || name == "demo") {  // the organs palpate the mapping's origin
        EXPECT_EQ(scene->slave_truth(2.3).contact_x_m, mapping.origin_x_m);
        EXPECT_EQ(scene->slave_truth(2.3).contact_y_m, mapping.origin_y_m);
      }
    }
  }
}

}  // namespace
