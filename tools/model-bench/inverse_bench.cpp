// Inverse suite (see inverse_bench.hpp): the fast allocation against the slow exact solve.
#include "inverse_bench.hpp"

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <fstream>
#include <iostream>
#include <limits>
#include <memory>
#include <random>
#include <span>
#include <string>
#include <vector>

#include "mrskin/driver/model/exact_inverse.hpp"
#include "mrskin/driver/model/inverse.hpp"

namespace mrskin::bench {

namespace {

using namespace mrskin::model;
using Clock = std::chrono::steady_clock;

constexpr int kCasesPerKind = 20;
constexpr int kFastRepetitions = 101;
constexpr unsigned kSeed = 20240601;
// Errors are plotted on a log axis: below this they are drawn at it.
constexpr double kPlotFloor_N = 1e-12;

enum class Kind : unsigned char { single, feasible, conflicting };
const char* name_of(Kind k) {
  switch (k) {
    case Kind::single:
      return "single_cell";
    case Kind::feasible:
      return "jointly_feasible";
    case Kind::conflicting:
      return "conflicting";
  }
  return "?";
}

struct Case {
  Kind kind = Kind::single;
  std::vector<CellImpedanceTarget> targets;
  std::vector<CellState> states;
};

// Error of a solution's exact rendered forces against its clamped targets, over loaded cells.
struct ExactForceError {
  double max_N = 0.0;
  double rms_N = 0.0;
  std::size_t cells = 0;
};

ExactForceError exact_error(const DeviceModel& m, const Case& c, std::span<const double> currents,
                            std::span<const double> target_N) {
  std::vector<double> f(m.layout().fluid_cell_count());
  ExactForceError e;
  if (exact_rendered_forces_N(m, c.targets, c.states, 0.0, currents, f) != Status::ok) {
    e.max_N = e.rms_N = std::numeric_limits<double>::quiet_NaN();
    return e;
  }
  double sum2 = 0.0;
  for (std::size_t i = 0; i < f.size(); ++i) {
    if (c.states[i].indentation_m > 0.0) {
      const double d = std::fabs(f[i] - target_N[i]);
      e.max_N = std::max(e.max_N, d);
      sum2 += d * d;
      ++e.cells;
    }
  }
  e.rms_N = e.cells > 0 ? std::sqrt(sum2 / static_cast<double>(e.cells)) : 0.0;
  return e;
}

CellImpedanceTarget law_for_force(double force_N, double indentation_m) {
  CellImpedanceTarget t;
  t.stiffness_N_per_m = force_N / indentation_m;
  t.force_ceiling_N = 100.0;
  t.valid_until_s = 1e9;
  return t;
}

// Cells joined to `cell` by a shared valve.
std::vector<std::size_t> neighbours(const DeviceModel& m, std::size_t cell) {
  std::vector<std::size_t> out;
  for (const std::size_t v : m.layout().valves_of_cell(cell)) {
    for (const std::size_t other : m.layout().cells_of_valve(v)) {
      if (other != cell && std::find(out.begin(), out.end(), other) == out.end()) {
        out.push_back(other);
      }
    }
  }
  return out;
}

std::vector<Case> make_cases(const DeviceModel& m) {
  const std::size_t n = m.layout().fluid_cell_count();
  const double imax = m.profile().coil.max_current_A;
  std::mt19937_64 rng(kSeed);
  auto u = [&](double lo, double hi) { return std::uniform_real_distribution<double>(lo, hi)(rng); };
  auto blank = [&](Kind k) {
    return Case{k, std::vector<CellImpedanceTarget>(n), std::vector<CellState>(n)};
  };
  auto state = [&](int k) { return CellState{u(0.5e-3, 5e-3), k % 4 == 0 ? 0.0 : u(2e-4, 0.01)}; };
  auto in_envelope = [&](Case& c, std::size_t cell, int k) {
    c.states[cell] = state(k);
    const CellEnvelope e = m.envelope(cell, c.states[cell].indentation_m, c.states[cell].rate_m_per_s).value;
    c.targets[cell] = law_for_force(u(e.force_min_N, e.force_max_N), c.states[cell].indentation_m);
  };
  std::vector<Case> cases;
  for (int k = 0; k < kCasesPerKind; ++k) {
    Case c = blank(Kind::single);
    in_envelope(c, rng() % n, k);
    cases.push_back(std::move(c));
  }
  for (int k = 0; k < kCasesPerKind; ++k) {
    Case c = blank(Kind::feasible);
    std::vector<double> truth(m.layout().valve_count());
    for (double& x : truth) {
      x = u(0.0, imax);
    }
    const std::size_t first = rng() % n;
    const std::vector<std::size_t> near = neighbours(m, first);
    c.states[first] = state(k);
    for (std::size_t j = 0; j < static_cast<std::size_t>(k % 3) && j < near.size(); ++j) {
      c.states[near[rng() % near.size()]] = state(k);
    }
    std::vector<double> f(n);
    (void)exact_rendered_forces_N(m, c.targets, c.states, 0.0, truth, f);
    for (std::size_t i = 0; i < n; ++i) {
      if (c.states[i].indentation_m > 0.0) {
        c.targets[i] = law_for_force(f[i], c.states[i].indentation_m);
      }
    }
    cases.push_back(std::move(c));
  }
  for (int k = 0; k < kCasesPerKind; ++k) {
    Case c = blank(Kind::conflicting);
    const std::size_t first = rng() % n;
    const std::vector<std::size_t> near = neighbours(m, first);
    in_envelope(c, first, k);
    for (std::size_t j = 0; j < 1 + static_cast<std::size_t>(k % 2) && j < near.size(); ++j) {
      in_envelope(c, near[rng() % near.size()], k);
    }
    cases.push_back(std::move(c));
  }
  return cases;
}

struct Outcome {
  double fast_ns = 0.0;  // median cold solve
  double slow_s = 0.0;
  ExactForceError fast;
  ExactForceError slow;
  double fast_residual_N = 0.0;  // the fast model's own estimate
  long slow_evaluations = 0;
  bool ok = true;
};

Outcome run_case(const DeviceModel& m, CellInverse& inv, const Case& c) {
  Outcome o;
  std::vector<double> ns;
  ns.reserve(kFastRepetitions);
  for (int r = 0; r < kFastRepetitions; ++r) {
    inv.invalidate();
    const auto t0 = Clock::now();
    const Status s = inv.solve(c.targets, c.states, 0.0);
    const auto t1 = Clock::now();
    o.ok = o.ok && s == Status::ok;
    ns.push_back(std::chrono::duration<double, std::nano>(t1 - t0).count());
  }
  keep(inv.currents_A()[0]);
  o.fast_ns = percentile(ns, 0.5);
  o.fast_residual_N = inv.report().residual_norm_N;
  std::vector<double> targets(c.states.size());
  for (std::size_t i = 0; i < targets.size(); ++i) {
    targets[i] = inv.cells()[i].target_force_N;
  }
  o.fast = exact_error(m, c, inv.currents_A(), targets);
  // The slow solve starts from nothing (zero currents) and from its own uniform per-cell
  // currents, never from the fast answer: an independent reference.
  const std::vector<double> zero(m.layout().valve_count(), 0.0);
  const auto t0 = Clock::now();
  const ExactInverseResult slow = solve_inverse_exact(m, c.targets, c.states, 0.0, zero);
  o.slow_s = std::chrono::duration<double>(Clock::now() - t0).count();
  o.ok = o.ok && slow.status == Status::ok;
  o.slow = exact_error(m, c, slow.currents_A, slow.target_force_N);
  o.slow_evaluations = slow.evaluations;
  return o;
}

// One press tracked at 1 kHz: a finger between two neighbouring cells, 1 s in at 4.5 mm/s and
// 0.5 s held, every target changing every tick. Time per solve (median over the ticks) and the
// exact rendered force error every 10th tick.
struct Tracking {
  double median_ns = 0.0;
  double p99_ns = 0.0;
  ExactForceError error;
  int ticks = 0;
};

Tracking run_tracking(const DeviceModel& m) {
  CellInverse inv(m);
  const std::size_t n = m.layout().fluid_cell_count();
  const std::size_t a = m.fluid_cell_index(1, 1).value;
  const std::size_t b = m.fluid_cell_index(2, 2).value;
  Case c{Kind::single, std::vector<CellImpedanceTarget>(n), std::vector<CellState>(n)};
  for (const std::size_t cell : {a, b}) {
    c.targets[cell] = {900.0, 1.2, 5.0, 0.0, 0.0, 2.5, 1e9};  // ~1.2 N at 4 mm, some damping
  }
  Tracking tr;
  std::vector<double> ns;
  double max_N = 0.0;
  double sum2 = 0.0;
  std::size_t samples = 0;
  for (int k = 0; k < 1500; ++k) {
    const double time = 1e-3 * k;
    const double d = time < 1.0 ? 0.5e-3 + 4.5e-3 * time : 5e-3;
    const double v = time < 1.0 ? 4.5e-3 : 0.0;
    c.states[a] = {d, v};
    c.states[b] = {0.7 * d, 0.7 * v};
    const auto t0 = Clock::now();
    const Status s = inv.solve(c.targets, c.states, 0.0);
    ns.push_back(std::chrono::duration<double, std::nano>(Clock::now() - t0).count());
    if (s != Status::ok) {
      tr.error.max_N = std::numeric_limits<double>::quiet_NaN();
      return tr;
    }
    if (k % 10 == 0) {
      std::vector<double> targets(n);
      for (std::size_t i = 0; i < n; ++i) {
        targets[i] = inv.cells()[i].target_force_N;
      }
      const ExactForceError e = exact_error(m, c, inv.currents_A(), targets);
      max_N = std::max(max_N, e.max_N);
      sum2 += e.rms_N * e.rms_N * static_cast<double>(e.cells);
      samples += e.cells;
    }
  }
  tr.median_ns = percentile(ns, 0.5);
  tr.p99_ns = percentile(ns, 0.99);
  tr.error.max_N = max_N;
  tr.error.rms_N = samples > 0 ? std::sqrt(sum2 / static_cast<double>(samples)) : 0.0;
  tr.error.cells = samples;
  tr.ticks = static_cast<int>(ns.size());
  return tr;
}

// Solves every case fast and slow; one row each in csv (after its header), a tick each on bar.
std::vector<Outcome> run_cases(const DeviceModel& model, CellInverse& inv, const std::vector<Case>& cases,
                               std::ofstream& csv, Progress* bar) {
  csv << "case,kind,loaded_cells,fast_ns_median,slow_s,fast_max_err_N,fast_rms_err_N,slow_max_err_N,"
         "slow_rms_err_N,fast_model_residual_N,slow_exact_evaluations\n";
  std::vector<Outcome> out;
  for (std::size_t k = 0; k < cases.size(); ++k) {
    const Outcome o = run_case(model, inv, cases[k]);
    csv << k << ',' << name_of(cases[k].kind) << ',' << o.fast.cells << ',' << sci(o.fast_ns, 4) << ','
        << sci(o.slow_s, 4) << ',' << sci(o.fast.max_N, 4) << ',' << sci(o.fast.rms_N, 4) << ','
        << sci(o.slow.max_N, 4) << ',' << sci(o.slow.rms_N, 4) << ',' << sci(o.fast_residual_N, 4) << ','
        << o.slow_evaluations << '\n';
    out.push_back(o);
    if (bar != nullptr) {
      bar->tick(name_of(cases[k].kind));
    }
  }
  return out;
}

// The time-against-error plot's frame and reference lines; the series come from the results.
LogLogPlot time_error_plot() {
  LogLogPlot plot;
  plot.title = "Inverse: exact rendered force error against time per solve";
  plot.subtitle =
      "5x5; fast CellInverse (cold) vs slow exact pattern search; per case: max error over loaded cells";
  plot.x_label = "time per solve (median for the fast solve, log)";
  plot.y_label = "max |exact force - target|, N (log)";
  plot.x_lo = -7;
  plot.x_hi = 1;
  plot.y_lo = -12;
  plot.y_hi = 0;
  plot.y_tick_every = 2;
  plot.y_tick = [](double v) { return "1e" + std::to_string(static_cast<int>(std::lround(std::log10(v)))); };
  plot.x_tick = [](double v) { return general(v, 3) + " s"; };
  plot.refs.push_back({false, 0.04, "0.04 N (2 % of 2 N)", "#c00"});
  plot.refs.push_back({true, 1e-3, "1 kHz tick", "#06c"});
  return plot;
}

// Per method and kind: the time and error distributions as a row of methods, a line of the
// summary table and a series of the plot.
void report_methods(const std::vector<Case>& cases, const std::vector<Outcome>& out, std::ofstream& methods,
                    LogLogPlot& plot) {
  // Per kind: dark for the fast solve, light for the slow one.
  const std::array<std::array<const char*, 3>, 2> colours = {
      {{"#0072b2", "#009e73", "#d55e00"}, {"#9ccbe8", "#8fd6bf", "#f2b38a"}}};
  for (const bool fast : {true, false}) {
    for (const Kind kind : {Kind::single, Kind::feasible, Kind::conflicting}) {
      std::vector<double> times;
      std::vector<double> errs;
      PlotSeries series{std::string(fast ? "fast " : "slow ") + name_of(kind),
                        colours[fast ? 0 : 1][static_cast<std::size_t>(kind)],
                        {},
                        false,
                        ""};
      for (std::size_t k = 0; k < cases.size(); ++k) {
        if (cases[k].kind != kind) {
          continue;
        }
        const double t = fast ? out[k].fast_ns * 1e-9 : out[k].slow_s;
        const double e = fast ? out[k].fast.max_N : out[k].slow.max_N;
        times.push_back(t);
        errs.push_back(e);
        series.points.push_back({t, std::max(e, kPlotFloor_N), ""});
      }
      plot.series.push_back(std::move(series));
      const char* method = fast ? "fast" : "slow";
      methods << method << ',' << name_of(kind) << ',' << times.size() << ','
              << sci(percentile(times, 0.5), 4) << ',' << sci(percentile(errs, 0.5), 4) << ','
              << sci(percentile(errs, 0.95), 4) << ',' << sci(*std::max_element(errs.begin(), errs.end()), 4)
              << '\n';
      std::cout << pad(method, 8, true) << pad(name_of(kind), 18, true)
                << pad(sci(percentile(times, 0.5), 2), 12) << pad(sci(percentile(errs, 0.5), 2), 12)
                << pad(sci(percentile(errs, 0.95), 2), 12)
                << pad(sci(*std::max_element(errs.begin(), errs.end()), 2), 12) << "\n";
    }
  }
}

// The tracked press: a row of methods, a line of the summary table and a point of the plot.
void report_tracking(const Tracking& tr, std::ofstream& methods, LogLogPlot& plot) {
  plot.series.push_back({"fast tracking (warm, 1 kHz)",
                         "#333",
                         {{tr.median_ns * 1e-9, std::max(tr.error.max_N, kPlotFloor_N), "tracking"}},
                         false,
                         ""});
  methods << "fast_tracking,two_cell_press," << tr.ticks << ',' << sci(tr.median_ns * 1e-9, 4) << ",,,"
          << sci(tr.error.max_N, 4) << '\n';
  std::cout << pad("fast", 8, true) << pad("tracking", 18, true) << pad(sci(tr.median_ns * 1e-9, 2), 12)
            << pad("", 12) << pad("", 12) << pad(sci(tr.error.max_N, 2), 12) << "  (" << tr.ticks
            << " ticks, p99 " << sci(tr.p99_ns * 1e-9, 2) << " s, rms " << sci(tr.error.rms_N, 2) << " N)\n";
}

// Head to head on the conflicting cases: the largest fast RMS error over the slow one's, where
// the slow one is above 1 uN.
double worst_conflicting_ratio(const std::vector<Case>& cases, const std::vector<Outcome>& out) {
  double worst_ratio = 0.0;
  for (std::size_t k = 0; k < cases.size(); ++k) {
    if (cases[k].kind == Kind::conflicting && out[k].slow.rms_N > 1e-6) {
      worst_ratio = std::max(worst_ratio, out[k].fast.rms_N / out[k].slow.rms_N);
    }
  }
  return worst_ratio;
}

}  // namespace

int run_inverse_bench(const std::string& out_dir, const DeviceModel& model, bool progress) {
  const auto built = Clock::now();
  CellInverse inv(model);
  const double build_s = std::chrono::duration<double>(Clock::now() - built).count();
  const std::vector<Case> cases = make_cases(model);
  std::ofstream csv(out_dir + "/inverse_cases.csv");
  std::ofstream methods(out_dir + "/inverse_methods.csv");
  if (!csv || !methods) {
    std::cerr << "inverse: cannot write into " << out_dir << ": create it or pass another --out\n";
    return 1;
  }
  std::unique_ptr<Progress> bar;
  if (progress) {
    bar = std::make_unique<Progress>("inverse: fast and slow solves", cases.size() + 1);
  }
  const std::vector<Outcome> out = run_cases(model, inv, cases, csv, bar.get());
  const bool ok = std::all_of(out.begin(), out.end(), [](const Outcome& o) { return o.ok; });
  const Tracking tr = run_tracking(model);
  if (bar) {
    bar->tick("tracking");
  }

  // Per method and kind: time and error distributions.
  methods << "method,kind,cases,time_per_solve_s_median,max_err_N_median,max_err_N_p95,max_err_N_max\n";
  std::cout << "inverse: " << cases.size() << " cases (" << kCasesPerKind
            << " each kind), fast timed as the median of " << kFastRepetitions
            << " cold solves; construction " << fixed(build_s * 1e3, 1)
            << " ms (tables: branch flow max relative error " << sci(inv.branch_table_max_relative_error(), 2)
            << ", current inverse max error " << sci(inv.current_table_max_error_Pa(), 2) << " Pa)\n";
  std::cout << pad("method", 8, true) << pad("kind", 18, true) << pad("time/solve", 12)
            << pad("err median", 12) << pad("err p95", 12) << pad("err max", 12) << "\n";
  LogLogPlot plot = time_error_plot();
  report_methods(cases, out, methods, plot);
  report_tracking(tr, methods, plot);
  std::cout << "conflicting cases: fast RMS error at most " << fixed(worst_conflicting_ratio(cases, out), 3)
            << " x the slow exact solve's (where the slow one is above 1 uN)\n";
  if (!plot.write(out_dir + "/inverse_time_vs_error.svg")) {
    return 1;
  }
  if (!ok) {
    std::cerr << "inverse: a solve failed (see the CSV)\n";
    return 1;
  }
  return 0;
}

int run_inverse_suite(const BenchOptions& o) {
  const DeviceModel model(o.profile.empty() ? default_profile() : load_profile(o.profile));
  return run_inverse_bench(o.out, model, true);
}

}  // namespace mrskin::bench
