// mrskinctl calibrate: sensor zero (tare), coil conditioning ("degauss"), a yield sweep at low
// currents fitted to the profile's model (the calibration's yield_scale), a held-out sweep that
// must not get worse, then the calibration stored versioned and read back. docs/cli.md.
#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "command.hpp"
#include "ctl_device_calibrate.hpp"
#include "ctl_device_rig.hpp"
#include "ctl_device_sampler.hpp"
#include "exit_codes.hpp"
#include "json_text.hpp"

namespace mrskin::ctl {
namespace {

struct CalibrateOptions {
  std::string uri = "mock://";
  LeaseOption lease;  // --bridge: the device of a running mrskin-bridged
  bool realtime = false;
  bool dry_run = false;
  double max_current_a = 0.0;  // 0: a fifth of the device's maximum
  int levels = 8;
  double rest_s = 0.3;
  bool zero_only = false;  // tare alone: no fixture, no sweep
};

// A fit whose median sensor misses the model by more than this many sweep resolutions is not a
// healthy unit: the model explains a perturbed unit to 0.8-3.2 resolutions (mock seeds 1-8),
// while a leaking valve leaves 5.7-12.6 (leak:0, 2, 5, 6, 8 on seeds 1, 3, 7, 8).
constexpr double kMisfitResolutions = 4.5;

// Sensors whose reading never changed over the rest while most others did (selftest's rule).
std::string still_sensors(const SensorStats& rest) {
  std::size_t moving = 0;
  for (const double sd : rest.std_dev) {
    moving += sd > 0.0 ? 1U : 0U;
  }
  std::string still;
  if (moving * 2 > rest.std_dev.size()) {
    for (std::size_t s = 0; s < rest.std_dev.size(); ++s) {
      if (!(rest.std_dev[s] > 0.0)) {
        still += fmt::format("{}{}", still.empty() ? "" : ", ", s);
      }
    }
  }
  return still;
}

std::string offset_unit(const std::string& sensor_unit) {
  return sensor_unit == "N" ? "n" : sensor_unit == "Pa" ? "pa" : "m";
}

constexpr int kTablePoints = 12;
constexpr double kDegaussTimeout_s = 5.0;  // the mock's takes ~1.1 s (57 half-cycles of 20 ms)
constexpr double kModelStep_s = 5e-4;
constexpr double kScaleMin = 0.5;  // the range parse_calibration accepts
constexpr double kScaleMax = 2.0;

std::string numbers(const std::vector<double>& v, double unit_scale = 1.0) {
  std::string out = "[";
  for (std::size_t i = 0; i < v.size(); ++i) {
    out += (i == 0 ? "" : ", ") + json_number(v[i] * unit_scale);
  }
  return out + "]";
}

// What was measured and fitted; printed as text or JSON.
struct Report {
  std::string result;  // WRITTEN, DRY_RUN, KEPT (the stored one fits better), REFUSED, FAILED
  std::string reason;
  long stored_version = 0;
  long new_version = 0;
  std::vector<double> offset_m;
  double noise_m = 0.0;             // largest sensor noise at rest
  std::vector<double> condition_a;  // on/off steps before the sweep
  RemanenceModel remanence;         // ...and the model's remanence after them
  std::string degauss = "not run";  // the unit's own degauss after the sweep: done, unsupported, unfinished
  RemanenceModel
      degauss_remanence;         // the model's remanence after the maximum, and after an alternating decay
  double zero_residual_m = 0.0;  // largest |residual| at 0 A after conditioning
  std::vector<double> fit_a;
  std::vector<double> held_out_a;
  double stored_scale = 1.0;
  double new_scale = 1.0;
  double rms_fit_stored_m = 0.0;
  double rms_fit_new_m = 0.0;
  double rms_held_stored_m = 0.0;
  double rms_held_new_m = 0.0;
  double sensitivity_m = 0.0;           // RMS rise when the scale moves 20 % off the fit
  double resolution_m = 0.0;            // what the sweep can resolve (noise of a residual)
  std::string sensor_unit = "m";        // the unit's sensors: "m", "N" or "Pa"
  double worst_sensor_misfit_m = 0.0;   // the fit's largest per-sensor rms miss
  double median_sensor_misfit_m = 0.0;  // ...and its median
  std::size_t worst_sensor = 0;         // the sensor of the worst misfit
  std::string text;
  std::string read_back;
  bool read_back_matches = false;
};

void print_report(const Report& r, const CalibrateOptions& o, const GlobalOptions& global) {
  if (global.json) {
    fmt::print(
        R"({{"uri": "{}", "dry_run": {}, "result": "{}", "reason": "{}", "stored_version": {}, "new_version": {}, )"
        R"("tare": {{"sensor_unit": "{}", "sensor_offset_m": {}, "noise_m": {}}}, )"
        R"("condition": {{"amplitudes_a": {}, "model_remanent_yield_after_max_pa": {}, "model_remanent_yield_after_steps_pa": {}, "residual_at_0_a_m": {}}}, )"
        R"("degauss": {{"outcome": "{}", "model_remanent_yield_before_pa": {}, "model_remanent_yield_after_pa": {}}}, )"
        R"("fit": {{"currents_a": {}, "held_out_currents_a": {}, "yield_scale_stored": {}, "yield_scale": {}, )"
        R"("rms_fit_stored_m": {}, "rms_fit_new_m": {}, "rms_held_out_stored_m": {}, "rms_held_out_new_m": {}, )"
        R"("sensitivity_m": {}, "resolution_m": {}, "worst_sensor_misfit_m": {}, "median_sensor_misfit_m": {}}}, )"
        R"("calibration": "{}", "read_back": "{}", "read_back_matches": {}}})"
        "\n",
        json_escape(o.uri), o.dry_run ? "true" : "false", r.result, json_escape(r.reason), r.stored_version,
        r.new_version, json_escape(r.sensor_unit), numbers(r.offset_m), json_number(r.noise_m),
        numbers(r.condition_a), json_number(r.remanence.after_max_pa),
        json_number(r.remanence.after_degauss_pa), json_number(r.zero_residual_m), r.degauss,
        json_number(r.degauss_remanence.after_max_pa), json_number(r.degauss_remanence.after_degauss_pa),
        numbers(r.fit_a), numbers(r.held_out_a), json_number(r.stored_scale), json_number(r.new_scale),
        json_number(r.rms_fit_stored_m), json_number(r.rms_fit_new_m), json_number(r.rms_held_stored_m),
        json_number(r.rms_held_new_m), json_number(r.sensitivity_m), json_number(r.resolution_m),
        json_number(r.worst_sensor_misfit_m), json_number(r.median_sensor_misfit_m), json_escape(r.text),
        json_escape(r.read_back), r.read_back_matches ? "true" : "false");
    return;
  }
  fmt::print("calibrate {}{}\n", o.uri, o.dry_run ? " (dry run: nothing is written)" : "");
  if (!r.offset_m.empty()) {
    // Displacement in micrometres; force and pressure sensors in their SI unit.
    const bool metres = r.sensor_unit == "m";
    const double scale = metres ? 1e6 : 1.0;
    const std::string unit = metres ? "um" : r.sensor_unit;
    std::string offsets;
    for (const double v : r.offset_m) {
      offsets += fmt::format(" {:.4g}", v * scale);
    }
    fmt::print("  zero (tare)  sensor offsets at rest, {}:{}; noise up to {:.4g} {}\n", unit, offsets,
               r.noise_m * scale, unit);
  }
  if (!r.condition_a.empty()) {
    fmt::print(
        "  condition    {} on/off steps {:.4g} .. {:.4g} A: every core on the branch down from the maximum, "
        "the history the sweep's model assumes (model remanence at 0 A {:.3g} Pa); measured residual at 0 A "
        "{:.2f} um\n",
        r.condition_a.size(), r.condition_a.front(), r.condition_a.back(), r.remanence.after_degauss_pa,
        r.zero_residual_m * 1e6);
  }
  if (r.degauss == "done") {
    fmt::print(
        "  degauss      done by the unit: a decaying alternating current through every coil; model "
        "remanence at 0 A {:.3g} Pa after the maximum -> {:.3g} Pa\n",
        r.degauss_remanence.after_max_pa, r.degauss_remanence.after_degauss_pa);
  } else if (r.degauss == "unsupported") {
    fmt::print(
        "  degauss      not supported by this unit (a unipolar coil driver cannot reverse the field): the "
        "cores keep up to {:.3g} Pa of remanent yield at 0 A on the model\n",
        r.degauss_remanence.after_max_pa);
  } else if (r.degauss == "unfinished") {
    fmt::print(
        "  degauss      started but not finished within {:.0f} s: check the unit (mrskinctl info --log)\n",
        kDegaussTimeout_s);
  }
  if (!r.fit_a.empty()) {
    fmt::print("  yield sweep  {} fit currents {:.4g} .. {:.4g} A, {} held out\n", r.fit_a.size(),
               r.fit_a.front(), r.fit_a.back(), r.held_out_a.size());
    fmt::print(
        "  fit          yield_scale {:.4f} (stored {:.4f}); rms residual fit {:.2f} um (stored {:.2f})\n",
        r.new_scale, r.stored_scale, r.rms_fit_new_m * 1e6, r.rms_fit_stored_m * 1e6);
    fmt::print(
        "  held out     rms residual {:.2f} um (stored {:.2f}); sensitivity {:.2f} um per 20 % (resolution "
        "{:.2f})\n",
        r.rms_held_new_m * 1e6, r.rms_held_stored_m * 1e6, r.sensitivity_m * 1e6, r.resolution_m * 1e6);
  }
  if (!r.text.empty()) {
    fmt::print("calibration version {}{}:\n", r.new_version, r.result == "WRITTEN" ? "" : " (not written)");
    fmt::print("{}", r.text);
  }
  if (r.result == "WRITTEN") {
    fmt::print("read back from the device ({}):\n{}", r.read_back_matches ? "matches" : "DIFFERS",
               r.read_back);
  }
  fmt::print("result: {}{}\n", r.result, r.reason.empty() ? "" : " (" + r.reason + ")");
}

// Per sensor: the rms of measured - predicted over the currents (0 for unused sensors).
std::vector<double> rms_per_sensor(const std::vector<std::vector<double>>& measured,
                                   const std::vector<std::vector<double>>& predicted,
                                   const std::vector<bool>& use) {
  std::vector<double> out(use.size(), 0.0);
  for (std::size_t s = 0; s < use.size(); ++s) {
    double sum = 0.0;
    for (std::size_t k = 0; k < measured.size() && use[s]; ++k) {
      sum += (measured[k][s] - predicted[k][s]) * (measured[k][s] - predicted[k][s]);
    }
    out[s] = measured.empty() ? 0.0 : std::sqrt(sum / static_cast<double>(measured.size()));
  }
  return out;
}

double rms(const std::vector<std::vector<double>>& measured,
           const std::vector<std::vector<double>>& predicted, const std::vector<bool>& use) {
  double sum = 0.0;
  std::size_t n = 0;
  for (std::size_t k = 0; k < measured.size(); ++k) {
    for (std::size_t s = 0; s < measured[k].size(); ++s) {
      if (use[s]) {
        sum += (measured[k][s] - predicted[k][s]) * (measured[k][s] - predicted[k][s]);
        ++n;
      }
    }
  }
  return n > 0 ? std::sqrt(sum / static_cast<double>(n)) : 0.0;
}

// Dry run: print and stop. Otherwise write `next` (already formatted in r.text), read it back
// and compare.
int write_and_read_back(Report& r, const model::Calibration& next, const CalibrateOptions& o,
                        const GlobalOptions& global, Rig& rig, Progress& progress, int& step) {
  if (o.dry_run) {
    r.result = "DRY_RUN";
    print_report(r, o, global);
    return tools::kOk;
  }
  try {
    rig.session().write_calibration(r.text);
  } catch (const Error& e) {
    r.result = "FAILED";
    r.reason = fmt::format("the device did not take the calibration: {}", e.what());
    print_report(r, o, global);
    return tools::kFailure;
  }
  progress.step(++step);
  r.read_back = rig.session().info().calibration;
  const model::Calibration back =
      model::parse_calibration(r.read_back, "read-back calibration", rig.info().valves);
  r.read_back_matches = r.read_back == r.text && back.version == next.version &&
                        std::abs(back.yield_scale - next.yield_scale) <= 1e-5 * next.yield_scale;
  r.result = r.read_back_matches ? "WRITTEN" : "FAILED";
  if (!r.read_back_matches) {
    r.reason = "the calibration read back differs from what was written";
  }
  print_report(r, o, global);
  return r.read_back_matches ? tools::kOk : tools::kFailure;
}

// The stored calibration as the next version, with yield_scale and the zero at rest (the bridge
// subtracts it from each reading); formatted into r.text.
model::Calibration next_calibration(const model::Calibration& stored, double yield_scale,
                                    const std::string& sensor_unit, Report& r) {
  model::Calibration next = stored;
  next.version = stored.version + 1;
  next.yield_scale = yield_scale;
  next.sensor_offset = r.offset_m;
  next.sensor_offset_unit = offset_unit(sensor_unit);
  r.new_version = next.version;
  r.new_scale = yield_scale;
  r.text = model::format_calibration(next);
  return next;
}

// Why the yield sweep cannot run on this unit ("" when it can).
std::string sweep_unavailable(Rig& rig, const DeviceInfo& info) {
  if (rig.fixture() == nullptr) {
    return "the yield sweep needs a press: only mock:// has a fixture the host can drive; "
           "--zero-only tares the sensors alone (docs/cli.md)";
  }
  if (info.sensor_unit != "m") {
    return "the yield sweep needs displacement sensors (it measures the residual depth); "
           "--zero-only tares the sensors alone";
  }
  return "";
}

// Zero: each sensor's mean at rest (valves open, nothing pressing) is its offset; the largest
// standard deviation is the noise.
SensorStats tare(Rig& rig, CurrentHolder& hold, double rest_s, Report& r) {
  hold.set(0.0);
  rig.run_for(0.1, hold);  // let the first readings settle after enabling
  SensorStats rest = sample_sensors(rig, rest_s, hold);
  r.offset_m = rest.mean;
  for (const double sd : rest.std_dev) {
    r.noise_m = std::max(r.noise_m, sd);
  }
  return rest;
}

// Conditioning: decaying on/off steps from the maximum current (30 ms each: the coil settles in
// ~5 ms) leave every core on the branch down from the maximum, which the sweep's model assumes.
void condition_cores(Rig& rig, CurrentHolder& hold, const model::DeviceProfile& profile,
                     const model::Calibration& stored, Report& r) {
  r.condition_a = degauss_amplitudes_a(rig.info().max_current_A);
  for (const double a : r.condition_a) {
    hold.set(a);
    rig.run_for(0.03, hold);
    hold.set(0.0);
    rig.run_for(0.03, hold);
  }
  r.remanence = model_remanence(model::apply_calibration(profile, stored), r.condition_a);
}

// The yield sweep's residual depths per sensor, each sensor's zero taken off.
struct Sweep {
  std::vector<std::size_t> shares;              // how many press groups load each sensor
  std::vector<bool> use;                        // the sensors some group loads: the fitted ones
  std::vector<std::vector<double>> fit_m;       // at each fitted current (r.fit_a)
  std::vector<std::vector<double>> held_out_m;  // at each held-out current (r.held_out_a)
};

// The sweep: level 0 (0 A), then k * max / levels; odd k fit, even k held out. Empty when the
// unit left ENABLED (or the run was interrupted) on the way.
std::optional<Sweep> sweep_yield(Rig& rig, const YieldSweepModel& sweep_model, const PressRelease& pr,
                                 double max_a, int levels, Report& r, Progress& progress, int& step) {
  const std::size_t sensors = rig.info().sensors;
  Sweep sweep;
  sweep.shares = sweep_model.groups_per_sensor();
  sweep.use.assign(sensors, false);
  for (std::size_t s = 0; s < sensors && s < sweep.shares.size(); ++s) {
    sweep.use[s] = sweep.shares[s] > 0;
  }
  for (int k = 0; k <= levels; ++k) {
    const double current_a = max_a * k / levels;
    PressReleaseResult m = press_release(rig, current_a, pr);
    if (rig.session().state() != DeviceState::enabled || Rig::interrupted()) {
      return std::nullopt;
    }
    for (std::size_t s = 0; s < m.residual_m.size(); ++s) {
      m.residual_m[s] -= r.offset_m[s] * static_cast<double>(s < sweep.shares.size() ? sweep.shares[s] : 0);
    }
    if (k == 0) {
      for (const double v : m.residual_m) {
        r.zero_residual_m = std::max(r.zero_residual_m, std::abs(v));
      }
    } else if (k % 2 == 1) {
      r.fit_a.push_back(current_a);
      sweep.fit_m.push_back(m.residual_m);
    } else {
      r.held_out_a.push_back(current_a);
      sweep.held_out_m.push_back(m.residual_m);
    }
    progress.step(++step);
  }
  return sweep;
}

// Degauss (protocol 1.1): the unit's own decaying alternating current, so the sweep's currents
// leave no remanence behind (the valves' floor at 0 A as low as the steel allows, and the state
// the bridge's observer starts from). A unipolar unit ignores it.
void degauss_cores(Rig& rig, const model::DeviceProfile& profile, const model::Calibration& stored,
                   Report& r) {
  switch (rig.degauss(kDegaussTimeout_s)) {
    case Rig::DegaussOutcome::done:
      r.degauss = "done";
      break;
    case Rig::DegaussOutcome::unsupported:
      r.degauss = "unsupported";
      break;
    case Rig::DegaussOutcome::unfinished:
      r.degauss = "unfinished";
      break;
  }
  r.degauss_remanence = model_remanence(model::apply_calibration(profile, stored),
                                        degauss_amplitudes_a(rig.info().max_current_A, 0.85, 1e-3), true);
}

// The model: residual against valve yield, over every yield the scale range can give. A
// calibration with yield_scale s at current I predicts table.at(s * the unit yield at I).
struct SweepPrediction {
  std::vector<double> fit_unit_pa;       // the valves' yield at each fitted current, yield_scale 1
  std::vector<double> held_out_unit_pa;  // ...and at each held-out one
  ResidualTable table;

