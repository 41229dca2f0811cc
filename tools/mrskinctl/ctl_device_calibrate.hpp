// The model side of `mrskinctl calibrate`: what the profile (with a calibration applied) predicts
// for the press-release experiment of ctl_device_sampler.hpp, and the coil conditioning
// ("degauss") the sweep starts from. docs/cli.md, "calibrate", says what is fitted and why.
#pragma once

#include <algorithm>
#include <cmath>
#include <span>
#include <vector>

#include "ctl_device_sampler.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/model/calibration.hpp"
#include "mrskin/driver/model/device_model.hpp"
#include "mrskin/driver/model/magnetic.hpp"
#include "mrskin/driver/model/network.hpp"

namespace mrskin::ctl {

// Decaying steps: amplitude max * ratio^k, k = 0.. while above floor_fraction of the maximum
// (on/off steps through the host's unipolar commands; the device's own degauss alternates them).
inline std::vector<double> degauss_amplitudes_a(double max_current_a, double ratio = 0.6,
                                                double floor_fraction = 0.01) {
  std::vector<double> out;
  for (double a = max_current_a; a >= floor_fraction * max_current_a; a *= ratio) {
    out.push_back(a);
  }
  return out;
}

// The steel's remanence on the play-operator model (magnetic.hpp) of a profile: the yield
// stress left at 0 A after the maximum current, and after the sequence that follows it, each
// step back to 0 A (on/off), or with alternating signs (a bipolar driver's degauss).
struct RemanenceModel {
  double after_max_pa = 0.0;
  double after_degauss_pa = 0.0;
};
inline RemanenceModel model_remanence(const model::DeviceProfile& p, std::span<const double> amplitudes_a,
                                      bool alternating = false) {
  model::HysteresisState h;
  const auto yield_at = [&](double current_a) {
    const auto f = model::gap_field_hysteretic(p.magnetic, p.fluid, current_a, h);
    return f.ok() ? f.value.yield_stress_Pa : 0.0;
  };
  RemanenceModel out;
  (void)yield_at(p.coil.max_current_A);
  out.after_max_pa = yield_at(0.0);
  double sign = 1.0;
  for (const double a : amplitudes_a) {
    (void)yield_at(sign * a);
    if (alternating) {
      sign = -sign;
    } else {
      (void)yield_at(0.0);
    }
  }
  out.after_degauss_pa = yield_at(0.0);
  return out;
}

// Runs the press-release experiment on the network simulation of nominal + base calibration
// (every scale but the yield's; the valves' gains). The valves' yield stress is one number u
// times each valve's gain, so one table over u serves every candidate yield_scale: a
// calibration with scale s at current I predicts residual(s * unit_yield_pa(I)).
// Left out of the model (as in the controller's): the 1.5 ms bus delay, sensor noise and
// quantisation; the coil is a first-order lag (driver + eddy time constants).
class YieldSweepModel {
 public:
  YieldSweepModel(const model::DeviceProfile& nominal, const model::Calibration& base, const PressRelease& p,
                  double dt_s)
      : unit_profile_(unit_profile(nominal, base)),
        model_(unit_profile_),
        net_(model_, model::NetworkOptions{}),
        layout_(unit_profile_.rows, unit_profile_.cols),
        groups_(press_groups(layout_)),
        reads_(sensor_cells(unit_profile_, layout_)),
        p_(p),
        dt_s_(dt_s),
        base_(base),
        lag_s_(unit_profile_.coil.eddy_time_constant_s +
               1.0 / (2.0 * 3.141592653589793 * unit_profile_.coil.driver_bandwidth_Hz)),
        remanent_pa_(unit_yield_pa(0.0) * base.yield_scale) {}

  // Yield stress at current_a with yield_scale 1 on the conditioned branch: the core has seen
  // the maximum current (the degauss starts there) and 0 A before every press.
  [[nodiscard]] double unit_yield_pa(double current_a) const {
    model::HysteresisState h;
    const auto at = [&](double i) {
      const auto f = model::gap_field_hysteretic(unit_profile_.magnetic, unit_profile_.fluid, i, h);
      return f.ok() ? f.value.yield_stress_Pa : 0.0;
    };
    (void)at(unit_profile_.coil.max_current_A);
    (void)at(0.0);
    return at(current_a);
  }
  [[nodiscard]] std::size_t sensors() const noexcept { return reads_.size(); }
  // How many press groups load sensor s (the experiment sums one share per group).
  [[nodiscard]] std::vector<std::size_t> groups_per_sensor() const {
    std::vector<std::size_t> out(reads_.size(), 0);
    for (const auto& g : groups_) {
      for (std::size_t s = 0; s < reads_.size(); ++s) {
        const bool loaded =
            std::any_of(reads_[s].begin(), reads_[s].end(), [&](std::size_t c) { return contains(g, c); });
        out[s] += loaded ? 1U : 0U;
      }
    }
    return out;
  }

