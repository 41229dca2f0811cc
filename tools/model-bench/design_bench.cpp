// Design suite (`--suite design`): the paper's Section 4 redone on the corrected laws. Freezes
// the organ scenes into loaded cell-ticks, searches the profile's design parameters for the
// largest coverage (the smallest over the six organs first, then their mean) under the stated
// constraints, and writes
//   <out>/designed.toml          the optimum, a complete profile (mock://<out>/designed.toml)
//   <out>/design_coverage.csv    coverage per scene of the base, paper-table4 and designed profiles
//   <out>/design_search.csv      every evaluation of the search
//   <out>/design_<key>.svg       coverage against each parameter around the optimum
// Deterministic: a coordinate search over grids that halve their span each round, from the base
// profile. docs/model.md, "The design study".
#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <fstream>
#include <iostream>
#include <limits>
#include <optional>
#include <string>
#include <vector>

#include "design_coverage.hpp"
#include "design_space.hpp"
#include "linear_plot.hpp"
#include "mrskin/driver/model/coil.hpp"
#include "suites.hpp"

namespace mrskin::bench {

namespace {

using model::DeviceModel;
using model::DeviceProfile;

constexpr std::array<const char*, 6> kOrgans = {"hand", "neck", "abdomen", "thigh", "back", "stomach"};
constexpr std::array<const char*, 3> kOthers = {"sweep", "tumour", "demo"};

struct Evaluated {
  Design design;
  std::array<double, kOrgans.size()> organ{};
  double min = -1.0;  // -1: infeasible or not evaluable
  double mean = -1.0;
  double coil_power_W = INFINITY;  // every coil at full current
  std::size_t model_errors = 0;    // loaded cell-ticks whose envelope the model could not give
  bool feasible = false;
  std::string why;
};

// The smallest organ coverage, then the mean, then the lower coil power (so that turns, which
// leave the coverage alone, move to free power for the parameters that do not).
bool better(const Evaluated& a, const Evaluated& b) {
  constexpr double kTie = 1e-12;
  if (std::fabs(a.min - b.min) > kTie) {
    return a.min > b.min;
  }
  if (std::fabs(a.mean - b.mean) > kTie) {
    return a.mean > b.mean;
  }
  return a.coil_power_W < b.coil_power_W * (1.0 - 1e-9);
}

struct Study {
  DesignLimits limits;
  std::vector<FrozenScene> organs;
  std::vector<FrozenScene> guarded;  // sweep and tumour: no worse than the base profile
  std::vector<double> guarded_base;  // their coverage on the base profile
  std::ofstream log;
  std::size_t evaluations = 0;
};

// Coverage on the organs, then the constraints; `full` adds the refill simulation and the guard
// on sweep and tumour (they cost more: only for a candidate that would be taken).
Evaluated evaluate(Study& s, Design d, bool full) {
  Evaluated e{d, {}, -1.0, -1.0, INFINITY, 0, false, ""};
  ++s.evaluations;
  try {
    if (!apply_derived(d)) {
      e.why = "no current renders the design force";
      return e;
    }
    e.design = d;
    const DeviceModel m(d.profile);
    double sum = 0.0;
    e.min = 1.0;
    for (std::size_t k = 0; k < s.organs.size(); ++k) {
      const Coverage c = coverage_of(m, s.organs[k]);
      e.organ.at(k) = c.fraction();
      e.model_errors += c.model_errors;
      e.min = std::min(e.min, e.organ.at(k));
      sum += e.organ.at(k);
    }
    e.mean = sum / static_cast<double>(s.organs.size());
    const ConstraintReport r = check_constraints(m, s.limits, full);
    e.coil_power_W = r.coil_power_W;
    e.feasible = r.ok;
    e.why = r.failed;
    for (std::size_t k = 0; full && e.feasible && k < s.guarded.size(); ++k) {
      const double c = coverage_of(m, s.guarded[k]).fraction();
      if (c < s.guarded_base[k]) {
        e.feasible = false;
        e.why = s.guarded[k].name + " coverage " + fixed(100.0 * c, 1) + " % below the base's";
      }
    }
  } catch (const std::exception& ex) {
    e.why = ex.what();
  }
  return e;
}

std::vector<double> grid(const DesignParam& d, double centre, double span_fraction, int points) {
  auto to = [&](double v) { return d.log_scale ? std::log(v) : v; };
  auto from = [&](double u) { return d.log_scale ? std::exp(u) : u; };
  const double half = 0.5 * span_fraction * (to(d.hi) - to(d.lo));
  const double lo = std::max(to(d.lo), to(centre) - half);
  const double hi = std::min(to(d.hi), to(centre) + half);
  std::vector<double> v;
  for (int k = 0; k < points; ++k) {
    double x = from(lo + (hi - lo) * k / (points - 1));
    x = d.integer ? std::round(x) : x;
    if (v.empty() || std::fabs(x - v.back()) > 1e-12 * std::fabs(x)) {
      v.push_back(x);
    }
  }
  return v;
}

Evaluated search(Study& s, const Design& base, int rounds, int points) {
  Evaluated best = evaluate(s, base, true);
  if (!best.feasible) {
    best.min = best.mean = -1.0;
  }
  s.log << "round,parameter,value,organ_min,organ_mean,model_errors,feasible,why\n";
  Progress bar("design search", static_cast<std::size_t>(rounds) * design_params().size());
  for (int round = 0; round < rounds; ++round) {
    const double span = 1.0 / std::pow(2.0, round);
    for (const DesignParam& d : design_params()) {
      std::optional<Evaluated> pick;
      for (const double v : grid(d, d.get(best.design), span, points)) {
        Design p = best.design;
        d.set(p, v);
        Evaluated e = evaluate(s, p, false);
        // The refill simulation only for a candidate that would be taken.
        if (e.feasible && better(e, pick ? *pick : best)) {
          e = evaluate(s, p, true);
        }
        s.log << round << ',' << d.key << ',' << general(v, 6) << ',' << e.min << ',' << e.mean << ','
              << e.model_errors << ',' << (e.feasible ? 1 : 0) << ",\"" << e.why << "\"\n";
        if (e.feasible && better(e, pick ? *pick : best)) {
          pick = e;
        }
      }
      if (pick) {
        best = *pick;
      }
      bar.tick(d.key);
    }
  }
  return best;
}

// Coverage against each parameter around the optimum, the others held there.
bool write_sweeps(Study& s, const Evaluated& best, const Design& base, const std::string& out, int points) {
  bool ok = true;
  Progress bar("design plots", design_params().size());
  for (const DesignParam& d : design_params()) {
    std::vector<double> xs = grid(d, d.get(best.design), 2.0, points);
    xs.push_back(d.get(best.design));
    std::sort(xs.begin(), xs.end());
    xs.erase(std::unique(xs.begin(), xs.end()), xs.end());
    PlotSeries lo{"min of the six organs", "#0072b2", {}, true, ""};
    PlotSeries mean{"mean of the six organs", "#009e73", {}, true, "5,3"};
    PlotSeries bad{"a constraint fails", "#999", {}, false, ""};
    for (const double x : xs) {
      Design p = best.design;
      d.set(p, x);
      const Evaluated e = evaluate(s, p, true);
      lo.points.push_back({x, 100.0 * std::max(e.min, 0.0), ""});
      mean.points.push_back({x, 100.0 * std::max(e.mean, 0.0), ""});
      if (!e.feasible) {
        bad.points.push_back({x, 100.0 * std::max(e.min, 0.0), ""});
      }
    }
    LinearPlot plot;
    plot.title = std::string("Organ coverage against ") + d.key;
    plot.subtitle = "the other parameters at the optimum; grey: a constraint fails";
    plot.x_label = std::string("[") + d.section + "] " + d.key;
    plot.y_label = "loaded cell-ticks inside the envelope, %";
    plot.x_lo = d.lo;
    plot.x_hi = d.hi;
    plot.y_lo = 0.0;
    plot.y_hi = 100.0;
    plot.series = {lo, mean, bad};
    plot.refs = {{true, d.get(best.design), "designed", "#c00"},
                 {true, d.get(base), "base profile", "#555"},
                 {false, 90.0, "goal: 90 % (10 % clamped)", "#e69f00"}};
    ok = plot.write(out + "/design_" + d.key + ".svg") && ok;
    bar.tick(d.key);
  }
  return ok;
}

}  // namespace

namespace {

struct Row {
  std::string profile;
  std::vector<Coverage> scenes;  // organs, then kOthers
  ConstraintReport constraints;
};

Row measure(const std::string& name, const DeviceProfile& p, const std::vector<FrozenScene>& all,
            const DesignLimits& limits) {
  const DeviceModel m(p);
  Row r{name, {}, check_constraints(m, limits, true)};
  for (const FrozenScene& f : all) {
    r.scenes.push_back(coverage_of(m, f));
  }
  return r;
}

void report(const std::vector<Row>& rows, const std::vector<FrozenScene>& all, const std::string& out) {
  std::ofstream csv(out + "/design_coverage.csv");
  csv << "profile,scene,loaded_cell_ticks,inside,below_floor,below_bulge_floor,floor_viscous,floor_membrane,"
         "floor_p0,"
         "above_ceiling,above_bulge_ceiling,model_errors,coverage\n";
  std::cout << pad("scene", 10, true) << pad("ticks", 7);
  for (const Row& r : rows) {
    std::cout << pad(r.profile + " cov (floor/ceil) %", 36);
  }
  std::cout << "\n";
  for (std::size_t k = 0; k < all.size(); ++k) {
    std::cout << pad(all[k].name, 10, true) << pad(std::to_string(all[k].ticks.size()), 7);
    for (const Row& r : rows) {
      const Coverage& c = r.scenes[k];
      auto pct = [&c](std::size_t n) {
        return fixed(100.0 * static_cast<double>(n) / static_cast<double>(c.ticks), 1);
      };
      std::cout << pad(
          fixed(100.0 * c.fraction(), 1) + " (" + pct(c.below_floor) + "/" + pct(c.above_ceiling) + ")", 36);
      csv << r.profile << ',' << all[k].name << ',' << c.ticks << ',' << c.inside << ',' << c.below_floor
          << ',' << c.below_bulge_floor << ',' << c.floor_viscous << ',' << c.floor_membrane << ','
          << c.floor_p0 << ',' << c.above_ceiling << ',' << c.above_bulge_ceiling << ',' << c.model_errors
          << ',' << c.fraction() << "\n";
    }
    std::cout << "\n";
  }
  for (const Row& r : rows) {
    const ConstraintReport& c = r.constraints;
    std::cout << r.profile << ": " << (c.ok ? "meets every constraint" : "fails: " + c.failed)
              << "; coil tau " << fixed(c.coil_time_constant_s * 1e3, 2) << " ms, full-scale step "
              << fixed(c.rail_voltage_V, 2) << " V, coils " << fixed(c.coil_power_W, 3) << " W (+"
              << fixed(c.temperature_rise_K, 2) << " K), one count "
              << fixed(100.0 * c.force_per_count_fraction, 3) << " % of the range, design force at "
              << (c.range_use < 0 ? std::string("none") : fixed(100.0 * c.range_use, 1) + " %")
              << " of I_max, refill "
              << (c.refill_depth_m < 0 ? std::string("not run") : fixed(c.refill_depth_m * 1e6, 1) + " um")
              << "\n";
  }
}

}  // namespace

int run_design_suite(const BenchOptions& o) {
  const auto start = std::chrono::steady_clock::now();
  const model::LoadedProfile base = model::load_profile_with_text(o.profile);
  Study s;
  s.limits.coil_time_constant_s = model::coil_time_constant_s(model::default_profile().coil);
  FreezeOptions freeze;
  freeze.duration_s = o.quick ? 4.3 : 8.0;  // quick: one organ cycle
  // The scenes, frozen once on the base's layout (every candidate has the same grid).
  const DeviceModel base_model(base.profile);
  std::vector<FrozenScene> all;
  for (const char* name : kOrgans) {
    s.organs.push_back(freeze_scene(name, base_model.layout(), freeze));
    all.push_back(s.organs.back());
  }
  for (const char* name : kOthers) {
    all.push_back(freeze_scene(name, base_model.layout(), freeze));
    if (all.back().name != "demo") {
      s.guarded.push_back(all.back());
    }
  }
  // The search starts from the base with its derived quantities recomputed by the same rules.
  const ConstraintReport base_check = check_constraints(base_model, s.limits, false);
  Design start_design{base.profile,
                      std::clamp(base_check.range_use, s.limits.min_range_use, s.limits.max_range_use)};
  if (!apply_derived(start_design)) {
    std::cerr << "design: the base profile renders no design force\n";
    return 1;
  }
  const DeviceModel start_model(start_design.profile);
  for (const FrozenScene& g : s.guarded) {
    s.guarded_base.push_back(coverage_of(start_model, g).fraction());
  }
  s.log.open(o.out + "/design_search.csv");
  const Evaluated best = search(s, start_design, o.quick ? 2 : 4, o.quick ? 4 : 9);
  if (!best.feasible) {
    std::cerr << "design: no candidate meets the constraints: " << best.why << "\n";
    return 1;
  }
  std::string command = "mrskin-model-bench --suite design --out DIR";
  command += o.quick ? " --quick" : "";
  command += o.profile.empty() ? "" : " --profile " + o.profile;
  std::ofstream(o.out + "/designed.toml") << designed_toml(base.text, best.design, command);
  const double search_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  const bool plots = write_sweeps(s, best, start_design, o.out, o.quick ? 3 : 15);
  const DeviceProfile written = model::load_profile(o.out + "/designed.toml");
  const std::vector<Row> rows = {measure(base.profile.name, base.profile, all, s.limits),
                                 measure("paper-table4", model::load_profile("paper-table4"), all, s.limits),
                                 measure("designed", written, all, s.limits)};
  report(rows, all, o.out);
  std::cout << "designed:";
  for (const DesignParam& d : design_params()) {
    std::cout << " " << d.key << "=" << general(d.get(best.design), 4) << " (base "
              << general(d.get(start_design), 4) << ")";
  }
  std::cout << " max_current_A=" << general(written.coil.max_current_A, 4) << " (base "
            << general(base.profile.coil.max_current_A, 4) << ")\n";
  const double total_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::cout << "search " << fixed(search_s, 1) << " s, " << s.evaluations << " evaluations in all, total "
            << fixed(total_s, 1) << " s; wrote " << o.out << "/designed.toml\n";
  // The written file must meet the constraints and cover the organs at least as the base does.
  double base_min = 1.0;
  double designed_min = 1.0;
  for (std::size_t k = 0; k < kOrgans.size(); ++k) {
    base_min = std::min(base_min, rows.front().scenes[k].fraction());
    designed_min = std::min(designed_min, rows.back().scenes[k].fraction());
  }
  if (!rows.back().constraints.ok || designed_min < base_min || !plots) {
    std::cerr << "design: the written profile fails a constraint or covers the organs less than the base\n";
    return 1;
  }
  return 0;
}

}  // namespace mrskin::bench
