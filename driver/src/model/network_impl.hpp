// NetworkSimulation's private parts, shared by its sources: the step's node state, the links and
// sensor plans, and the state behind NetworkSimulation (Impl). network_build.cpp checks the
// options and builds the nodes, links, cell laws and sensor plans once; network.cpp steps.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include "mrskin/driver/model/network.hpp"
#include "network_ldl.hpp"

namespace mrskin::model::network_detail {

inline constexpr std::size_t kMaxContacts = 16;
inline constexpr std::int64_t kNone = -1;
inline constexpr int kScalarIterations = 200;
inline constexpr int kForceEvaluations = 100;
inline constexpr int kForceSweeps = 30;
inline constexpr double kArmijo = 1e-4;
inline constexpr double kMinStep = 1.0 / 1024.0;

// One input per valve or cell: out_of_range on a size mismatch or a value at or above `limit`,
// not_finite, negative.
inline Status check_inputs(std::span<const double> v, std::size_t size, double limit) noexcept {
  if (v.size() != size) {
    return Status::out_of_range;
  }
  for (const double x : v) {
    if (!std::isfinite(x)) {
      return Status::not_finite;
    }
    if (x < 0.0) {
      return Status::negative;
    }
    if (x >= limit) {
      return Status::out_of_range;
    }
  }
  return Status::ok;
}

// An energy k1 x^2 / 2 + k3 x^4 / 4 (pad: x = depth; bulge: x = bulge volume). Its discrete
// gradient (U(x1) - U(x0)) / (x1 - x0) is a polynomial, evaluated without the subtraction, so
// it needs no special case for a tiny increment.
struct Quartic {
  double k1 = 0.0;
  double k3 = 0.0;
  [[nodiscard]] double grad(double x) const noexcept { return (k1 + k3 * x * x) * x; }
  [[nodiscard]] double stiffness(double x) const noexcept { return k1 + 3.0 * k3 * x * x; }
  [[nodiscard]] double discrete_grad(double x0, double x1) const noexcept {
    return 0.5 * (x0 + x1) * (k1 + 0.5 * k3 * (x0 * x0 + x1 * x1));
  }
  // d/dx1 of discrete_grad: k1/2 + k3 ((x0 + x1)^2 + 2 x1^2) / 4 > 0.
  [[nodiscard]] double discrete_stiffness(double x0, double x1) const noexcept {
    const double m = x0 + x1;
    return 0.5 * k1 + 0.25 * k3 * (m * m + 2.0 * x1 * x1);
  }
  // dg: the discrete gradient between x0 and x1, else the gradient at x1.
  [[nodiscard]] double value(double x0, double x1, bool dg) const noexcept {
    return dg ? discrete_grad(x0, x1) : grad(x1);
  }
  [[nodiscard]] double slope(double x0, double x1, bool dg) const noexcept {
    return dg ? discrete_stiffness(x0, x1) : stiffness(x1);
  }
};

// Node state of one evaluation of the step's balance at trial volumes e.
struct Eval {
  std::vector<double> e;                  // node volume gain, m^3
  std::vector<double> p;                  // node pressure used by the law (discrete gradient or point), Pa
  std::vector<double> c;                  // node compliance 1 / (dp/de), m^3/Pa
  std::vector<double> d;                  // cells: pad depth, m
  std::vector<unsigned char> in_contact;  // cells: pad held at the contact depth
  std::vector<double> r;                  // node residual e - e0 + dt * outflow, m^3
  std::vector<double> q;                  // link flow, m^3/s
  std::vector<double> g;                  // link conductance dq/dx, m^3/(s Pa)
  std::vector<double> x;                  // link pressure difference the law was evaluated at, Pa
  double norm2 = 0.0;
  double norm_inf = 0.0;