  // Residual depth per sensor, m, with every valve at yield u_pa times its gain.
  std::vector<double> residual_m(double u_pa) {
    const std::size_t cells = layout_.fluid_cell_count();
    const std::size_t valves = layout_.valve_count();
    std::vector<double> out(reads_.size(), 0.0);
    std::vector<double> finger(cells, 0.0);
    std::vector<double> yield(valves, 0.0);
    std::vector<double> reading(reads_.size(), 0.0);
    std::vector<double> sum(reads_.size(), 0.0);
    double level = remanent_pa_;  // lagged yield, as a multiple of each valve's gain
    net_.reset();
    const auto run = [&](double duration_s, double target_pa, auto&& each) {
      const int steps = std::max(1, static_cast<int>(std::lround(duration_s / dt_s_)));
      for (int k = 0; k < steps; ++k) {
        level += (target_pa - level) * std::min(1.0, dt_s_ / lag_s_);
        for (std::size_t v = 0; v < valves; ++v) {
          yield[v] = level * base_.valve_gain(v);
        }
        (void)net_.set_valve_yield_stress_Pa(yield);
        each(static_cast<double>(k + 1) * dt_s_);
        (void)net_.step(dt_s_);
      }
    };
    const auto none = [](double) {};
    for (const auto& group : groups_) {
      const auto set_finger = [&](double depth_m) {
        for (const std::size_t c : group) {
          finger[c] = depth_m;
        }
        (void)net_.set_cell_indentation_m(finger);
      };
      set_finger(p_.depth_m);
      run(p_.press_s, remanent_pa_, none);
      run(p_.coil_rise_s, u_pa, none);
      run(p_.retreat_s, u_pa, [&](double t_s) {
        set_finger(p_.depth_m + std::min(1.0, t_s / p_.retreat_s) * (p_.touch_m - p_.depth_m));
      });
      set_finger(p_.touch_m);
      run(std::max(0.0, p_.settle_s - 0.05), u_pa, none);
      std::fill(sum.begin(), sum.end(), 0.0);
      int samples = 0;
      run(0.05, u_pa, [&](double) {
        net_.read_sensors(reading);
        for (std::size_t s = 0; s < sum.size(); ++s) {
          sum[s] += reading[s];
        }
        ++samples;
      });
      for (std::size_t s = 0; s < reads_.size(); ++s) {
        std::size_t loaded = 0;
        for (const std::size_t c : reads_[s]) {
          loaded += contains(group, c) ? 1U : 0U;
        }
        if (loaded > 0) {
          out[s] += sum[s] / samples -
                    p_.touch_m * static_cast<double>(loaded) / static_cast<double>(reads_[s].size());
        }
      }
      std::fill(finger.begin(), finger.end(), 0.0);
      (void)net_.set_cell_indentation_m(finger);
      run(0.05, remanent_pa_, none);
    }
    return out;
  }

 private:
  static model::DeviceProfile unit_profile(const model::DeviceProfile& nominal, model::Calibration c) {
    c.yield_scale = 1.0;
    return model::apply_calibration(nominal, c);
  }
  static bool contains(const std::vector<std::size_t>& v, std::size_t x) {
    return std::find(v.begin(), v.end(), x) != v.end();
  }

  model::DeviceProfile unit_profile_;
  model::DeviceModel model_;
  model::NetworkSimulation net_;
  GridLayout layout_;
  std::vector<std::vector<std::size_t>> groups_;
  std::vector<std::vector<std::size_t>> reads_;
  PressRelease p_;
  double dt_s_;
  model::Calibration base_;
  double lag_s_;  // coil: driver + eddy time constants
  double remanent_pa_;
};

// residual(u) per sensor, tabulated on log-spaced u and interpolated linearly in log u.
class ResidualTable {
 public:
  template <class Step>
  ResidualTable(YieldSweepModel& m, double u_lo_pa, double u_hi_pa, int points, Step&& step) {
    for (int k = 0; k < points; ++k) {
      const double u = u_lo_pa * std::pow(u_hi_pa / u_lo_pa, static_cast<double>(k) / (points - 1));
      log_u_.push_back(std::log(u));
      rows_.push_back(m.residual_m(u));
      step();
    }
  }
  [[nodiscard]] std::vector<double> at(double u_pa) const {
    const double x = std::log(std::max(u_pa, 1e-12));
    std::size_t k = 1;
    while (k + 1 < log_u_.size() && log_u_[k] < x) {
      ++k;
    }
    const double w = std::clamp((x - log_u_[k - 1]) / (log_u_[k] - log_u_[k - 1]), 0.0, 1.0);
    std::vector<double> out(rows_[k].size());
    for (std::size_t s = 0; s < out.size(); ++s) {
      out[s] = rows_[k - 1][s] + w * (rows_[k][s] - rows_[k - 1][s]);
    }
    return out;
  }

 private:
  std::vector<double> log_u_;
  std::vector<std::vector<double>> rows_;
};

}  // namespace mrskin::ctl