  [[nodiscard]] std::vector<std::vector<double>> at(const std::vector<double>& unit_pa, double scale) const {
    std::vector<std::vector<double>> out;
    out.reserve(unit_pa.size());
    for (const double u : unit_pa) {
      out.push_back(table.at(scale * u));
    }
    return out;
  }
};

SweepPrediction predict_sweep(YieldSweepModel& sweep_model, const Report& r, Progress& progress, int& step) {
  std::vector<double> unit_fit;
  std::vector<double> unit_held;
  for (const double a : r.fit_a) {
    unit_fit.push_back(sweep_model.unit_yield_pa(a));
  }
  for (const double a : r.held_out_a) {
    unit_held.push_back(sweep_model.unit_yield_pa(a));
  }
  const double u_lo = kScaleMin * std::max(1e-3, std::min(unit_fit.front(), unit_held.front()));
  const double u_hi = kScaleMax * std::max(unit_fit.back(), unit_held.back()) * 1.01;
  ResidualTable table(sweep_model, u_lo, std::max(u_hi, 2.0 * u_lo), kTablePoints,
                      [&] { progress.step(++step); });
  return {std::move(unit_fit), std::move(unit_held), std::move(table)};
}

// The yield_scale with the least fit_rms(scale): a coarse scan in log scale, then golden section
// around the best point.
template <class FitRms>
double best_scale(const FitRms& fit_rms, double stored_scale) {
  constexpr int kScan = 61;
  double best = stored_scale;
  double best_rms = std::numeric_limits<double>::infinity();
  const double step_log = std::log(kScaleMax / kScaleMin) / (kScan - 1);
  for (int i = 0; i < kScan; ++i) {
    const double s = kScaleMin * std::exp(step_log * i);
    const double e = fit_rms(s);
    if (e < best_rms) {
      best_rms = e;
      best = s;
    }
  }
  double lo = std::log(std::max(kScaleMin, best * std::exp(-step_log)));
  double hi = std::log(std::min(kScaleMax, best * std::exp(step_log)));
  constexpr double kGolden = 0.6180339887498949;
  for (int i = 0; i < 40; ++i) {
    const double a = hi - kGolden * (hi - lo);
    const double b = lo + kGolden * (hi - lo);
    if (fit_rms(std::exp(a)) < fit_rms(std::exp(b))) {
      hi = b;
    } else {
      lo = a;
    }
  }
  if (fit_rms(std::exp(0.5 * (lo + hi))) < best_rms) {
    best = std::exp(0.5 * (lo + hi));
  }
  return best;
}

// Each fitted sensor's rms miss of the fit: the median and the worst (and which sensor that is).
void sensor_misfits(const std::vector<double>& per_sensor, const std::vector<bool>& use, Report& r) {
  std::vector<double> used;
  std::size_t worst = 0;
  for (std::size_t s = 0; s < per_sensor.size(); ++s) {
    if (use[s]) {
      used.push_back(per_sensor[s]);
      worst = per_sensor[s] > per_sensor[worst] || !use[worst] ? s : worst;
    }
  }
  std::nth_element(used.begin(), used.begin() + static_cast<std::ptrdiff_t>(used.size() / 2), used.end());
  r.median_sensor_misfit_m = used.empty() ? 0.0 : used[used.size() / 2];
  r.worst_sensor_misfit_m = per_sensor.empty() ? 0.0 : per_sensor[worst];
  r.worst_sensor = worst;
}

// Fits yield_scale to the sweep: into r the new scale, the rms residuals of the new and the stored
// one (fitted and held out), how sharply the fit tells the scale, what the sweep resolves, and the
// per-sensor misfits.
void fit_yield_scale(YieldSweepModel& sweep_model, const Sweep& sweep, const model::Calibration& stored,
                     const DeviceInfo& info, Report& r, Progress& progress, int& step) {
  const SweepPrediction predicted = predict_sweep(sweep_model, r, progress, step);
  const auto fit_rms = [&](double scale) {
    return rms(sweep.fit_m, predicted.at(predicted.fit_unit_pa, scale), sweep.use);
  };
  const auto held_out_rms = [&](double scale) {
    return rms(sweep.held_out_m, predicted.at(predicted.held_out_unit_pa, scale), sweep.use);
  };
  const double best = best_scale(fit_rms, stored.yield_scale);
  r.new_scale = best;
  r.rms_fit_new_m = fit_rms(best);
  r.rms_fit_stored_m = fit_rms(stored.yield_scale);
  r.rms_held_new_m = held_out_rms(best);
  r.rms_held_stored_m = held_out_rms(stored.yield_scale);
  r.sensitivity_m = std::min(fit_rms(std::clamp(best * 1.2, kScaleMin, kScaleMax)),
                             fit_rms(std::clamp(best / 1.2, kScaleMin, kScaleMax))) -
                    r.rms_fit_new_m;
  // A residual is the sum of 50 ms means (50 samples) over the groups that load the sensor.
  const double groups = static_cast<double>(*std::max_element(sweep.shares.begin(), sweep.shares.end()));
  r.resolution_m = 3.0 * std::max(r.noise_m, info.sensor_lsb) * std::sqrt(groups / 50.0);
  sensor_misfits(rms_per_sensor(sweep.fit_m, predicted.at(predicted.fit_unit_pa, best), sweep.use), sweep.use,
                 r);
}

// Why the new calibration is not written, into r.result and r.reason: REFUSED for a sweep the
// model does not explain (a fault) or one that cannot tell the scale, KEPT for a fit worse than
// the stored calibration's. False when it may be written.
bool withheld(Report& r) {
  if (r.median_sensor_misfit_m > kMisfitResolutions * r.resolution_m) {
    r.result = "REFUSED";
    r.reason = fmt::format(
        "the model does not explain the sweep: the median sensor misses it by {:.1f} um rms ({:.1f} "
        "resolutions; the worst, sensor {}, by {:.1f} um): a leaking valve or a faulty sensor? (run "
        "mrskinctl selftest); nothing written",
        r.median_sensor_misfit_m * 1e6, r.median_sensor_misfit_m / r.resolution_m, r.worst_sensor,
        r.worst_sensor_misfit_m * 1e6);
    return true;
  }
  if (r.sensitivity_m < r.resolution_m) {
    r.result = "REFUSED";
    r.reason = fmt::format(
        "ill-conditioned: moving yield_scale 20 % changes the fit by {:.2f} um, below the {:.2f} um the "
        "sweep "
        "resolves; sweep higher currents (--max-current-a) or check the sensors",
        r.sensitivity_m * 1e6, r.resolution_m * 1e6);
    return true;
  }
  if (r.rms_held_new_m > r.rms_held_stored_m) {
    // Not a failure: the unit is calibrated, and better than this sweep would make it.
    r.result = "KEPT";
    r.reason = fmt::format(
        "the stored calibration fits the held-out sweep better than the new yield_scale ({:.2f} um "
        "against {:.2f} um rms): kept it, nothing written",
        r.rms_held_stored_m * 1e6, r.rms_held_new_m * 1e6);
    return true;
  }
  return false;
}

int run_calibrate(const CalibrateOptions& o, const GlobalOptions& global) {
  Report r;
  Rig rig(o.uri, o.realtime, o.lease.lease_socket());
  const DeviceInfo& info = rig.info();
  const model::DeviceProfile* profile = rig.session().profile();
  const auto refuse = [&](std::string result, std::string reason) {
    r.result = std::move(result);
    r.reason = std::move(reason);
    rig.release();
    print_report(r, o, global);
    return tools::kFailure;
  };
  if (profile == nullptr) {
    return refuse("FAILED", "the device holds no readable profile: nothing to fit against");
  }
  model::Calibration stored;
  try {
    stored = model::parse_calibration(info.calibration, "stored calibration", info.valves);
  } catch (const InvalidArgument& e) {
    return refuse("FAILED", fmt::format("{}; write a calibration by hand or ask the vendor", e.what()));
  }
  r.stored_version = stored.version;
  r.sensor_unit = info.sensor_unit;
  r.stored_scale = stored.yield_scale;
  const double max_a = o.max_current_a > 0.0 ? o.max_current_a : 0.2 * info.max_current_A;
  if (max_a > info.max_current_A + 1e-12) {
    throw InvalidArgument(
        fmt::format("--max-current-a {} A is above the device's maximum {} A", max_a, info.max_current_A));
  }
  if (const std::string why = o.zero_only ? "" : sweep_unavailable(rig, info); !why.empty()) {
    return refuse("FAILED", why);
  }
  const int levels = o.levels;
  const int total = o.zero_only ? 2 : 2 + (levels + 1) + 1 + kTablePoints + 1;
  Progress progress(!global.json, "calibrate", total);
  int step = 0;
  try {
    rig.enable();
  } catch (const Error& e) {
    return refuse("FAILED", e.what());
  }

  CurrentHolder hold(rig);
  const SensorStats rest = tare(rig, hold, o.rest_s, r);
  progress.step(++step);
  if (const std::string still = still_sensors(rest); !still.empty()) {
    return refuse("REFUSED",
                  fmt::format("sensor(s) {} read the same value throughout the rest while the others "
                              "moved: stuck? (run mrskinctl selftest); nothing written",
                              still));
  }
  if (o.zero_only) {
    rig.release();  // the unit takes a calibration only while not ENABLED
    const model::Calibration next = next_calibration(stored, stored.yield_scale, info.sensor_unit, r);
    return write_and_read_back(r, next, o, global, rig, progress, step);
  }
  condition_cores(rig, hold, *profile, stored, r);
  progress.step(++step);

  PressRelease pr;
  YieldSweepModel sweep_model(*profile, stored, pr, kModelStep_s);
  const std::optional<Sweep> sweep = sweep_yield(rig, sweep_model, pr, max_a, levels, r, progress, step);
  if (!sweep) {
    return refuse("FAILED",
                  fmt::format("the unit left ENABLED during the sweep: state {}, fault {}",
                              to_string(rig.session().state()), fault_name(rig.session().fault_code())));
  }
  rig.release();  // the unit takes a calibration only while not ENABLED
  degauss_cores(rig, *profile, stored, r);
  progress.step(++step);

  fit_yield_scale(sweep_model, *sweep, stored, info, r, progress, step);
  const model::Calibration next = next_calibration(stored, r.new_scale, info.sensor_unit, r);
  if (withheld(r)) {
    print_report(r, o, global);
    return r.result == "KEPT" ? tools::kOk : tools::kFailure;
  }
  return write_and_read_back(r, next, o, global, rig, progress, step);
}

}  // namespace

void add_calibrate_command(CliCommand app, const GlobalOptions& global, int& exit_code) {
  auto options = std::make_shared<CalibrateOptions>();
  CliCommand sub = app.subcommand(
      "calibrate",
      "zero the sensors, degauss the cores, sweep the valves' yield at low currents and fit the "
      "calibration's "
      "yield_scale to the profile's model; store it versioned and read it back (docs/cli.md). Exit 0 written "
      "(or --dry-run), or the stored calibration kept as the better fit; 1 refused or failed (nothing "
      "written)");
  add_device_options(sub, options->uri, options->realtime);
  sub.flag("--dry-run", options->dry_run, "measure and fit, print the calibration, write nothing");
  sub.flag("--zero-only", options->zero_only,
           "tare the sensors at rest and store only that (no degauss, no sweep, no fixture needed)");
  sub.option("--max-current-a", options->max_current_a,
             "highest sweep current, A (default: a fifth of the device's maximum)")
      .range(1e-4, 10.0);
  sub.option("--levels", options->levels, "sweep currents above 0 A (odd ones fitted, even ones held out)")
      .range(4, 40)
      .show_default();
  sub.option("--rest", options->rest_s, "seconds of rest sampled for the zero")
      .range(0.05, 10.0)
      .show_default();
  add_lease_option(sub, options->lease);
  sub.callback([options, &global, &exit_code] {
    if (const std::optional<std::string> socket = options->lease.lease_socket()) {
      options->uri = "bridge:" + *socket;  // what the report names; the Rig leases the socket
    }
    exit_code = run_calibrate(*options, global);
  });
}

}  // namespace mrskin::ctl
