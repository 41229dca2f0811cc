// NetworkSimulation's step in phases (begin_step, advance_step): the linearly implicit step's
// parts run in order over kStepPhases calls, each call's share of the work about even, the
// arithmetic step()'s to the bit.
#include <algorithm>
#include <cmath>
#include <limits>

#include "mrskin/driver/model/network.hpp"
#include "network_impl.hpp"
#include "network_ldl.hpp"

namespace mrskin::model {

// Each part's work in about an instruction, as callgrind counted them on the 5 x 5 (release,
// x86-64: a link's law about 145, a cell's 70, a node's bookkeeping 10 to 25, an entry of the
// factorisation 15, of the solve 11): the plan need only be even, not exact.
void NetworkSimulation::Impl::plan_phases() {
  StepWork& w = step_work;
  const auto n_cells = static_cast<double>(cells);
  const auto n_nodes = static_cast<double>(nodes);
  const auto n_links = static_cast<double>(links.size());
  w.nodes = 70.0 * n_cells + 25.0 * n_nodes;
  w.link = 145.0;
  w.assemble = 15.0 * n_nodes + 22.0 * n_links;
  w.row.assign(nodes, 0.0);
  for (std::size_t k = 0; k < nodes; ++k) {
    w.row[k] = 20.0 + 15.0 * static_cast<double>(ldl.row_work(k));
  }
  w.pressures = 11.0 * static_cast<double>(ldl.solve_work());
  w.flows = 45.0 * n_links + 10.0 * n_nodes;
  w.settle_cell = 70.0;
  w.finish = 60.0 * n_cells + 25.0 * n_nodes + 20.0 * static_cast<double>(valves);
  w.total =
      w.nodes + w.link * n_links + w.assemble + w.pressures + w.flows + w.settle_cell * n_cells + w.finish;
  for (const double r : w.row) {
    w.total += r;
  }
}

// The step's parts from where the last call stopped until the work done reaches target (all of
// them but the commit when target is infinite). A failure abandons the step (nothing committed).
Status NetworkSimulation::Impl::run_step_work(double target) noexcept {
  const double dt = phase_dt_s;
  const StepWork& w = step_work;
  // How many items of `each` the work left to target takes (at least one; all when infinite).
  const auto items_within = [&](double left_of, double each) -> std::size_t {
    const double n = std::ceil((left_of - work_done) / each);
    return n < 1e9 ? static_cast<std::size_t>(std::max(n, 1.0)) : std::size_t{1000000000};
  };
  while (stage != StepStage::commit && work_done < target) {
    Status s = Status::ok;
    switch (stage) {
      case StepStage::nodes:
        compute_depths();
        report = StepReport{};
        std::copy(e.begin(), e.end(), cur.e.begin());
        s = evaluate_nodes(cur, false);
        work_done += w.nodes;
        stage_item = 0;
        stage = links.empty() ? StepStage::assemble : StepStage::links;
        break;
      case StepStage::links: {
        const std::size_t first = stage_item;
        stage_item = std::min(links.size(), first + items_within(target, w.link));
        s = evaluate_links(cur, first, stage_item, dt, true);
        work_done += w.link * static_cast<double>(stage_item - first);
        if (stage_item == links.size()) {
          stage = StepStage::assemble;
        }
        break;
      }
      case StepStage::assemble:
        s = evaluate_norms(cur);
        if (s == Status::ok) {
          assemble(cur, dt);
        }
        work_done += w.assemble;
        stage_item = 0;
        stage = StepStage::rows;
        break;
      case StepStage::rows: {
        const std::size_t first = stage_item;
        while (stage_item < nodes && work_done < target) {
          work_done += w.row[stage_item++];
        }
        s = ldl.factorize_rows(first, stage_item) ? Status::ok : Status::no_convergence;
        if (stage_item == nodes) {
          stage = StepStage::pressures;
        }
        break;
      }
      case StepStage::pressures:
        one_solve_pressures();
        work_done += w.pressures;
        stage = StepStage::flows;
        break;
      case StepStage::flows:
        one_solve_flows(dt);
        work_done += w.flows;
        stage_item = 0;
        stage = StepStage::settle;
        break;
      case StepStage::settle: {
        const std::size_t first = stage_item;
        stage_item = std::min(cells, first + items_within(target, w.settle_cell));
        s = settle_cells(first, stage_item);
        work_done += w.settle_cell * static_cast<double>(stage_item - first);
        if (stage_item == cells) {
          stage = StepStage::finish;
        }
        break;
      }
      case StepStage::finish:
        s = finish_settled_cells();
        if (s == Status::ok) {
          s = check_new_state();
        }
        work_done += w.finish;
        stage = StepStage::commit;
        break;
      case StepStage::commit:
        break;
    }
    if (s != Status::ok) {
      phase = 0;  // nothing committed: the state stays as before begin_step
      return s;
    }
  }
  return Status::ok;
}

Result<bool> NetworkSimulation::begin_step(double dt_s) noexcept {
  Impl& m = *impl_;
  m.phase = 0;
  if (m.opt.stepper != Stepper::linearly_implicit_regularised || !m.direct_depths || !std::isfinite(dt_s) ||
      !(dt_s > 0.0)) {
    const Result<StepReport> r = step(dt_s);
    return r.ok() ? Result<bool>{true} : failure<bool>(r.status);
  }
  m.phase_dt_s = dt_s;
  m.stage = StepStage::nodes;
  m.stage_item = 0;
  m.work_done = 0.0;
  m.phase = 1;
  if (const Status s = m.run_step_work(m.step_work.total / kStepPhases); s != Status::ok) {
    return failure<bool>(s);
  }
  return {false};
}

Result<bool> NetworkSimulation::advance_step() noexcept {
  Impl& m = *impl_;
  if (m.phase < 1 || m.phase >= kStepPhases) {
    return failure<bool>(Status::out_of_range);
  }
  ++m.phase;
  const bool last = m.phase == kStepPhases;
  const double target = last ? std::numeric_limits<double>::infinity()
                             : m.step_work.total * static_cast<double>(m.phase) / kStepPhases;
  if (const Status s = m.run_step_work(target); s != Status::ok) {
    return failure<bool>(s);
  }
  if (!last) {
    return {false};
  }
  m.commit(m.phase_dt_s);
  m.phase = 0;
  return {true};
}

}  // namespace mrskin::model
