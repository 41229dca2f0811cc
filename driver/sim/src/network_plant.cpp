#include "mrskin/sim/network_plant.hpp"

#include <algorithm>
#include <bit>
#include <cmath>
#include <limits>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/model/coil.hpp"
#include "mrskin/driver/model/device_model.hpp"
#include "mrskin/driver/model/magnetic.hpp"

namespace mrskin::sim {

namespace {

// Commands waiting out the bus delay: a fixed ring of (apply time, currents).
constexpr std::size_t kDelaySlots = 64;

double factor(std::mt19937_64& rng, double half_width) {
  std::uniform_real_distribution<double> u(-half_width, half_width);
  return 1.0 + u(rng);
}

}  // namespace

model::DeviceProfile perturbed_profile(const model::DeviceProfile& nominal, double perturbation,
                                       std::uint64_t seed) {
  if (!(perturbation >= 0.0 && perturbation < 0.5)) {
    throw InvalidArgument("plant perturbation must be in [0, 0.5) (got " + std::to_string(perturbation) +
                          ")");
  }
  std::mt19937_64 rng(seed);
  model::DeviceProfile p = nominal;
  p.name = nominal.name + " (perturbed, seed " + std::to_string(seed) + ")";
  p.fluid.viscosity_Pa_s *= factor(rng, perturbation);
  p.fluid.carrier_factor *= factor(rng, perturbation);
  p.membrane.youngs_modulus_Pa *= factor(rng, perturbation);
  p.membrane.pretension_N_per_m *= factor(rng, perturbation);
  p.reservoir.compliance_m3_per_Pa *= factor(rng, perturbation);
  const double turns = static_cast<double>(p.magnetic.turns) * factor(rng, perturbation / 3.0);
  p.magnetic.turns = std::max(1, static_cast<int>(std::lround(turns)));
  p.valve.gap_m *= factor(rng, perturbation / 5.0);
  p.magnetic.fluid_gap_m = p.valve.gap_m;
  return p;
}

struct __attribute__((visibility("hidden"))) NetworkPlant::Impl {
  Impl(const model::DeviceProfile& nominal, const NetworkPlantOptions& o)
      : options(o),
        truth(perturbed_profile(nominal, o.perturbation, o.seed)),
        network(truth, network_options(o, truth)),
        rng(o.seed ^ 0x9E3779B97F4A7C15ULL) {
    const std::size_t valves = truth.layout().valve_count();
    const std::size_t sensors = truth.profile().sensors.size();
    if (!(o.command_delay_s >= 0.0 && o.command_delay_s < 0.05)) {
      throw InvalidArgument("plant command_delay_s must be in [0, 0.05) s (got " +
                            std::to_string(o.command_delay_s) + ")");
    }
    std::mt19937_64 gains(o.seed + 1);
    valve_gain.resize(valves);
    for (double& g : valve_gain) {
      g = factor(gains, o.perturbation);
    }
    coil.resize(valves);
    hysteresis.resize(valves);
    commanded_A.assign(valves, 0.0);
    yield_Pa.assign(valves, 0.0);
    solved.assign(valves, SolvedField{});
    coil_A.assign(valves, 0.0);
    ring_A.assign(kDelaySlots * valves, 0.0);
    ring_time_s.assign(kDelaySlots, 0.0);
    sensor_value.assign(sensors, 0.0);
    sensor_noisy.assign(sensors, 0.0);
    magnetic = truth.profile().magnetic;
    magnetic.steel.coercivity_A_per_m *= o.hysteresis_scale;
    noise_std.resize(sensors);
    resolution.resize(sensors);
    for (std::size_t i = 0; i < sensors; ++i) {
      noise_std[i] = truth.profile().sensors[i].noise_std * o.sensor_noise_scale;
      resolution[i] = truth.profile().sensors[i].resolution;
    }
  }

