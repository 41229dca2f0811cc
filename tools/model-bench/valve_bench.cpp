// Valve suite: every valve path timed per call and its error measured over the stated range
// (Q 1e-9..1e-4 m^3/s, tau_y 0..50 kPa), in one run. Writes
//   <out>/valve_methods.csv   one row per method: time per call (median, p10, p90 over
//                             repetitions), max/mean relative pressure error, error extremes
//   <out>/valve_errors.csv    the error grid (Q, tau_y, fast and Wereley-Pang relative errors)
//   <out>/valve_time_vs_error.svg
// and prints a summary. Timing is wall clock on a shared machine: the methods are interleaved
// in every repetition so that they share the machine's noise, and medians are quoted.
// --check: exit 1 unless fast is within 0.5 % and at least 10x faster than exact.
#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <fstream>
#include <iostream>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include "bench_common.hpp"
#include "mrskin/driver/model/device_model.hpp"
#include "suites.hpp"

namespace mrskin::bench {

namespace {

using namespace mrskin::model;
using Clock = std::chrono::steady_clock;

constexpr double kQMin = 1e-9;
constexpr double kQMax = 1e-4;
constexpr double kTauMax = 50e3;

struct MethodStats {
  std::string name;
  std::vector<double> ns;  // per repetition, ns per call
  double max_rel = 0.0;
  double mean_rel = 0.0;
  double min_signed = 0.0;
  double max_signed = 0.0;
  double worst_q = 0.0;
  double worst_tau = 0.0;
};

// ns per call of fn over the inputs, one pass.
template <class Fn>
double time_pass(const std::vector<double>& q, const std::vector<double>& tau, Fn fn) {
  double acc = 0.0;
  const auto t0 = Clock::now();
  for (std::size_t i = 0; i < q.size(); ++i) {
    acc += fn(q[i], tau[i]);
  }
  const auto t1 = Clock::now();
  keep(acc);
  return std::chrono::duration<double, std::nano>(t1 - t0).count() / static_cast<double>(q.size());
}

struct Point {
  std::string label;
  double x_ns;
  double y_err;
  std::string colour;
};

void write_svg(const std::string& path, const std::vector<Point>& pts, double exact_ns,
               const std::string& subtitle) {
  LogLogPlot plot;
  plot.title = "Valve law: run time per call against max relative pressure error";
  plot.subtitle = subtitle;
  plot.x_label = "time per call (median over repetitions, log)";
  plot.y_label = "max relative pressure error vs exact (log)";
  plot.x_lo = 0;
  plot.x_hi = 3;
  plot.y_lo = -17;
  plot.y_hi = -1;
  plot.y_tick_every = 2;
  plot.x_tick = [](double v) { return general(v, 6) + " ns"; };
  plot.y_tick = [](double v) { return "1e" + std::to_string(static_cast<int>(std::lround(std::log10(v)))); };
  plot.legend = false;
  plot.refs.push_back({false, 5e-3, "0.5 % limit", "#c00"});
  plot.refs.push_back({true, exact_ns / 10.0, "10x faster than exact", "#06c"});
  for (const Point& p : pts) {
    plot.series.push_back({p.label, p.colour, {{p.x_ns, p.y_err, p.label}}, false, ""});
  }
  (void)plot.write(path);
}

using Uniform = std::uniform_real_distribution<double>;

// Each law's relative pressure error against the exact one over the stated range: a 401 x 401
// grid (every 4th point of every 4th row written to grid, which is then closed) plus 200,000
// random points. Returns the number of points.
std::size_t measure_errors(const ValveLaw& v, std::ofstream& grid, std::mt19937_64& rng, Uniform& u01,
                           std::vector<MethodStats>& stats) {
  std::size_t n = 0;
  auto measure = [&](double q, double tau, bool write) {
    const double e = v.pressure_exact_Pa(q, tau).value;
    const double back = v.pressure_exact_Pa(v.flow_m3_per_s(e, tau).value, tau).value;  // p -> Q -> p
    const std::array<double, 3> errs = {back / e - 1.0, v.pressure_wereley_pang_Pa(q, tau).value / e - 1.0,
                                        v.pressure_fast_Pa(q, tau).value / e - 1.0};
    for (std::size_t m = 0; m < 3; ++m) {
      MethodStats& s = stats[m];
      const double a = std::fabs(errs[m]);
      if (a > s.max_rel) {
        s.max_rel = a;
        s.worst_q = q;
        s.worst_tau = tau;
      }
      s.mean_rel += a;
      s.min_signed = std::min(s.min_signed, errs[m]);
      s.max_signed = std::max(s.max_signed, errs[m]);
    }
    ++n;
    if (write) {
      grid << sci(q, 6) << ',' << sci(tau, 6) << ',' << sci(e, 9) << ',' << sci(errs[2], 3) << ','
           << sci(errs[1], 3) << ',' << sci(errs[0], 3) << '\n';
    }
  };
  constexpr int kGrid = 401;
  for (int i = 0; i < kGrid; ++i) {
    const double q = kQMin * std::pow(kQMax / kQMin, static_cast<double>(i) / (kGrid - 1));
    for (int j = 0; j < kGrid; ++j) {
      measure(q, kTauMax * j / (kGrid - 1), i % 4 == 0 && j % 4 == 0);
    }
  }
  grid.close();
  for (int k = 0; k < 200000; ++k) {
    // One draw a statement, in the order g++ took them: g++ and clang order a call's arguments apart.
    const double stress_share = u01(rng);
    const double flow_share = u01(rng);
    measure(kQMin * std::pow(kQMax / kQMin, flow_share), kTauMax * stress_share, false);
  }
  for (MethodStats& s : stats) {
    s.mean_rel /= static_cast<double>(n);
  }
  return n;
}

// The model's two calls timed beside the laws, ns per call, one entry per repetition.
struct ModelTimes {
  std::vector<double> cell_ns;  // cell_force_uniform at the design cell
  std::vector<double> env_ns;   // envelope there
  std::size_t law_calls = 0;    // valve-law calls per repetition
  std::size_t model_calls = 0;  // model calls per repetition
};

// Times each law (into stats[m].ns) on the same 4096 random inputs, interleaved, and the model's
// two calls on 256 random presses of the design cell: three warm-up passes, then reps
// repetitions. The bar is made after the warm-up and left to the caller: it ends its line when
// the suite ends.
ModelTimes time_calls(const ValveLaw& v, const DeviceModel& model, const DeviceProfile& profile, int reps,
                      std::mt19937_64& rng, Uniform& u01, std::vector<MethodStats>& stats,
                      std::optional<Progress>& bar) {
  std::vector<double> qs(4096);
  std::vector<double> taus(4096);
  for (std::size_t i = 0; i < qs.size(); ++i) {
    qs[i] = kQMin * std::pow(kQMax / kQMin, u01(rng));
    taus[i] = kTauMax * u01(rng);
  }
  const std::size_t centre = model.fluid_cell_index(profile.design.row, profile.design.col).value;
  std::vector<double> ds(256);
  std::vector<double> vs(256);
  for (std::size_t i = 0; i < ds.size(); ++i) {
    ds[i] = profile.design.indentation_m * (0.2 + 0.8 * u01(rng));
    vs[i] = 10e-3 * u01(rng);
  }
  ModelTimes t{{}, {}, qs.size(), ds.size()};
  auto exact = [&](double q, double tau) { return v.pressure_exact_Pa(q, tau).value; };
  auto wp = [&](double q, double tau) { return v.pressure_wereley_pang_Pa(q, tau).value; };
  auto fast = [&](double q, double tau) { return v.pressure_fast_Pa(q, tau).value; };
  const double imax = profile.coil.max_current_A;
  auto cell = [&](double d, double vel) {
    return model.cell_force_uniform(centre, d, vel, 0.6 * imax).value.force_N;
  };
  auto env = [&](double d, double vel) { return model.envelope(centre, d, vel).value.force_max_N; };
  for (int warm = 0; warm < 3; ++warm) {
    time_pass(qs, taus, exact);
    time_pass(qs, taus, wp);
    time_pass(qs, taus, fast);
  }
  bar.emplace("valve laws", static_cast<std::size_t>(reps));
  for (int r = 0; r < reps; ++r) {
    bar->tick();
    // Rotate the order so that no method always runs first after the others.
    for (int k = 0; k < 3; ++k) {
      switch ((r + k) % 3) {
        case 0:
          stats[0].ns.push_back(time_pass(qs, taus, exact));
          break;
        case 1:
          stats[1].ns.push_back(time_pass(qs, taus, wp));
          break;
        default:
          stats[2].ns.push_back(time_pass(qs, taus, fast));
          break;
      }
    }
    t.cell_ns.push_back(time_pass(ds, vs, cell));
    t.env_ns.push_back(time_pass(ds, vs, env));
  }
  return t;
}

// valve_methods.csv and the summary table: each law's time per call and error, then the model's
// two calls. Returns each law's point for the plot.
std::vector<Point> report_methods(const BenchOptions& o, const std::vector<MethodStats>& stats,
                                  const ModelTimes& t, std::size_t points, double exact_med,
                                  const DeviceProfile& profile) {
  std::ofstream csv(o.out + "/valve_methods.csv");
  csv << "method,ns_per_call_median,ns_per_call_p10,ns_per_call_p90,speedup_vs_exact,max_rel_error,"
         "mean_rel_error,min_signed_error,max_signed_error,worst_q_m3_s,worst_tau_y_pa,error_points,"
         "repetitions,calls_per_repetition\n";
  std::cout << "valve law over Q " << sci(kQMin, 0) << ".." << sci(kQMax, 0) << " m^3/s, tau_y 0.."
            << fixed(kTauMax / 1e3, 0) << " kPa (" << points << " points; " << o.reps << " repetitions x "
            << t.law_calls << " calls)\n";
  std::cout << pad("method", 14, true) << pad("median_ns", 11) << pad("p10_ns", 11) << pad("p90_ns", 11)
            << pad("speedup", 10) << pad("max_rel_err", 13) << pad("mean_rel_err", 13) << "   signed range\n";
  std::vector<Point> pts;
  const std::array<std::string, 3> colours = {"#333", "#e69f00", "#009e73"};
  for (std::size_t m = 0; m < stats.size(); ++m) {
    const MethodStats& s = stats[m];
    const double med = percentile(s.ns, 0.5);
    csv << s.name << ',' << fixed(med, 4) << ',' << fixed(percentile(s.ns, 0.1), 4) << ','
        << fixed(percentile(s.ns, 0.9), 4) << ',' << fixed(exact_med / med, 3) << ',' << sci(s.max_rel, 6)
        << ',' << sci(s.mean_rel, 6) << ',' << sci(s.min_signed, 6) << ',' << sci(s.max_signed, 6) << ','
        << sci(s.worst_q, 6) << ',' << sci(s.worst_tau, 6) << ',' << points << ',' << o.reps << ','
        << t.law_calls << '\n';
    std::cout << pad(s.name, 14, true) << pad(fixed(med, 2), 11) << pad(fixed(percentile(s.ns, 0.1), 2), 11)
              << pad(fixed(percentile(s.ns, 0.9), 2), 11) << pad(fixed(exact_med / med, 1) + "x", 10)
              << pad(sci(s.max_rel, 3), 13) << pad(sci(s.mean_rel, 3), 13) << "   ["
              << signed_sci(s.min_signed, 3) << ", " << signed_sci(s.max_signed, 3) << "]\n";
    const std::string label =
        m == 0 ? "exact (p-Q-p round trip " + sci(s.max_rel, 1) + ")"
               : s.name + " (" + general(s.max_rel * 100, 2) + " %, " + fixed(exact_med / med, 1) + "x)";
    pts.push_back({label, med, std::max(s.max_rel, 1e-17), colours[m]});
  }
  csv << "cell_force_uniform," << fixed(percentile(t.cell_ns, 0.5), 4) << ','
      << fixed(percentile(t.cell_ns, 0.1), 4) << ',' << fixed(percentile(t.cell_ns, 0.9), 4) << ",,,,,,,,"
      << o.reps << ',' << t.model_calls << '\n';
  csv << "envelope," << fixed(percentile(t.env_ns, 0.5), 4) << ',' << fixed(percentile(t.env_ns, 0.1), 4)
      << ',' << fixed(percentile(t.env_ns, 0.9), 4) << ",,,,,,,," << o.reps << ',' << t.model_calls << '\n';
  csv.close();
  std::cout << pad("cell_force", 14, true) << pad(fixed(percentile(t.cell_ns, 0.5), 0), 11)
            << pad(fixed(percentile(t.cell_ns, 0.1), 0), 11) << pad(fixed(percentile(t.cell_ns, 0.9), 0), 11)
            << "   (cell " << profile.design.row << "," << profile.design.col << " of " << profile.name
            << ", exact network solve)\n";
  std::cout << pad("envelope", 14, true) << pad(fixed(percentile(t.env_ns, 0.5), 0), 11)
            << pad(fixed(percentile(t.env_ns, 0.1), 0), 11) << pad(fixed(percentile(t.env_ns, 0.9), 0), 11)
            << "   (two cell forces)\n";
  return pts;
}

}  // namespace

int run_valve_suite(const BenchOptions& o) {
  const DeviceProfile profile = o.profile.empty() ? default_profile() : load_profile(o.profile);
  // The stated range is for the paper's valve (0.5 mm gap); the profile supplies the fluid.
  const ValveLaw v(slot_geometry(0.5e-3, 30e-3, 24.01e-3), profile.fluid.viscosity_Pa_s,
                   profile.fluid.density_kg_per_m3);
  const DeviceModel model(profile);

  // ---- error over the stated range: a 401 x 401 grid plus 200,000 random points ----
  std::vector<MethodStats> stats(3);
  stats[0].name = "exact";
  stats[1].name = "wereley-pang";
  stats[2].name = "fast";
  std::ofstream grid(o.out + "/valve_errors.csv");
  if (!grid) {
    std::cerr << "cannot write to " << o.out << ": create the directory first, or pass another --out DIR\n";
    return 1;
  }
  grid << "q_m3_s,tau_y_pa,dp_exact_pa,rel_err_fast,rel_err_wereley_pang,round_trip_rel_err_exact\n";
  // One random stream: the error points first, then the timed inputs.
  std::mt19937_64 rng(20240601);
  Uniform u01(0.0, 1.0);
  const std::size_t n = measure_errors(v, grid, rng, u01, stats);

  // ---- time per call: the same 4096 random inputs for every method, interleaved ----
  std::optional<Progress> bar;
  const ModelTimes times = time_calls(v, model, profile, o.reps, rng, u01, stats, bar);

  const double exact_med = percentile(stats[0].ns, 0.5);
  const std::vector<Point> pts = report_methods(o, stats, times, n, exact_med, profile);
  write_svg(o.out + "/valve_time_vs_error.svg", pts, exact_med,
            "Q " + sci(kQMin, 0) + ".." + sci(kQMax, 0) + " m^3/s, tau_y 0..50 kPa; " + std::to_string(n) +
                " error points; " + std::to_string(o.reps) + " x 4096 timed calls per method");
  const double fast_err = stats[2].max_rel;
  const double ratio = exact_med / percentile(stats[2].ns, 0.5);
  const bool ok = fast_err <= 5e-3 && ratio >= 10.0;
  std::cout << "fast path: max error " << sci(fast_err, 3) << " (limit 5e-3), " << fixed(ratio, 1)
            << "x faster than exact (limit 10x): " << (ok ? "meets the figure" : "MISSES the figure") << "\n";
  std::cout << "wrote " << o.out << "/valve_methods.csv, " << o.out << "/valve_errors.csv, " << o.out
            << "/valve_time_vs_error.svg\n";
  return o.check && !ok ? 1 : 0;
}

}  // namespace mrskin::bench
