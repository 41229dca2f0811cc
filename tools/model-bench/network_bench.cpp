// Network suite: the NetworkSimulation steppers, timed and measured in one run. Writes
//   <out>/network_steppers.csv   every stepper and step size over a standard press-hold-release
//                                of the 5x5 against implicit_exact at 1 us: RMS and max contact
//                                force error (N), wall time per simulated second (median, p10,
//                                p90 over repetitions), Newton iterations, energy gap, status
//   <out>/network_stepper_error_vs_time.svg
//   <out>/network_scaling.csv    time per step (median, p90, p99 over the steps) of the implicit
//                                steppers on 5x5, 16x16 and 64x64 with 1, 5, 25, 100 % of the
//                                fluid cells pressed
//   <out>/network_scaling.svg
// Wall clock on a shared machine: medians are quoted; nothing here is a pass/fail gate.
#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <fstream>
#include <iostream>
#include <string>
#include <vector>

#include "bench_common.hpp"
#include "mrskin/driver/model/network.hpp"
#include "suites.hpp"

namespace mrskin::bench {

namespace {

using namespace mrskin::model;
using Clock = std::chrono::steady_clock;

// A stepper with its options: the four steppers, and implicit_exact with backward_euler.
struct Variant {
  const char* name;
  Stepper stepper;
  bool backward_euler;
  const char* colour;
  [[nodiscard]] NetworkOptions options() const {
    NetworkOptions o;
    o.stepper = stepper;
    o.backward_euler = backward_euler;
    return o;
  }
};
constexpr std::array<Variant, 5> kVariants = {{
    {"implicit_exact", Stepper::implicit_exact, false, "#333"},
    {"implicit_exact+backward_euler", Stepper::implicit_exact, true, "#cc79a7"},
    {"implicit_regularised", Stepper::implicit_regularised, false, "#0072b2"},
    {"linearly_implicit_regularised", Stepper::linearly_implicit_regularised, false, "#009e73"},
    {"explicit_euler", Stepper::explicit_euler, false, "#d55e00"},
}};

double yield_at_max_Pa(const DeviceModel& m) {
  return m.yield_stress_at_current_Pa(m.profile().coil.max_current_A).value;
}

// The standard scenario: a fingertip (sphere of radius 20 mm) over the design cell pressed to
// the design depth in 0.2 s, held 0.3 s, released in 0.2 s, then 0.1 s of rest; every valve at
// 60 % of its highest yield stress while pressing and holding, 20 % after. The contact force is
// sampled every 4 ms (a multiple of every step size used).
struct Scenario {
  // (time s, indentation as a fraction of the design depth), joined by straight lines.
  static constexpr std::array<std::array<double, 2>, 5> kKnots = {
      {{0.0, 0.0}, {0.2, 1.0}, {0.5, 1.0}, {0.7, 0.0}, {0.8, 0.0}}};
  double depth_m = 5e-3;
  double sample_s = 4e-3;
  [[nodiscard]] static double duration_s() { return kKnots.back()[0]; }
  [[nodiscard]] double indentation_m(double t) const {
    for (std::size_t k = 1; k < kKnots.size(); ++k) {
      if (t <= kKnots[k][0]) {
        const double u = (t - kKnots[k - 1][0]) / (kKnots[k][0] - kKnots[k - 1][0]);
        return depth_m * (kKnots[k - 1][1] + u * (kKnots[k][1] - kKnots[k - 1][1]));
      }
    }
    return depth_m * kKnots.back()[1];
  }
  [[nodiscard]] static double yield_fraction(double t) { return t <= kKnots[2][0] ? 0.6 : 0.2; }
};

struct Run {
  Status status = Status::ok;
  long failed_step = -1;
  long steps = 0;
  std::vector<double> force_N;  // at every sample
  double wall_s = 0.0;
  double iterations = 0.0;  // mean per step
  double energy_gap = 0.0;  // |work - stored change - dissipated| / max of the three
  [[nodiscard]] bool status_ok() const { return status == Status::ok; }
};

Run run_scenario(const DeviceModel& m, const NetworkOptions& o, double dt, const Scenario& sc) {
  NetworkSimulation sim(m, o);
  Run r;
  const long steps = std::lround(Scenario::duration_s() / dt);
  const long every = std::max(1L, std::lround(sc.sample_s / dt));
  r.force_N.reserve(static_cast<std::size_t>(steps / every + 1));
  std::vector<double> yield(sim.valve_count(), 0.0);
  Contact c;
  c.x_m = m.profile().design.col * m.profile().cell_pitch_m;
  c.y_m = m.profile().design.row * m.profile().cell_pitch_m;
  c.radius_m = 0.02;
  double fraction = -1.0;
  long iterations = 0;
  const auto t0 = Clock::now();
  for (long k = 0; k < steps; ++k) {
    const double t = static_cast<double>(k + 1) * dt;
    if (Scenario::yield_fraction(t) != fraction) {
      fraction = Scenario::yield_fraction(t);
      std::fill(yield.begin(), yield.end(), fraction * yield_at_max_Pa(m));
      (void)sim.set_valve_yield_stress_Pa(yield);
    }
    c.indentation_m = sc.indentation_m(t);
    (void)sim.set_contacts(std::span<const Contact>(&c, 1));
    const Result<StepReport> rep = sim.step(dt);
    if (!rep.ok()) {
      r.status = rep.status;
      r.failed_step = k;
      break;
    }
    iterations += rep.value.iterations;
    r.steps = k + 1;
    if ((k + 1) % every == 0) {
      r.force_N.push_back(sim.contact_force_N()[0]);
    }
  }
  r.wall_s = std::chrono::duration<double>(Clock::now() - t0).count();
  r.iterations = static_cast<double>(iterations) / static_cast<double>(std::max(1L, r.steps));
  const NetworkEnergy e = sim.energy();
  const double stored = e.stored_J - e.stored_initial_J;
  const double scale = std::max({std::fabs(e.work_J), std::fabs(stored), std::fabs(e.dissipated_J), 1e-300});
  r.energy_gap = std::fabs(e.work_J - stored - e.dissipated_J) / scale;
  return r;
}

struct ForceError {
  double rms_N = HUGE_VAL;
  double max_N = HUGE_VAL;
};
ForceError force_error(const std::vector<double>& f, const std::vector<double>& ref) {
  if (f.size() != ref.size()) {
    return {};
  }
  ForceError e{0.0, 0.0};
  for (std::size_t i = 0; i < f.size(); ++i) {
    const double d = f[i] - ref[i];
    e.rms_N += d * d;
    e.max_N = std::max(e.max_N, std::fabs(d));
  }
  e.rms_N = std::sqrt(e.rms_N / static_cast<double>(f.size()));
  if (!std::isfinite(e.rms_N)) {
    return {};
  }
  return e;
}

std::vector<double> step_sizes(Stepper s) {
  if (s == Stepper::explicit_euler) {
    return {1e-6, 2e-6, 5e-6, 1e-5, 2e-5, 5e-5, 1e-4, 2e-4, 5e-4, 1e-3, 2e-3, 4e-3};
  }
  return {1e-5, 2e-5, 5e-5, 1e-4, 2e-4, 5e-4, 1e-3, 2e-3, 4e-3};
}

int stepper_suite(const BenchOptions& o) {
  const DeviceModel m(load_profile("mr-skin-5x5"));
  const Scenario sc;
  constexpr double kRefDt = 1e-6;
  std::size_t runs = 2;
  for (const Variant& v : kVariants) {
    runs += step_sizes(v.stepper).size();
  }
  Progress bar("network steppers", runs);
  const Run ref = run_scenario(m, kVariants[0].options(), kRefDt, sc);
  bar.tick("reference");
  const Run ref2 = run_scenario(m, kVariants[0].options(), 2 * kRefDt, sc);
  bar.tick("reference check");
  if (!ref.status_ok()) {
    std::cerr << "the reference run failed: " << to_string(ref.status) << "\n";
    return 1;
  }
  const ForceError ref_err = force_error(ref2.force_N, ref.force_N);
  const double peak_N = *std::max_element(ref.force_N.begin(), ref.force_N.end());

  std::ofstream csv(o.out + "/network_steppers.csv");
  if (!csv) {
    std::cerr << "cannot write to " << o.out << ": create the directory first, or pass another --out DIR\n";
    return 1;
  }
  csv << "stepper,dt_s,status,failed_at_step,steps,rms_force_error_N,max_force_error_N,"
         "wall_s_per_sim_s_median,wall_s_per_sim_s_p10,wall_s_per_sim_s_p90,repetitions,"
         "newton_iterations_per_step,energy_gap_rel\n";
  std::cout << "steppers: 5x5 " << Scenario::duration_s()
            << " s press-hold-release; reference implicit_exact dt " << sci(kRefDt, 0) << " (" << ref.steps
            << " steps; dt " << sci(2 * kRefDt, 0) << " differs by RMS " << sci(ref_err.rms_N, 2)
            << " N); peak force " << fixed(peak_N, 3) << " N\n";
  std::cout << pad("stepper", 31, true) << pad("dt_s", 8) << pad("rms_err_N", 11) << pad("max_err_N", 11)
            << pad("s_per_sim_s", 13) << pad("iter", 7) << pad("energy_gap", 12) << "  status\n";
  LogLogPlot plot;
  plot.title = "Network steppers: RMS contact force error against run time";
  plot.subtitle = "5x5, 0.8 s press-hold-release to 5 mm; reference implicit_exact at dt 1 us; labels: dt";
  plot.x_label = "wall time per simulated second (median, log)";
  plot.y_label = "RMS contact force error vs reference, N (log)";
  plot.x_lo = -3;
  plot.x_hi = 1;
  plot.y_lo = -9;
  plot.y_hi = 1;
  plot.y_tick = [](double v) { return "1e" + std::to_string(static_cast<int>(std::lround(std::log10(v)))); };
  plot.x_tick = [](double v) { return general(v, 3) + " s"; };
  plot.refs.push_back({false, 0.04, "0.04 N (2 % of 2 N)", "#c00"});
  plot.refs.push_back({true, 1.0, "real time", "#06c"});
  for (const Variant& v : kVariants) {
    PlotSeries series{v.name, v.colour, {}, true, ""};
    for (const double dt : step_sizes(v.stepper)) {
      // Repeat for a median; long runs fewer times (the whole suite stays at a few seconds).
      const double est_s = Scenario::duration_s() / dt * 3e-6;
      const int reps = est_s > 0.3 ? 3 : (est_s > 0.03 ? 5 : 9);
      std::vector<double> per_sim_s;
      Run first;
      for (int r = 0; r < reps; ++r) {
        Run run = run_scenario(m, v.options(), dt, sc);
        per_sim_s.push_back(run.wall_s / Scenario::duration_s());
        if (r == 0) {
          first = std::move(run);
        }
        if (!first.status_ok()) {
          break;  // a failing run is not timed further
        }
      }
      bar.tick(std::string(v.name) + " dt " + sci(dt, 0));
      const ForceError err = first.status_ok() ? force_error(first.force_N, ref.force_N) : ForceError{};
      // A run that ends "ok" but creates energy (gap above 10 %) or errs by more than the peak
      // force has gone unstable without producing a NaN.
      const bool unstable = !std::isfinite(err.rms_N) || first.energy_gap > 0.1 || err.max_N > peak_N;
      const std::string status = first.status_ok() ? (unstable ? "unstable" : "ok")
                                                   : std::string("failed: ") + to_string(first.status);
      const double med = percentile(per_sim_s, 0.5);
      csv << v.name << ',' << sci(dt, 1) << ',' << status << ',' << first.failed_step << ',' << first.steps
          << ',' << sci(err.rms_N, 4) << ',' << sci(err.max_N, 4) << ',' << sci(med, 4) << ','
          << sci(percentile(per_sim_s, 0.1), 4) << ',' << sci(percentile(per_sim_s, 0.9), 4) << ','
          << per_sim_s.size() << ',' << fixed(first.iterations, 3) << ',' << sci(first.energy_gap, 3) << '\n';
      std::cout << pad(v.name, 31, true) << pad(sci(dt, 0), 8) << pad(sci(err.rms_N, 2), 11)
                << pad(sci(err.max_N, 2), 11) << pad(sci(med, 2), 13) << pad(fixed(first.iterations, 2), 7)
                << pad(sci(first.energy_gap, 1), 12) << "  " << status
                << (first.failed_step >= 0 ? " at step " + std::to_string(first.failed_step) : "") << "\n";
      if (first.status_ok() && !unstable) {
        series.points.push_back({med, std::max(err.rms_N, 1e-12), sci(dt, 0)});
      }
    }
    plot.series.push_back(std::move(series));
  }
  (void)plot.write(o.out + "/network_stepper_error_vs_time.svg");
  return 0;
}

int scaling_suite(const BenchOptions& o) {
  struct Grid {
    const char* profile;
    int steps;
  };
  constexpr std::array<Grid, 3> kGrids = {
      {{"mr-skin-5x5", 2000}, {"fingertip-16x16", 400}, {"palm-64x64", 100}}};
  constexpr std::array<double, 4> kFractions = {0.01, 0.05, 0.25, 1.0};
  constexpr double kPress_s = 0.05;  // the pressed cells reach the design depth in 50 ms, then hold
  constexpr std::array<std::size_t, 4> kImplicit = {0, 1, 2, 3};  // into kVariants
  std::ofstream csv(o.out + "/network_scaling.csv");
  if (!csv) {
    std::cerr << "cannot write to " << o.out << "\n";
    return 1;
  }
  csv << "profile,nodes,links,factor_nonzeros,stepper,contact_fraction,cells_pressed,steps,dt_s,"
         "us_per_step_median,us_per_step_p90,us_per_step_p99,us_per_step_max,newton_iterations_per_step,"
         "failed_steps\n";
  std::cout
      << "scaling: dt 1e-3 s (smaller where a stepper refuses it); the pressed cells (those nearest the "
         "design cell) reach the design depth in 50 ms and hold\n";
  std::cout << pad("profile", 17, true) << pad("nodes", 6) << pad("stepper", 31) << pad("pressed", 9)
            << pad("dt_s", 7) << pad("median_us", 11) << pad("p90_us", 10) << pad("p99_us", 10)
            << pad("iter", 7) << "\n";
  Progress bar("network scaling", kGrids.size() * kFractions.size() * kImplicit.size());
  LogLogPlot plot;
  plot.title = "Network step: time per step against network size";
  plot.subtitle =
      "5x5 (26 nodes), 16x16 (257), 64x64 (4097); dt 1 ms (linearised: see CSV); median over the steps";
  plot.x_label = "nodes (fluid cells + chambers + reservoir, log)";
  plot.y_label = "time per step, us (median, log)";
  plot.x_lo = 1;
  plot.x_hi = 4;
  plot.y_lo = 0;
  plot.y_hi = 5;
  plot.legend_width = 320;
  // Colour: the fraction pressed; dashes: the stepper.
  constexpr std::array<const char*, 4> kFractionColours = {"#0072b2", "#009e73", "#e69f00", "#d55e00"};
  constexpr std::array<const char*, 4> kDashes = {"", "1,3", "2,3", "8,4"};
  std::vector<PlotSeries> series;
  for (std::size_t si = 0; si < kImplicit.size(); ++si) {
    for (std::size_t fi = 0; fi < kFractions.size(); ++fi) {
      series.push_back(
          {std::string(kVariants[kImplicit[si]].name) + " " + fixed(100 * kFractions[fi], 0) + " %",
           kFractionColours[fi],
           {},
           true,
           kDashes[si]});
    }
  }
  for (const Grid& g : kGrids) {
    const DeviceModel m(load_profile(g.profile));
    const double depth = m.profile().design.indentation_m;
    const double tau = 0.5 * yield_at_max_Pa(m);
    for (std::size_t fi = 0; fi < kFractions.size(); ++fi) {
      const std::vector<std::size_t> pressed = pressed_cells(m, kFractions[fi]);
      for (std::size_t si = 0; si < kImplicit.size(); ++si) {
        const Variant& v = kVariants[kImplicit[si]];
        // 1 ms, or the largest of 0.1 ms, 10 us at which every step succeeds (the linearised
        // stepper refuses 1 ms steps on the small, stiff cells of 16x16 and 64x64).
        double dt = 1e-3;
        std::vector<double> us;
        long iterations = 0;
        int failed = 0;
        NetworkSimulation sim(m, v.options());
        for (; dt >= 1e-5; dt /= 10.0) {
          sim.reset();
          const std::vector<double> yield(sim.valve_count(), tau);
          (void)sim.set_valve_yield_stress_Pa(yield);
          std::vector<double> d(sim.fluid_cell_count(), 0.0);
          us.assign(0, 0.0);
          us.reserve(static_cast<std::size_t>(g.steps));
          iterations = 0;
          failed = 0;
          for (int k = 0; k < g.steps; ++k) {
            const double x = depth * std::min(1.0, (k + 1) * dt / kPress_s);
            for (const std::size_t c : pressed) {
              d[c] = x;
            }
            (void)sim.set_cell_indentation_m(d);
            const auto t0 = Clock::now();
            const Result<StepReport> r = sim.step(dt);
            us.push_back(std::chrono::duration<double, std::micro>(Clock::now() - t0).count());
            failed += r.ok() ? 0 : 1;
            iterations += r.value.iterations;
          }
          if (failed == 0) {
            break;
          }
        }
        dt = std::max(dt, 1e-5);
        bar.tick(std::string(g.profile) + " " + v.name);
        const double med = percentile(us, 0.5);
        const double it = static_cast<double>(iterations) / g.steps;
        csv << g.profile << ',' << sim.node_count() << ',' << sim.link_count() << ',' << sim.factor_nonzeros()
            << ',' << v.name << ',' << kFractions[fi] << ',' << pressed.size() << ',' << g.steps << ','
            << sci(dt, 0) << ',' << fixed(med, 2) << ',' << fixed(percentile(us, 0.9), 2) << ','
            << fixed(percentile(us, 0.99), 2) << ',' << fixed(*std::max_element(us.begin(), us.end()), 2)
            << ',' << fixed(it, 3) << ',' << failed << '\n';
        std::cout << pad(g.profile, 17, true) << pad(std::to_string(sim.node_count()), 6) << pad(v.name, 31)
                  << pad(std::to_string(pressed.size()), 9) << pad(sci(dt, 0), 7) << pad(fixed(med, 1), 11)
                  << pad(fixed(percentile(us, 0.9), 1), 10) << pad(fixed(percentile(us, 0.99), 1), 10)
                  << pad(fixed(it, 2), 7) << (failed > 0 ? "  FAILED STEPS: " + std::to_string(failed) : "")
                  << "\n";
        series[si * kFractions.size() + fi].points.push_back(
            {static_cast<double>(sim.node_count()), med, ""});
      }
    }
  }
  plot.series = std::move(series);
  (void)plot.write(o.out + "/network_scaling.svg");
  return 0;
}

}  // namespace

int run_network_suite(const BenchOptions& o) {
  const int a = stepper_suite(o);
  const int b = scaling_suite(o);
  std::cout << "wrote " << o.out << "/network_steppers.csv, network_stepper_error_vs_time.svg, "
            << "network_scaling.csv, network_scaling.svg\n";
  return a != 0 ? a : b;
}

}  // namespace mrskin::bench