  static model::NetworkOptions network_options(const NetworkPlantOptions& o,
                                               const model::DeviceModel& truth) {
    if (!(o.substep_s > 0.0 && std::isfinite(o.substep_s))) {
      std::ostringstream got;
      got << o.substep_s;  // the shortest form, as %g: 1e-12, not 0.000000
      throw InvalidArgument(
          "the plant's substep (NetworkPlantOptions::substep_s, the mock's physics_dt) must be positive and "
          "finite, got " +
          got.str() + " s");
    }
    model::NetworkOptions n;
    n.stepper = o.stepper;
    using Integration = NetworkPlantOptions::Integration;
    n.backward_euler = o.integration == Integration::backward_euler ||
                       (o.integration == Integration::automatic &&
                        truth.cell_open_drain_time_s() < NetworkPlantOptions::kStiffStepRatio * o.substep_s);
    return n;
  }

  // Moves every command whose delay has elapsed to the coil drivers.
  void release_due_commands() noexcept {
    const std::size_t valves = commanded_A.size();
    while (ring_count > 0 && ring_time_s[ring_head] <= time_s + 1e-12) {
      std::copy_n(ring_A.begin() + static_cast<std::ptrdiff_t>(ring_head * valves), valves,
                  commanded_A.begin());
      ring_head = (ring_head + 1) % kDelaySlots;
      --ring_count;
    }
  }

  // A valve's last gap-field solve: its inputs (the eddy-lagged current and the steel's play
  // before it) and its output play. The solve is a pure function of those two inputs, so a valve
  // whose inputs have the same bits keeps its yield stress without solving the magnetic circuit
  // again: the coils of untouched cells settle to a fixed point within tens of substeps, and the
  // solve was most of a large grid's idle substep (palm-64x64: about two thirds).
  struct SolvedField {
    std::uint64_t current_bits = std::bit_cast<std::uint64_t>(std::numeric_limits<double>::quiet_NaN());
    std::uint64_t play_in_bits = 0;
    double play_out_A_per_m = 0.0;
  };