  void resize(std::size_t nodes, std::size_t cells, std::size_t links) {
    e.assign(nodes, 0.0);
    p.assign(nodes, 0.0);
    c.assign(nodes, 0.0);
    r.assign(nodes, 0.0);
    d.assign(cells, 0.0);
    in_contact.assign(cells, 1);
    q.assign(links, 0.0);
    g.assign(links, 0.0);
    x.assign(links, 0.0);
  }
  void swap(Eval& o) noexcept {
    e.swap(o.e);
    p.swap(o.p);
    c.swap(o.c);
    d.swap(o.d);
    in_contact.swap(o.in_contact);
    r.swap(o.r);
    q.swap(o.q);
    g.swap(o.g);
    x.swap(o.x);
    std::swap(norm2, o.norm2);
    std::swap(norm_inf, o.norm_inf);
  }
};

// The parts of a linearly implicit step, in order (a step in phases: network_phases.cpp).
enum class StepStage : unsigned char {
  nodes,
  links,
  assemble,
  rows,
  pressures,
  flows,
  settle,
  finish,
  commit
};

struct Link {
  std::uint32_t a = 0;
  std::uint32_t b = 0;
  std::int32_t valve = -1;
};

struct SensorPlan {
  SensorQuantity quantity = SensorQuantity::displacement;
  PlaceKind place = PlaceKind::valve;
  std::size_t index = 0;
  std::uint32_t cells_begin = 0;  // into sensor_cells (displacement/force at a valve)
  std::uint32_t cells_end = 0;
};

}  // namespace mrskin::model::network_detail

namespace mrskin::model {

// The network's sources share these parts by name (only they include this header).
using namespace network_detail;

// Hidden: its functions are called directly (and inlined) within the library, never through the PLT.
struct __attribute__((visibility("hidden"))) NetworkSimulation::Impl {
  Impl(DeviceModel m, const NetworkOptions& o);
  // Construction steps (network_build.cpp), in this order; each throws InvalidArgument naming
  // origin for a profile or option it cannot use.
  void check_options(const std::string& origin) const;
  void build_nodes_and_links(const std::string& origin);
  void build_cell_laws(const std::string& origin);
  void plan_sensors();
  void size_state();

  // ---- constants ----
  DeviceModel model;
  NetworkOptions opt;
  std::size_t cells = 0;
  std::size_t valves = 0;
  std::size_t nodes = 0;
  std::vector<Link> links;
  std::vector<std::int64_t> chamber_node;  // per valve
  std::int64_t reservoir_node = kNone;
  std::vector<double> node_compliance;  // chambers and reservoir, m^3/Pa
  std::vector<double> cell_x;
  std::vector<double> cell_y;
  double area = 0.0;  // A_eff
  Quartic pad;
  Quartic bulge;
  double s_rest = 0.0;  // bulge volume at p0
  double p0 = 0.0;
  double cell_depth = 0.0;
  double floor_conductance = 0.0;      // regularised law's conductance inside the yield band
  double newtonian_conductance = 0.0;  // an open passage's without yield, laminar
  double critical_flow = 0.0;          // where its flow turns turbulent (flow_point's branch)
  std::vector<SensorPlan> sensors;
  std::vector<std::uint32_t> sensor_cells;
  detail::SparseLdl ldl;

  // ---- inputs ----
  std::vector<double> valve_tau;
  std::array<Contact, kMaxContacts> contacts{};
  std::size_t contact_count = 0;
  bool direct_depths = true;  // set_cell_indentation_m (true) or contacts
  std::vector<double> direct_depth;
  std::array<double, kMaxContacts> contact_ind{};  // solved indentation of each contact

  // ---- committed state ----
  std::vector<double> e;
  std::vector<double> d;
  std::vector<double> velocity;
  std::vector<double> node_p;
  std::vector<double> force;
  std::vector<double> chamber_p;
  std::vector<double> q;
  std::vector<double> prev_e;  // the step before (Newton's predictor)
  double prev_dt = 0.0;        // 0: no step since construction or reset
  std::array<double, kMaxContacts> contact_force{};
  double work = 0.0;
  double stored_initial = 0.0;
  double dissipated = 0.0;
  // Free pads' depth searches (resolve_cell) and their Newton iterations, since construction or
  // reset. Counted inside const evaluations; the object is not shared between threads.
  mutable std::uint64_t pad_searches = 0;
  mutable std::uint64_t pad_search_iterations = 0;
  mutable std::uint64_t balance_evaluations = 0;  // evaluate_nodes calls, the same way

