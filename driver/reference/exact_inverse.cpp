#include "mrskin/driver/model/exact_inverse.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

namespace mrskin::model {

namespace {
bool is_loaded(CellRole r) noexcept { return r == CellRole::holding || r == CellRole::loading; }
}  // namespace

namespace {

struct ExactProblem {
  const DeviceModel& model;
  std::vector<std::size_t> loaded;
  std::vector<double> depth;
  std::vector<double> rate;
  std::vector<double> target;
  long evaluations = 0;

  double force(std::size_t cell, std::span<const double> currents) {
    ++evaluations;
    const Result<CellLoad> l = model.cell_force(cell, depth[cell], rate[cell], currents);
    return l.ok() ? l.value.force_N : std::numeric_limits<double>::quiet_NaN();
  }
  double objective(std::span<const double> currents) {
    double s = 0.0;
    for (const std::size_t i : loaded) {
      const double d = force(i, currents) - target[i];
      s += d * d;
    }
    return s;
  }
};

// Pattern search along `dir` (clamped into the box): a scan then golden section on the best
// bracket. Only `cells` change with this direction.
double line_search(ExactProblem& pb, std::vector<double>& cur, const std::vector<double>& dir,
                   const std::vector<std::size_t>& cells, double imax) {
  const std::vector<double> base = cur;
  auto at = [&](double a) {
    for (std::size_t v = 0; v < cur.size(); ++v) {
      cur[v] = dir[v] == 0.0 ? base[v] : std::clamp(base[v] + a * dir[v], 0.0, imax);
    }
    double s = 0.0;
    for (const std::size_t i : cells) {
      const double d = pb.force(i, cur) - pb.target[i];
      s += d * d;
    }
    return std::isfinite(s) ? s : std::numeric_limits<double>::infinity();
  };
  constexpr int kScan = 16;
  double best_a = 0.0;
  double best = at(0.0);
  const double start = best;
  std::array<double, kScan + 1> as{};
  std::array<double, kScan + 1> fs{};
  for (int k = 0; k <= kScan; ++k) {
    as[static_cast<std::size_t>(k)] = -imax + 2.0 * imax * k / kScan;
    fs[static_cast<std::size_t>(k)] = at(as[static_cast<std::size_t>(k)]);
    if (fs[static_cast<std::size_t>(k)] < best) {
      best = fs[static_cast<std::size_t>(k)];
      best_a = as[static_cast<std::size_t>(k)];
    }
  }
  // Golden section around the best point found (one scan step each side).
  double lo = best_a - 2.0 * imax / kScan;
  double hi = best_a + 2.0 * imax / kScan;
  const double gr = 0.5 * (std::sqrt(5.0) - 1.0);
  double x1 = hi - gr * (hi - lo);
  double x2 = lo + gr * (hi - lo);
  double f1 = at(x1);
  double f2 = at(x2);
  for (int it = 0; it < 60 && hi - lo > 1e-12 * imax; ++it) {
    if (f1 < f2) {
      hi = x2;
      x2 = x1;
      f2 = f1;
      x1 = hi - gr * (hi - lo);
      f1 = at(x1);
    } else {
      lo = x1;
      x1 = x2;
      f1 = f2;
      x2 = lo + gr * (hi - lo);
      f2 = at(x2);
    }
  }
  if (f1 < best) {
    best = f1;
    best_a = x1;
  }
  if (f2 < best) {
    best = f2;
    best_a = x2;
  }
  at(best < start ? best_a : 0.0);
  return start - std::min(best, start);
}

void pattern_search(ExactProblem& pb, std::vector<double>& cur, int max_sweeps, int& sweeps) {
  const DeviceModel& m = pb.model;
  const double imax = m.profile().coil.max_current_A;
  const GridLayout& l = m.layout();
  // Directions: each valve of a loaded cell, then each loaded cell's valves together.
  std::vector<std::vector<double>> dirs;
  std::vector<std::vector<std::size_t>> touched;
  std::vector<char> used(cur.size(), 0);
  auto cells_of_valves = [&](const std::vector<double>& dir) {
    std::vector<std::size_t> cs;
    for (const std::size_t i : pb.loaded) {
      for (const std::size_t v : l.valves_of_cell(i)) {
        if (dir[v] != 0.0) {
          cs.push_back(i);
          break;
        }
      }
    }
    return cs;
  };
  for (const std::size_t i : pb.loaded) {
    for (const std::size_t v : l.valves_of_cell(i)) {
      if (used[v] == 0) {
        used[v] = 1;
        std::vector<double> d(cur.size(), 0.0);
        d[v] = 1.0;
        touched.push_back(cells_of_valves(d));
        dirs.push_back(std::move(d));
      }
    }
  }
  for (const std::size_t i : pb.loaded) {
    std::vector<double> d(cur.size(), 0.0);
    for (const std::size_t v : l.valves_of_cell(i)) {
      d[v] = 1.0;
    }
    touched.push_back(cells_of_valves(d));
    dirs.push_back(std::move(d));
  }
  double f = pb.objective(cur);
  for (sweeps = 0; sweeps < max_sweeps; ++sweeps) {
    double gain = 0.0;
    for (std::size_t k = 0; k < dirs.size(); ++k) {
      gain += line_search(pb, cur, dirs[k], touched[k], imax);
    }
    f -= gain;
    if (gain <= 1e-14 * std::max(f, 1e-12) || f <= 1e-20) {
      ++sweeps;
      break;
    }
  }
}

}  // namespace

ExactInverseResult solve_inverse_exact(const DeviceModel& model, std::span<const CellImpedanceTarget> targets,
                                       std::span<const CellState> states, double now_s,
                                       std::span<const double> start_currents_A,
                                       const InverseOptions& options, int max_sweeps) {
  const std::size_t cells = model.layout().fluid_cell_count();
  const std::size_t valves = model.layout().valve_count();
  ExactInverseResult out;
  if (targets.size() != cells || states.size() != cells || start_currents_A.size() != valves) {
    out.status = Status::out_of_range;
    return out;
  }
  ExactProblem pb{model,
                  {},
                  std::vector<double>(cells, 0.0),
                  std::vector<double>(cells, 0.0),
                  std::vector<double>(cells, 0.0)};
  out.roles.assign(cells, CellRole::no_contact);
  out.target_force_N.assign(cells, 0.0);
  out.force_N.assign(cells, 0.0);
  for (std::size_t i = 0; i < cells; ++i) {
    const CellRole role =
        classify_cell(states[i], now_s > targets[i].valid_until_s, options.hold_rate_tolerance_m_per_s);
    out.roles[i] = role;
    if (!is_loaded(role)) {
      continue;
    }
    pb.loaded.push_back(i);
    pb.depth[i] = states[i].indentation_m;
    pb.rate[i] = role == CellRole::loading ? states[i].rate_m_per_s : 0.0;
    const Result<CellEnvelope> env = model.envelope(i, pb.depth[i], pb.rate[i]);
    if (!env.ok()) {
      out.status = env.status;
      return out;
    }
    pb.target[i] =
        std::clamp(impedance_force_N(targets[i], states[i]), env.value.force_min_N, env.value.force_max_N);
    out.target_force_N[i] = pb.target[i];
  }
  const double imax = model.profile().coil.max_current_A;
  std::vector<double> a(start_currents_A.begin(), start_currents_A.end());
  for (double& x : a) {
    x = std::clamp(x, 0.0, imax);
  }
  // Second start: every valve at the largest uniform current its loaded cells need.
  std::vector<double> b(valves, 0.0);
  for (const std::size_t i : pb.loaded) {
    const Result<double> ic = model.current_for_force_A(i, pb.depth[i], pb.rate[i], pb.target[i]);
    const double cur = ic.ok() ? ic.value : (pb.target[i] > 0.5 * imax ? imax : 0.0);
    for (const std::size_t v : model.layout().valves_of_cell(i)) {
      b[v] = std::max(b[v], cur);
    }
  }
  int sa = 0;
  int sb = 0;
  pattern_search(pb, a, max_sweeps, sa);
  pattern_search(pb, b, max_sweeps, sb);
  const double fa = pb.objective(a);
  const double fb = pb.objective(b);
  out.currents_A = fa <= fb ? a : b;
  out.sweeps = sa + sb;
  double sum = 0.0;
  for (const std::size_t i : pb.loaded) {
    out.force_N[i] = pb.force(i, out.currents_A);
    const double d = out.force_N[i] - pb.target[i];
    sum += d * d;
  }
  out.residual_norm_N = std::sqrt(sum);
  out.evaluations = pb.evaluations;
  return out;
}

Status exact_rendered_forces_N(const DeviceModel& model, std::span<const CellImpedanceTarget> targets,
                               std::span<const CellState> states, double now_s,
                               std::span<const double> currents_A, std::span<double> out,
                               const InverseOptions& options) {
  const std::size_t cells = model.layout().fluid_cell_count();
  if (targets.size() != cells || states.size() != cells || out.size() != cells ||
      currents_A.size() != model.layout().valve_count()) {
    return Status::out_of_range;
  }
  for (std::size_t i = 0; i < cells; ++i) {
    out[i] = 0.0;
    const CellRole role =
        classify_cell(states[i], now_s > targets[i].valid_until_s, options.hold_rate_tolerance_m_per_s);
    if (!is_loaded(role)) {
      continue;
    }
    const double v = role == CellRole::loading ? states[i].rate_m_per_s : 0.0;
    const Result<CellLoad> l = model.cell_force(i, states[i].indentation_m, v, currents_A);
    if (!l.ok()) {
      return l.status;
    }
    out[i] = l.value.force_N;
  }
  return Status::ok;
}

}  // namespace mrskin::model