  NetworkPlantOptions options;
  model::DeviceModel truth;  // perturbed: the plant's reference physics
  model::NetworkSimulation network;
  model::MagneticCircuitParams magnetic;
  std::mt19937_64 rng;
  std::normal_distribution<double> normal{0.0, 1.0};
  std::vector<double> valve_gain;
  std::vector<model::CoilState> coil;
  std::vector<model::HysteresisState> hysteresis;
  std::vector<double> commanded_A;  // at the coil drivers (after the bus delay)
  std::vector<double> yield_Pa;
  std::vector<SolvedField> solved;
  std::vector<double> coil_A;
  std::vector<double> ring_A;
  std::vector<double> ring_time_s;
  std::size_t ring_head = 0;
  std::size_t ring_count = 0;
  std::vector<double> sensor_value;
  std::vector<double> sensor_noisy;
  std::vector<double> noise_std;
  std::vector<double> resolution;
  double time_s = 0.0;
  std::uint64_t failed = 0;
  std::uint64_t field_solves = 0;
};

NetworkPlant::NetworkPlant(const model::DeviceProfile& nominal, const NetworkPlantOptions& options)
    : impl_(std::make_unique<Impl>(nominal, options)) {}

NetworkPlant::~NetworkPlant() = default;

std::size_t NetworkPlant::sensor_count() const noexcept { return impl_->sensor_value.size(); }

void NetworkPlant::set_valve_currents(std::span<const double> current_A) noexcept {
  Impl& m = *impl_;
  const std::size_t valves = m.commanded_A.size();
  if (current_A.size() != valves) {
    return;
  }
  if (m.ring_count == kDelaySlots) {  // more commands in flight than slots: the oldest applies now
    std::copy_n(m.ring_A.begin() + static_cast<std::ptrdiff_t>(m.ring_head * valves), valves,
                m.commanded_A.begin());
    m.ring_head = (m.ring_head + 1) % kDelaySlots;
    --m.ring_count;
  }
  const std::size_t slot = (m.ring_head + m.ring_count) % kDelaySlots;
  const double max_A = m.truth.profile().coil.max_current_A;
  for (std::size_t v = 0; v < valves; ++v) {
    const double i = current_A[v];
    // Negative: a bipolar driver reversing the field (the mock's degauss); hosts send 0..max.
    m.ring_A[slot * valves + v] = std::isfinite(i) ? std::clamp(i, -max_A, max_A) : 0.0;
  }
  m.ring_time_s[slot] = m.time_s + m.options.command_delay_s;
  ++m.ring_count;
}

void NetworkPlant::set_finger_indentation(std::span<const double> indentation_m) noexcept {
  // A bad span is refused by the network, which keeps the previous depths.
  (void)impl_->network.set_cell_indentation_m(indentation_m);
}

void NetworkPlant::step(double dt_s) noexcept {
  Impl& m = *impl_;
  m.time_s += dt_s;
  m.release_due_commands();
  const model::CoilParams& coil_params = m.truth.profile().coil;
  const model::FluidParams& fluid = m.truth.profile().fluid;
  for (std::size_t v = 0; v < m.coil.size(); ++v) {
    const model::Result<model::CoilState> next =
        model::coil_step(coil_params, m.coil[v], m.commanded_A[v], dt_s);
    if (next.ok()) {
      m.coil[v] = next.value;
    }
    m.coil_A[v] = m.coil[v].current_A;
    Impl::SolvedField& last = m.solved[v];
    const auto current_bits = std::bit_cast<std::uint64_t>(m.coil[v].field_current_A);
    const auto play_bits = std::bit_cast<std::uint64_t>(m.hysteresis[v].play_A_per_m);
    if (m.options.reuse_settled_fields && current_bits == last.current_bits &&
        play_bits == last.play_in_bits) {
      m.hysteresis[v].play_A_per_m = last.play_out_A_per_m;  // the solve would give these bits
      continue;
    }
    const model::Result<model::GapField> field =
        model::gap_field_hysteretic(m.magnetic, fluid, m.coil[v].field_current_A, m.hysteresis[v]);
    ++m.field_solves;
    if (field.ok()) {
      m.yield_Pa[v] = field.value.yield_stress_Pa * m.valve_gain[v];
      last = {current_bits, play_bits, m.hysteresis[v].play_A_per_m};
    } else {
      last = Impl::SolvedField{};  // a failed solve kept the last yield; try again next substep
    }
  }
  (void)m.network.set_valve_yield_stress_Pa(m.yield_Pa);
  const model::Result<model::StepReport> r = m.network.step(dt_s);
  if (!r.ok()) {
    ++m.failed;
  }
  m.network.read_sensors(m.sensor_value);
  for (std::size_t i = 0; i < m.sensor_value.size(); ++i) {
    double y = m.sensor_value[i] + m.noise_std[i] * m.normal(m.rng);
    if (m.options.quantise_sensors && m.resolution[i] > 0.0) {
      y = std::round(y / m.resolution[i]) * m.resolution[i];
    }
    m.sensor_noisy[i] = y;
  }
}

void NetworkPlant::read_sensors(std::span<double> out) const noexcept {
  const std::size_t n = std::min(out.size(), impl_->sensor_noisy.size());
  std::copy_n(impl_->sensor_noisy.begin(), n, out.begin());
}

void NetworkPlant::contact_forces(std::span<double> out_N) const noexcept {
  const std::span<const double> f = impl_->network.cell_force_N();
  const std::size_t n = std::min(out_N.size(), f.size());
  std::copy_n(f.begin(), n, out_N.begin());
}

const model::NetworkSimulation& NetworkPlant::network() const noexcept { return impl_->network; }
std::span<const double> NetworkPlant::valve_yield_stress_Pa() const noexcept { return impl_->yield_Pa; }
std::span<const double> NetworkPlant::coil_current_A() const noexcept { return impl_->coil_A; }
std::uint64_t NetworkPlant::failed_steps() const noexcept { return impl_->failed; }
std::uint64_t NetworkPlant::gap_field_solves() const noexcept { return impl_->field_solves; }
const model::DeviceProfile& NetworkPlant::true_profile() const noexcept { return impl_->truth.profile(); }
std::span<const double> NetworkPlant::valve_yield_gain() const noexcept { return impl_->valve_gain; }

}  // namespace mrskin::sim
