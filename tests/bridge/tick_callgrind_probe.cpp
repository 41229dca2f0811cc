// Instruction-count probe for the bridge tick (Bridge::step: session poll, observer, tissue and
// targets, inverse, allocation, encode), run under
//   valgrind --tool=callgrind --instr-atstart=no --collect-atstart=no
// (see tick_callgrind_gate.sh). The mock device runs a synthetic plant: the sensors read a
// depth pattern (no hydraulics), so that a 64 x 64 unit can be driven under valgrind; its
// forces are never read. Warm-up runs uninstrumented; then the probe switches instrumentation on
// and collects around Bridge::step only (CALLGRIND_TOGGLE_COLLECT), so the mock's firmware and
// plant stepping between ticks are not counted.
//
//   tick_callgrind_probe CASE PROFILE_DIR
//   CASE: idle5     5 x 5, nothing touches the skin
//         load5     5 x 5, the centre cell loading at 4.5 mm/s (0.9 to 3.6 mm)
//         hold5     5 x 5, the centre cell held at 4 mm
//         grid0     64 x 64, nothing touches the skin
//         grid5     64 x 64, a compact patch of 5 % of the fluid cells loading at 1 mm/s
//         grid100   64 x 64, every fluid cell loading at 1 mm/s
// The firmware adds the profile's sensor noise (seeded: the counts repeat). Prints "ticks N"
// (the number of collected ticks) for the gate to divide by, and the bridge's state at the end.
// For measurements (docs/protocol.md, "Sensor deadband (1.2)"): MRSKIN_PROBE_DEADBAND=N gives the
// unit a declared sensor deadband of N counts, MRSKIN_PROBE_NO_SENSOR_FAULTS=1 turns the bridge's
// sensor-fault tests off.
#include <valgrind/callgrind.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <numeric>
#include <span>
#include <string>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/driver/session.hpp"
#include "mrskin/sim/mock_device.hpp"
#include "mrskin/sim/plant.hpp"

namespace {

using namespace mrskin;

// Sensors from the finger's depth, as the network plant's (a fluid-cell sensor reads its pad
// depth, a valve sensor the mean of the cells it joins); pad depth = finger depth.
class PatternPlant final : public sim::Plant {
 public:
  explicit PatternPlant(const model::DeviceProfile& profile)
      : profile_(profile), layout_(profile.rows, profile.cols), depth_(layout_.fluid_cell_count(), 0.0) {}
  [[nodiscard]] std::size_t sensor_count() const noexcept override { return profile_.sensors.size(); }
  void set_valve_currents(std::span<const double> /*current_A*/) noexcept override {}
  void set_finger_indentation(std::span<const double> indentation_m) noexcept override {
    for (std::size_t i = 0; i < depth_.size() && i < indentation_m.size(); ++i) {
      depth_[i] = std::max(0.0, indentation_m[i]);
    }
  }
  void step(double /*dt_s*/) noexcept override {}
  void read_sensors(std::span<double> out) const noexcept override {
    for (std::size_t k = 0; k < out.size() && k < profile_.sensors.size(); ++k) {
      const model::SensorSpec& s = profile_.sensors[k];
      double value = 0.0;
      if (s.quantity == model::SensorQuantity::displacement && s.place == model::PlaceKind::fluid_cell) {
        value = depth_[s.index];
      } else if (s.quantity == model::SensorQuantity::displacement && s.place == model::PlaceKind::valve) {
        const std::vector<std::size_t>& joined = layout_.cells_of_valve(s.index);
        for (const std::size_t c : joined) {
          value += depth_[c];
        }
        value /= static_cast<double>(std::max<std::size_t>(joined.size(), 1));
      }
      out[k] = value;
    }
  }
  void contact_forces(std::span<double> out_N) const noexcept override {
    for (std::size_t i = 0; i < out_N.size() && i < depth_.size(); ++i) {
      out_N[i] = 300.0 * depth_[i];
    }
  }

