// The behaviour reference for refactoring the tick (issue 19): every built-in scene at seed 7 on
// the simulated clock, its statistics against tests/bridge/golden/scene_stats_seed7.txt. Counts
// (ticks, samples, clamped cell-ticks, ...) must be identical and forces, currents and energies
// within 1e-9 of their unit. g++ release builds only: another compiler or a sanitizer's
// instrumentation may round differently, which is not a change of behaviour.
//   MRSKIN_UPDATE_GOLDEN=1 build/release/tests/bridge/bridge_reference_test   rewrites the file
// (an intended change of behaviour: say so in the commit).
#include <gtest/gtest.h>

#include <cmath>
#include <cstdlib>
#include <fstream>
#include <iterator>
#include <map>
#include <sstream>
#include <string>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "scene_rig.hpp"

namespace mrskin::bridge {
namespace {

constexpr double kSeconds = 8.0;

struct Field {
  std::string key;
  double value = 0.0;
  bool exact = false;  // a count
};

std::vector<Field> fields_of(const BridgeStats& s) {
  const auto count = [](const char* key, std::uint64_t v) {
    return Field{key, static_cast<double>(v), true};
  };
  const auto real = [](const char* key, double v) { return Field{key, v, false}; };
  return {
      count("ticks", s.ticks),
      count("slave_samples", s.slave_samples),
      count("stale_ticks", s.stale_ticks),
      count("force_samples", s.force_samples),
      count("release_samples", s.release_samples),
      count("target_cell_ticks", s.target_cell_ticks),
      count("clamped_cell_ticks", s.clamped_cell_ticks),
      count("relative_error_samples", s.relative_error.count()),
      count("unchanged_sends_skipped", s.unchanged_sends_skipped),
      count("inverse_cached", s.inverse_cached),
      count("observer_errors", s.observer_errors),
      count("inverse_errors", s.inverse_errors),
      count("sensor_faults", s.sensor_faults),
      count("active_ticks", s.active_ticks),
      count("clamped_floor_viscous", s.clamp_causes.floor_viscous),
      count("clamped_floor_membrane", s.clamp_causes.floor_membrane),
      count("clamped_floor_p0", s.clamp_causes.floor_p0),
      count("clamped_ceiling", s.clamp_causes.ceiling),
      real("force_rms_error_n", s.force_rms_error_N()),
      real("force_max_abs_error_n", s.force_max_abs_error_N),
      real("true_state_rms_error_n", s.true_state_rms_error_N()),
      real("release_rms_error_n", s.release_rms_error_N()),
      real("relative_error_p95", s.relative_error.percentile(0.95)),
      real("true_state_relative_error_p95", s.true_state_relative_error.percentile(0.95)),
      real("unclamped_rms_error_n", s.unclamped_rms_error_N()),
      real("unclamped_true_state_rms_error_n", s.unclamped_true_state_rms_error_N()),
      real("unclamped_relative_error_p95", s.unclamped.relative_error.percentile(0.95)),
      real("unclamped_true_state_relative_error_p95", s.unclamped.true_state_relative_error.percentile(0.95)),
      real("clamped_missed_force_mean_n", s.clamped_missed_force_mean_N()),
      real("max_current_a", s.max_current_A),
      real("inverse_residual_sum_n", s.inverse_residual_sum_N),
      real("passivity_energy_j", s.passivity_energy_J),
      real("passivity_min_energy_j", s.passivity_min_energy_J),
  };
}

std::string line_of(std::string_view scene, const std::vector<Field>& fields) {
  std::ostringstream out;
  out.precision(17);
  out << scene;
  for (const Field& f : fields) {
    out << ' ' << f.key << '=' << f.value;
  }
  return out.str();
}

// scene -> key -> value
std::map<std::string, std::map<std::string, double>> read_golden(const std::string& path) {
  std::map<std::string, std::map<std::string, double>> golden;
  std::ifstream in(path);
  std::string line;
  while (std::getline(in, line)) {
    if (line.empty() || line[0] == '#') {
      continue;
    }
    std::istringstream words(line);
    std::string scene;
    words >> scene;
    std::string kv;
    while (words >> kv) {
      const std::size_t eq = kv.find('=');
      golden[scene][kv.substr(0, eq)] = std::strtod(kv.c_str() + eq + 1, nullptr);
    }
  }
  return golden;
}

TEST(Reference, EveryScenesStatisticsAtSeed7MatchTheGoldenFile) {
#if defined(MRSKIN_SANITIZED) || defined(__clang__) || !defined(NDEBUG)
  GTEST_SKIP() << "the golden file is the g++ release build's";
#endif
  const std::string path = std::string(MRSKIN_GOLDEN_DIR) + "/scene_stats_seed7.txt";
  const bool update = std::getenv("MRSKIN_UPDATE_GOLDEN") != nullptr;
  std::string text =
      "# Every built-in scene, 8 s on the simulated clock, mock://?seed=7, default BridgeOptions:\n"
      "# tests/bridge/reference_test.cpp (MRSKIN_UPDATE_GOLDEN=1 rewrites it).\n";
  const auto golden = read_golden(path);
  if (!update) {
    ASSERT_FALSE(golden.empty()) << path << " is missing or empty";
  }
  for (const std::string_view name : scene_names()) {
    const test::SceneRun r = test::run_scene(std::string(name), kSeconds, "mock://?seed=7");
    const std::vector<Field> fields = fields_of(r.stats);
    text += line_of(name, fields) + "\n";
    // Every clamped cell-tick has one cause.
    const BridgeStats::ClampCauses& causes = r.stats.clamp_causes;
    EXPECT_EQ(causes.floor_viscous + causes.floor_membrane + causes.floor_p0 + causes.ceiling,
              r.stats.clamped_cell_ticks)
        << name;
    if (update) {
      continue;
    }
    const auto scene = golden.find(std::string(name));
    ASSERT_NE(scene, golden.end()) << name << " is not in " << path;
    for (const Field& f : fields) {
      const auto want = scene->second.find(f.key);
      ASSERT_NE(want, scene->second.end()) << name << ": " << f.key << " is not in " << path;
      if (f.exact) {
        EXPECT_EQ(f.value, want->second) << name << ": " << f.key;
      } else {
        EXPECT_NEAR(f.value, want->second, 1e-9) << name << ": " << f.key;
      }
    }
  }
  if (update) {
    std::ofstream(path) << text;
    std::printf("wrote %s\n", path.c_str());  // NOLINT(cppcoreguidelines-pro-type-vararg)
  }
}

// A measurement, not a test: the same rig on another unit, MRSKIN_REFERENCE_DEVICE (default
// mock://?seed=7, the golden file's), one table row a scene: clamped, RMS error, p95 relative,
// unclamped RMS, release RMS (MRSKIN_REFERENCE_SCENES=demo,sweep: only those). docs/model.md's
// closed-loop table of the designed profile:
//   MRSKIN_REFERENCE_DEVICE="mock://$PWD/tools/model-bench/results/design/designed.toml?seed=7"
//   build/release/tests/bridge/bridge_reference_test --gtest_also_run_disabled_tests
//     --gtest_filter='*MeasureEveryScene*'      (one command, the variable set before it)
TEST(Reference, DISABLED_MeasureEverySceneOnADevice) {
  const char* env = std::getenv("MRSKIN_REFERENCE_DEVICE");
  const std::string device = env != nullptr ? env : "mock://?seed=7";
  std::printf("%s, %.0f s on the simulated clock, default BridgeOptions%s\n", device.c_str(), kSeconds,
              std::getenv("MRSKIN_REFERENCE_AS_GIVEN") != nullptr ? " (scale_to_design off)" : "");
  std::printf(
      "| scene | clamped | RMS error | p95 relative | unclamped RMS | release RMS "
      "|\n|---|---|---|---|---|---|\n");
  // MRSKIN_REFERENCE_AS_GIVEN set: BridgeOptions::scale_to_design off (the reference design's
  // thresholds, laws and finger on any unit, as before the design scale).
  BridgeOptions options;
  options.scale_to_design = std::getenv("MRSKIN_REFERENCE_AS_GIVEN") == nullptr;
  // MRSKIN_REFERENCE_SCENES: a comma-separated list of scenes (default: every scene; the palm
  // takes minutes a scene).
  const char* only = std::getenv("MRSKIN_REFERENCE_SCENES");
  const std::string wanted = only != nullptr ? "," + std::string(only) + "," : std::string();
  for (const std::string_view name : scene_names()) {
    if (!wanted.empty() && wanted.find("," + std::string(name) + ",") == std::string::npos) {
      continue;
    }
    const BridgeStats s = test::run_scene(std::string(name), kSeconds, device, nullptr, 0, options).stats;
    std::printf("| %s | %.1f %% | %.4f N | %.1f %% | %.4f N | %.4f N |\n", std::string(name).c_str(),
                100.0 * s.clamped_fraction(), s.force_rms_error_N(),
                100.0 * s.relative_error.percentile(0.95), s.unclamped_rms_error_N(),
                s.release_rms_error_N());
  }
}

// docs/statistics.md is the one table of the statistics' keys: every key to_json writes is in it.
TEST(Reference, EveryStatisticsKeyIsDocumented) {
  const std::string json = to_json(BridgeStats{}, 1e-3);
  std::ifstream in(std::string(MRSKIN_DOCS_DIR) + "/statistics.md");
  const std::string doc((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  ASSERT_FALSE(doc.empty());
  EXPECT_NE(json.find("\"format_version\": " + std::to_string(kStatisticsFormatVersion)), std::string::npos);
  std::size_t keys = 0;
  for (std::size_t at = json.find('"'); at != std::string::npos; at = json.find('"', at)) {
    const std::size_t end = json.find('"', at + 1);
    ASSERT_NE(end, std::string::npos);
    const std::string key = json.substr(at + 1, end - at - 1);
    if (json.compare(end + 1, 1, ":") == 0) {
      ++keys;
      EXPECT_NE(doc.find("`" + key + "`"), std::string::npos) << key << " is not in docs/statistics.md";
    }
    at = end + 1;
  }
  EXPECT_GT(keys, 40U);
}

}  // namespace
}  // namespace mrskin::bridge
