// Per-sensor statistics over a window of telemetry, and the press-release experiment that
// selftest's valve sweep and leak check and calibrate's yield sweep share.
#pragma once

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

#include "ctl_device_rig.hpp"

namespace mrskin::ctl {

struct SensorStats {
  std::vector<double> mean;
  std::vector<double> std_dev;
  std::vector<double> min;
  std::vector<double> max;
  std::size_t samples = 0;
};

// Ticks the rig for duration_s, accumulating every new telemetry sample; each() runs per tick
// (to keep commands alive).
template <class F>
SensorStats sample_sensors(Rig& rig, double duration_s, F&& each) {
  const std::size_t n = rig.info().sensors;
  std::vector<double> sum(n, 0.0);
  std::vector<double> sum2(n, 0.0);
  SensorStats st;
  st.min.assign(n, std::numeric_limits<double>::infinity());
  st.max.assign(n, -std::numeric_limits<double>::infinity());
  std::uint32_t last_us = rig.session().sensor_device_time_us();
  rig.run_for(duration_s, [&] {
    each();
    const std::uint32_t t_us = rig.session().sensor_device_time_us();
    if (t_us == last_us) {
      return;
    }
    last_us = t_us;
    const auto s = rig.session().sensors();
    for (std::size_t i = 0; i < n && i < s.size(); ++i) {
      sum[i] += s[i];
      sum2[i] += s[i] * s[i];
      st.min[i] = std::min(st.min[i], s[i]);
      st.max[i] = std::max(st.max[i], s[i]);
    }
    ++st.samples;
  });
  st.mean.assign(n, 0.0);
  st.std_dev.assign(n, 0.0);
  if (st.samples > 0) {
    const auto k = static_cast<double>(st.samples);
    for (std::size_t i = 0; i < n; ++i) {
      st.mean[i] = sum[i] / k;
      st.std_dev[i] = std::sqrt(std::max(0.0, sum2[i] / k - st.mean[i] * st.mean[i]));
    }
  }
  return st;
}

// Holds commanded currents alive (resent every 20 ms) while the rig ticks.
class CurrentHolder {
 public:
  explicit CurrentHolder(Rig& rig) : rig_(rig), current_a_(rig.info().valves, 0.0) {}
  void set(double current_a) {
    std::fill(current_a_.begin(), current_a_.end(), current_a);
    (void)rig_.session().send_valve_currents(current_a_);
  }
  void operator()() noexcept {
    if (++k_ % 20 == 0 && rig_.last() == ResultCode::ok) {
      (void)rig_.session().send_valve_currents(current_a_);
    }
  }