 private:
  model::DeviceProfile profile_;
  GridLayout layout_;
  std::vector<double> depth_;
};

// A slave that keeps touching tissue of one stiffness: a fresh sample every tick.
class SteadySlave final : public bridge::SlaveSource {
 public:
  explicit SteadySlave(double stiffness_N_per_m) : stiffness_(stiffness_N_per_m) {}
  bool latest(TimePoint now, bridge::SlaveSample& out) noexcept override {
    out = {};
    out.stamp = now;
    out.indentation_m = 2e-3;
    out.force_N = stiffness_ * out.indentation_m;
    out.valid = true;
    return true;
  }

 private:
  double stiffness_;
};

struct Case {
  std::string profile;
  double stiffness_N_per_m = 300.0;
  int warmup = 0;  // uninstrumented ticks
  int ticks = 0;   // collected ticks
  // Finger depth of each fluid cell at tick k.
  std::vector<std::size_t> cells;
  std::vector<double> shape;  // depth scale per pressed cell
  double depth0_m = 0.0;      // at the first tick
  double rate_m_per_tick = 0.0;
  double max_m = 5e-3;
  int press_from = 0;  // the finger touches from this tick
};

}  // namespace

int main(int argc, char** argv) {
  if (argc < 3) {
    std::fprintf(stderr, "usage: %s idle5|load5|hold5|grid0|grid5|grid100 PROFILE_DIR\n", argv[0]);
    return 2;
  }
  const std::string which = argv[1];
  const std::string dir = argv[2];
  Case c;
  const bool small = which == "idle5" || which == "load5" || which == "hold5";
  c.profile = dir + (small ? "/mr-skin-5x5.toml" : "/palm-64x64.toml");
  const model::LoadedProfile loaded = model::load_profile_with_text(c.profile);
  const GridLayout layout(loaded.profile.rows, loaded.profile.cols);
  const std::size_t cells = layout.fluid_cell_count();
  if (small) {
    c.stiffness_N_per_m = 300.0;
    c.ticks = 1000;
    const std::size_t centre = 6;  // (2, 2) of the 5 x 5
    if (which == "load5") {
      // 0 at tick 300, 4.5 mm/s: collected from 0.9 mm to 5.4 mm... capped at 4 mm: 100..~1000.
      c.cells = {centre};
      c.shape = {1.0};
      c.press_from = 300;
      c.rate_m_per_tick = 4.5e-6;
      c.max_m = 4.2e-3;
      c.warmup = 300 + 200;
      c.ticks = 600;
    } else if (which == "hold5") {
      c.cells = {centre};
      c.shape = {1.0};
      c.press_from = 300;
      c.rate_m_per_tick = 4.5e-6;
      c.max_m = 4e-3;
      c.warmup = 300 + 1400;  // held since ~tick 1190
    } else {
      c.warmup = 500;
    }
  } else {
    c.stiffness_N_per_m = 30.0;  // ~0.05 N at 1.5 mm: the palm's range
    c.ticks = which == "grid100" ? 10 : 20;
    double fraction = 0.0;
    if (which == "grid5") {
      fraction = 0.05;
    } else if (which == "grid100") {
      fraction = 1.0;
    } else if (which != "grid0") {
      std::fprintf(stderr, "unknown case %s\n", which.c_str());
      return 2;
    }
    // The fraction of fluid cells nearest the grid's centre: one compact patch (a palm press).
    const auto count = static_cast<std::size_t>(std::lround(fraction * static_cast<double>(cells)));
    std::vector<std::size_t> order(cells);
    std::iota(order.begin(), order.end(), std::size_t{0});
    const double rc = 0.5 * (loaded.profile.rows - 1);
    const double cc = 0.5 * (loaded.profile.cols - 1);
    auto r2 = [&](std::size_t i) {
      const GridCell& g = layout.fluid_cells()[i];
      return (g.row - rc) * (g.row - rc) + (g.col - cc) * (g.col - cc);
    };
    std::stable_sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) { return r2(a) < r2(b); });
    order.resize(count);
    const double r2max = count > 0 ? r2(order.back()) + 1.0 : 1.0;
    for (const std::size_t i : order) {
      c.cells.push_back(i);
      c.shape.push_back(1.0 - 0.3 * r2(i) / r2max);  // deepest at the centre
    }
    c.press_from = 20;
    c.depth0_m = 0.5e-3;
    c.rate_m_per_tick = 1e-6;
    c.max_m = 3e-3;
    c.warmup = 60;
  }
  if (c.ticks == 0) {
    std::fprintf(stderr, "unknown case %s\n", which.c_str());
    return 2;
  }

  sim::MockOptions mock_options;
  mock_options.seed = 11;
  mock_options.calibration_error = -1.0;  // the nominal calibration: no plant to measure
  // MRSKIN_PROBE_DEADBAND=N: the unit's declared sensor deadband in counts (mock://?deadband=N).
  if (const char* band = std::getenv("MRSKIN_PROBE_DEADBAND"); band != nullptr) {
    mock_options.sensor_deadband_counts = std::atoi(band);
  }
  auto mock = std::make_shared<sim::MockDevice>(loaded.profile, loaded.text, mock_options,
                                                std::make_unique<PatternPlant>(loaded.profile));
  SimulatedClock clock;
  DeviceSession session(mock->connect(true, &clock), clock, SessionOptions{});
  SteadySlave slave(c.stiffness_N_per_m);
  bridge::BridgeOptions options;
  options.sensor_faults.enabled = std::getenv("MRSKIN_PROBE_NO_SENSOR_FAULTS") == nullptr;
  bridge::Bridge loop(session, slave, options);
  loop.set_perf_clock(&clock);
  std::vector<double> finger(cells, 0.0);
  auto finger_at = [&](int k) {
    std::fill(finger.begin(), finger.end(), 0.0);
    if (k < c.press_from) {
      return;
    }
    const double depth = std::min(c.max_m, c.depth0_m + c.rate_m_per_tick * (k - c.press_from));
    for (std::size_t j = 0; j < c.cells.size(); ++j) {
      finger[c.cells[j]] = depth * c.shape[j];
    }
  };
  int k = 0;
  auto tick = [&](bool collect) {
    finger_at(k);
    mock->set_finger_indentation(finger);
    mock->step(clock.now());
    if (collect) {
      CALLGRIND_TOGGLE_COLLECT;
    }
    const ResultCode rc = loop.step(clock.now());
    if (collect) {
      CALLGRIND_TOGGLE_COLLECT;
    }
    clock.advance(std::chrono::milliseconds(1));
    ++k;
    return rc;
  };
  if (loop.enable() != ResultCode::ok) {
    std::fprintf(stderr, "enable failed\n");
    return 1;
  }
  for (int w = 0; w < c.warmup; ++w) {
    (void)tick(false);
  }
  int failures = 0;
  CALLGRIND_START_INSTRUMENTATION;
  for (int t = 0; t < c.ticks; ++t) {
    failures += tick(true) == ResultCode::ok ? 0 : 1;
  }
  CALLGRIND_STOP_INSTRUMENTATION;
  const model::CellObserver& obs = loop.observer();
  std::size_t touched = 0;
  double max_depth = 0.0;
  for (std::size_t i = 0; i < cells; ++i) {
    touched += obs.indentation_m()[i] > 50e-6 ? 1 : 0;
    max_depth = std::max(max_depth, obs.indentation_m()[i]);
  }
  const bridge::BridgeStats& s = loop.stats();
  std::printf("ticks %d\nfailures %d\ncells %zu pressed %zu observed_in_contact %zu max_depth_mm %.3f\n",
              c.ticks, failures, cells, c.cells.size(), touched, max_depth * 1e3);
  std::printf("inverse loaded %zu cached %llu observer_errors %llu inverse_errors %llu\n",
              loop.inverse().report().loaded_cells, static_cast<unsigned long long>(s.inverse_cached),
              static_cast<unsigned long long>(s.observer_errors),
              static_cast<unsigned long long>(s.inverse_errors));
  return failures == 0 ? 0 : 1;
}