  // ---- one step's workspace ----
  std::vector<double> dc;           // contact depth of each cell for the step
  std::vector<std::int64_t> owner;  // contact that sets it
  Eval cur;
  Eval trial;
  std::vector<double> y;
  std::vector<double> de;
  // The step's result, committed by commit().
  std::vector<double> new_e;
  std::vector<double> new_d;
  std::vector<unsigned char> new_in_contact;
  std::vector<double> new_q;
  std::vector<double> new_p;
  std::vector<double> new_force;
  std::array<double, kMaxContacts> new_contact_force{};
  double new_dissipated = 0.0;
  StepReport report;
  // A step in phases (begin_step): the phases run (0: none in progress), its dt (s), the
  // stage and item it reached and the work done, in the plan's units.
  int phase = 0;
  double phase_dt_s = 0.0;
  StepStage stage = StepStage::nodes;
  std::size_t stage_item = 0;
  double work_done = 0.0;
  // The plan (plan_phases, by topology): each part's work in about an instruction (callgrind,
  // x86-64 release), so that kStepPhases phases share the step about evenly.
  struct StepWork {
    double nodes = 0.0;
    double link = 0.0;
    double assemble = 0.0;
    std::vector<double> row;
    double pressures = 0.0;
    double flows = 0.0;
    double settle_cell = 0.0;
    double finish = 0.0;
    double total = 0.0;
  } step_work;
  // advance_cell_gain's pressures, one per node, and each fluid cell's links in link order.
  std::vector<double> between_p;
  std::vector<std::uint32_t> cell_links_begin;
  std::vector<std::uint32_t> cell_links;

  // ---- laws ----
  [[nodiscard]] double s_of(double depth, double gain) const noexcept { return s_rest + area * depth + gain; }
  Status link_law(std::size_t l, double x, bool regularised, double& flow, double& cond) const noexcept;
  Status resolve_cell(std::size_t i, double e1, bool dg, Eval& ev) const noexcept;
  Status evaluate(Eval& ev, double dt, bool dg, bool regularised) const noexcept;
  Status evaluate_nodes(Eval& ev, bool dg) const noexcept;
  Status evaluate_links(Eval& ev, std::size_t first, std::size_t last, double dt,
                        bool regularised) const noexcept;
  Status evaluate_norms(Eval& ev) const noexcept;
  bool assemble_and_factorize(const Eval& ev, double dt) noexcept;
  void assemble(const Eval& ev, double dt) noexcept;
  Status newton(double dt, bool regularised) noexcept;
  Status one_solve(double dt) noexcept;
  Status one_solve_evaluate(double dt) noexcept;
  void one_solve_finish(double dt) noexcept;
  void one_solve_pressures() noexcept;
  void one_solve_flows(double dt) noexcept;
  Status settle_one_step_cells() noexcept;
  Status settle_cells(std::size_t first, std::size_t last) noexcept;
  Status finish_settled_cells() noexcept;
  Status check_new_state() const noexcept;
  Status forward_euler(double dt) noexcept;
  Status run_trial(double dt) noexcept;
  Status check_linearisation() noexcept;
  void finish_volumes(const Eval& at, double dt) noexcept;
  void finish_state(const Eval& depths) noexcept;
  void compute_depths() noexcept;
  Status solve_force_contacts(double dt) noexcept;
  Status solve_one_contact(std::size_t c, double dt) noexcept;
  [[nodiscard]] double contact_error(std::size_t c) const noexcept {
    return new_contact_force[c] - contacts[c].force_N;
  }
  void commit(double dt) noexcept;
  void plan_phases();
  Status run_step_work(double target) noexcept;
  [[nodiscard]] double stored_energy() const noexcept;
  void reset() noexcept;
};

}  // namespace mrskin::model