 private:
  Rig& rig_;
  std::vector<double> current_a_;
  int k_ = 0;
};

// Groups of fluid cells no two of which share a valve: pressed together, each valve's passages
// see at most one loaded cell, and the reservoir takes a few cells' fluid, not the whole skin's
// (pressing every cell at once raises the reservoir above any yield pressure).
inline std::vector<std::vector<std::size_t>> press_groups(const GridLayout& layout) {
  std::vector<std::vector<std::size_t>> groups;
  std::vector<std::vector<bool>> valve_used;
  for (std::size_t c = 0; c < layout.fluid_cell_count(); ++c) {
    std::size_t g = 0;
    for (; g < groups.size(); ++g) {
      const auto& valves = layout.valves_of_cell(c);
      if (std::none_of(valves.begin(), valves.end(), [&](std::size_t v) { return valve_used[g][v]; })) {
        break;
      }
    }
    if (g == groups.size()) {
      groups.emplace_back();
      valve_used.emplace_back(layout.valve_count(), false);
    }
    groups[g].push_back(c);
    for (const std::size_t v : layout.valves_of_cell(c)) {
      valve_used[g][v] = true;
    }
  }
  return groups;
}

// The cells a displacement sensor reads (one on a cell: that cell; one under a valve: the mean
// of the cells it joins); empty for other sensors.
inline std::vector<std::vector<std::size_t>> sensor_cells(const model::DeviceProfile& profile,
                                                          const GridLayout& layout) {
  std::vector<std::vector<std::size_t>> out(profile.sensors.size());
  for (std::size_t s = 0; s < profile.sensors.size(); ++s) {
    const auto& spec = profile.sensors[s];
    if (spec.quantity != model::SensorQuantity::displacement) {
      continue;
    }
    if (spec.place == model::PlaceKind::fluid_cell) {
      out[s] = {spec.index};
    } else if (spec.place == model::PlaceKind::valve) {
      out[s] = layout.cells_of_valve(spec.index);
    }
  }
  return out;
}

// The press-release experiment (needs the fixture and displacement sensors). For each press
// group: with the valves open (0 A) the fixture presses the group's cells to depth_m, so fluid
// leaves their pads; every coil is set to current_a and the fixture retreats to a light touch
// (touch_m) over retreat_s. The precharge and the membrane push fluid back through the valves,
// which pass it only above their yield pressure: a held pad stays below the retreating finger.
// The finger stays at the touch (an untouched pad no longer shows its depth to the sensors).
// Result per sensor: the residual depth below the touch, averaged over the cells the sensor
// reads, after settle_s (mean of 50 ms); and, when drift_s > 0, the same drift_s later.
struct PressRelease {
  double depth_m = 3e-3;
  double touch_m = 0.1e-3;
  double press_s = 0.1;
  double coil_rise_s = 0.02;
  double retreat_s = 0.08;
  double settle_s = 0.2;
  double drift_s = 0.0;
};
struct PressReleaseResult {
  std::vector<double> residual_m;
  std::vector<double> later_m;  // drift_s after residual_m (drift_s > 0)
};

inline PressReleaseResult press_release(Rig& rig, double current_a, const PressRelease& p) {
  sim::MockDevice* fixture = rig.fixture();
  const model::DeviceProfile& profile = *rig.session().profile();
  const GridLayout layout(profile.rows, profile.cols);
  const auto groups = press_groups(layout);
  const auto reads = sensor_cells(profile, layout);
  const std::size_t n = rig.info().sensors;
  PressReleaseResult out{std::vector<double>(n, 0.0), std::vector<double>(n, 0.0)};
  CurrentHolder hold(rig);
  for (const auto& group : groups) {
    std::vector<bool> pressed(layout.fluid_cell_count(), false);
    for (const std::size_t c : group) {
      pressed[c] = true;
    }
    std::vector<double> finger(layout.fluid_cell_count(), 0.0);
    const auto set_finger = [&](double depth_m) {
      for (const std::size_t c : group) {
        finger[c] = depth_m;
      }
      fixture->set_finger_indentation(finger);
    };
    hold.set(0.0);
    set_finger(p.depth_m);
    rig.run_for(p.press_s, hold);
    hold.set(current_a);
    rig.run_for(p.coil_rise_s, hold);
    const double start_s = rig.elapsed_s();
    rig.run_for(p.retreat_s, [&] {
      hold();
      const double f = std::min(1.0, (rig.elapsed_s() - start_s) / p.retreat_s);
      set_finger(p.depth_m + f * (p.touch_m - p.depth_m));
    });
    set_finger(p.touch_m);
    rig.run_for(std::max(0.0, p.settle_s - 0.05), hold);
    const SensorStats first = sample_sensors(rig, 0.05, hold);
    SensorStats later = first;
    if (p.drift_s > 0.0) {
      rig.run_for(std::max(0.0, p.drift_s - 0.05), hold);
      later = sample_sensors(rig, 0.05, hold);
    }
    // This group's share of each sensor: its pressed cells' residual depth over the cells read.
    for (std::size_t s = 0; s < n && s < reads.size(); ++s) {
      std::size_t loaded = 0;
      for (const std::size_t c : reads[s]) {
        loaded += pressed[c] ? 1U : 0U;
      }
      if (loaded == 0) {
        continue;
      }
      const double touch_share =
          p.touch_m * static_cast<double>(loaded) / static_cast<double>(reads[s].size());
      out.residual_m[s] += first.mean[s] - touch_share;
      out.later_m[s] += later.mean[s] - touch_share;
    }
    rig.lift_finger();
    hold.set(0.0);
    rig.run_for(0.05, hold);
  }
  return out;
}

}  // namespace mrskin::ctl
