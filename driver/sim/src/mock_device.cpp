#include "mrskin/sim/mock_device.hpp"

#include <fmt/format.h>
#include <pthread.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <limits>
#include <set>
#include <sstream>
#include <string>

#include "mock_device_impl.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/model/calibration.hpp"
#include "mrskin/protocol/bus_budget.hpp"
#include "mrskin/protocol/packed_report.hpp"
#include "mrskin/protocol/packet.hpp"
#include "mrskin/protocol/units.hpp"
#include "mrskin/sim/network_plant.hpp"

namespace mrskin::sim {
namespace proto = mrskin::protocol;

namespace {

constexpr std::size_t kDelayLineCapacity = 4096;
constexpr std::size_t kAnswerReserve = 64;  // device->host slots telemetry may not take
constexpr std::size_t kStatusPacketBytes = proto::kPacketHeaderBytes + 5 + proto::kPacketCrcBytes;

std::uint64_t splitmix(std::uint64_t& s) noexcept {
  std::uint64_t z = (s += 0x9E3779B97F4A7C15ULL);
  z = (z ^ (z >> 30U)) * 0xBF58476D1CE4E5B9ULL;
  z = (z ^ (z >> 27U)) * 0x94D049BB133111EBULL;
  return z ^ (z >> 31U);
}
double unit_random(std::uint64_t& s) noexcept { return static_cast<double>(splitmix(s) >> 11U) * 0x1.0p-53; }
// Standard normal by Box-Muller; deterministic for a seed.
double gaussian(std::uint64_t& s) noexcept {
  const double u1 = (static_cast<double>(splitmix(s) >> 11U) + 1.0) * 0x1.0p-53;
  const double u2 = unit_random(s);
  return std::sqrt(-2.0 * std::log(u1)) * std::cos(6.283185307179586 * u2);
}

std::vector<std::uint8_t> to_bytes(const std::string& text) { return {text.begin(), text.end()}; }

}  // namespace

bool MockFaults::any() const noexcept {
  return drop_probability > 0.0 || duplicate_probability > 0.0 || corrupt_probability > 0.0 ||
         reorder_probability > 0.0 || delay_s > 0.0 || disconnect_at_s >= 0.0 || stuck_sensor >= 0 ||
         noisy_sensor >= 0 || offset_sensor >= 0 || overheat_valve >= 0 || bus_off_at_s >= 0.0 ||
         leak_valve >= 0;
}

// Host end of the in-process link: pushes into the device's queue, pops from the host's.
class MockDevice::Impl::HostTransport final : public Transport {
 public:
  HostTransport(Impl& device, bool synchronous) : device_(device), synchronous_(synchronous) {}
  ResultCode send(std::span<const std::uint8_t> bytes) noexcept override {
    if (!device_.link_up_.load(std::memory_order_acquire)) {
      return ResultCode::disconnected;
    }
    if (bytes.size() > kMaxDatagramBytes) {
      return ResultCode::invalid_value;
    }
    HostDatagram d;
    std::copy(bytes.begin(), bytes.end(), d.datagram.bytes.begin());
    d.datagram.length = static_cast<std::uint16_t>(bytes.size());
    // On the bus from when the host sent it, not from the unit's next step: there a packet that
    // travels (classic CAN's frames) arrived a whole step late, and a threaded unit that woke late
    // took a burst of reports at once (docs/protocol.md, "When a packet enters the bus").
    if (synchronous_) {
      d.sent = sync_now();
    } else if (device_.sync_clock_ != nullptr) {
      d.sent = device_.sync_clock_->now();
    }
    return device_.to_device_.try_push(d) ? ResultCode::ok : ResultCode::would_block;
  }
  ResultCode receive(Datagram& out) noexcept override {
    if (!device_.link_up_.load(std::memory_order_acquire)) {
      return ResultCode::disconnected;
    }
    if (synchronous_) {
      const TimePoint now = sync_now();
      device_.handle_host_input(now);
      if (device_.options_.bus.kind == MockBusKind::hid_fs ||
          device_.options_.bus.kind == MockBusKind::hid_hs) {
        // A host blocked in a setup call (a configuration read) steps no unit: the reports its
        // answers queued for their slots still go as the frames pass.
        device_.bus_.advance(now, device_.sink_);
      }
      device_.flush_delayed(now);
    }
    return device_.to_host_.try_pop(out) ? ResultCode::ok : ResultCode::would_block;
  }
  [[nodiscard]] TransportState state() const noexcept override {
    return device_.link_up_.load(std::memory_order_acquire) ? TransportState::open
                                                            : TransportState::disconnected;
  }
  [[nodiscard]] std::string_view uri() const noexcept override { return "mock://"; }
  [[nodiscard]] std::optional<protocol::BusSpec> bus() const noexcept override {
    return bus_spec_of(device_.options_.bus);
  }

 private:
  // The host's clock, never behind the unit's.
  [[nodiscard]] TimePoint sync_now() const noexcept {
    return device_.sync_clock_ != nullptr ? std::max(device_.sync_clock_->now(), device_.last_step_)
                                          : device_.last_step_;
  }
  Impl& device_;
  bool synchronous_;
};

MockDevice::Impl::Impl(const model::DeviceProfile& profile, std::string_view profile_text,
                       const MockOptions& options, std::unique_ptr<Plant> plant)
    : profile_(profile),
      layout_(profile.rows, profile.cols),
      options_(options),
      max_current_A_(profile.coil.max_current_A),
      current_lsb_A_(profile.coil.current_resolution_A),
      coil_resistance_ohm_(profile.coil.resistance_ohm),
      seeder_(profile),
      targets_held_(layout_.fluid_cell_count()),
      plant_(std::move(plant)),
      bus_(options.bus),
      commanded_A_(layout_.valve_count(), 0.0),
      coil_A_(layout_.valve_count(), 0.0),
      plant_A_(layout_.valve_count(), 0.0),
      coil_C_(layout_.valve_count(), options.ambient_C),
      delay_line_(kDelayLineCapacity),
      fault_rng_(options.seed ^ 0x5EEDFA017ULL),
      finger_m_(layout_.fluid_cell_count()),
      truth_N_(layout_.fluid_cell_count()),
      applied_A_(layout_.valve_count()),
      scratch_(std::max(layout_.fluid_cell_count(), layout_.valve_count()), 0.0),
      noise_state_(options.seed ^ 0xA5A5A5A5ULL) {
  const std::string& name = profile.name;
  if (!plant_) {
    throw InvalidArgument("mock device for profile " + name + " needs a plant");
  }
  if (plant_->sensor_count() != profile.sensors.size()) {
    throw InvalidArgument(fmt::format("profile {} declares {} sensors but the plant has {}", name,
                                      profile.sensors.size(), plant_->sensor_count()));
  }
  // A fault on a sensor or valve the unit does not have would silently do nothing.
  const MockFaults& faults = options.faults;
  const auto unit_has = [&](int index, std::size_t count, const char* fault, const char* what) {
    if (index >= 0 && static_cast<std::size_t>(index) >= count) {
      throw InvalidArgument(fmt::format("mock:// fault '{}:{}': profile {} has {} {}s (0 to {})", fault,
                                        index, name, count, what, count == 0 ? 0 : count - 1));
    }
  };
  unit_has(faults.stuck_sensor, profile.sensors.size(), "stuck", "sensor");
  unit_has(faults.noisy_sensor, profile.sensors.size(), "noisy", "sensor");
  unit_has(faults.offset_sensor, profile.sensors.size(), "offset", "sensor");
  unit_has(faults.overheat_valve, layout_.valve_count(), "overheat", "valve");
  unit_has(faults.leak_valve, layout_.valve_count(), "leak", "valve");
  const double counts = max_current_A_ / current_lsb_A_;
  if (!(current_lsb_A_ >= 1e-9) || !(counts >= 1.0) || counts > proto::kCurrentCountMax + 0.5) {
    throw InvalidArgument(fmt::format(
        "profile {}: [coil] max_current_A = {} A in steps of current_resolution_A = {} A is {:.0f} counts; "
        "protocol v1 carries 1..{} counts of at least 1 nA: coarsen the resolution or lower the maximum",
        name, max_current_A_, current_lsb_A_, counts, proto::kCurrentCountMax));
  }
  const model::SensorSpec& first = profile.sensors.front();
  for (const model::SensorSpec& s : profile.sensors) {
    if (s.quantity != first.quantity ||
        std::abs(s.resolution - first.resolution) > 1e-12 * first.resolution) {
      throw InvalidArgument(
          fmt::format("profile {}: its sensors differ in quantity or resolution ({} in {} vs {} in {}); "
                      "protocol v1's Identity "
                      "declares one quantity and resolution for all sensors: give them one",
                      name, model::to_string(first.quantity), first.resolution, model::to_string(s.quantity),
                      s.resolution));
    }
  }
  sensor_lsb_ = first.resolution;
  if (!(sensor_lsb_ >= 1e-9 && sensor_lsb_ <= 4.0)) {
    throw InvalidArgument(
        fmt::format("profile {}: sensor resolution {} {} is outside what protocol v1 carries "
                    "(1e-9 .. 4 of the SI unit)",
                    name, sensor_lsb_, model::unit_of(first.quantity)));
  }
  for (const model::SensorSpec& s : profile.sensors) {
    sensor_noise_.push_back(s.noise_std * options.sensor_noise_scale);
  }
  stuck_value_.assign(plant_->sensor_count(), 0.0);
  sensor_si_.assign(plant_->sensor_count(), 0.0);
  config_bytes_beside_telemetry_ =
      proto::config_bytes_beside_telemetry(sensor_si_.size(), proto::kHidReportBytes);
  reported_.assign(plant_->sensor_count(), 0.0);
  block_sent_counts_.assign(plant_->sensor_count(), kNoBlockSent);
  if (options.sensor_deadband_counts < -1 ||
      options.sensor_deadband_counts > proto::kSensorDeadbandMaxCounts) {
    throw InvalidArgument(
        fmt::format("mock device: sensor deadband {} counts is outside 0..{} (-1: the bus's default)",
                    options.sensor_deadband_counts, proto::kSensorDeadbandMaxCounts));
  }
  sensor_deadband_counts_ = options.sensor_deadband_counts >= 0    ? options.sensor_deadband_counts
                            : options.bus.kind == MockBusKind::can ? kClassicCanSensorDeadbandCounts
                                                                   : 0;
  sample_counts_.assign(plant_->sensor_count(), 0);
  for (auto& f : finger_m_) {
    f.store(0.0);
  }
  for (auto& t : truth_N_) {
    t.store(0.0);
  }
  for (auto& a : applied_A_) {
    a.store(0.0);
  }
  // What a factory writes: a versioned calibration and the profile the unit was built to.
  calibration_blob_ =
      to_bytes("# mrskin calibration\nversion = " + std::to_string(options.calibration_version) +
               "\nserial = " + std::to_string(options.serial) + "\nprofile = \"" + name +
               "\"\nvalve_yield_gain = 1.0\n");
  calibration_blob_.reserve(kConfigCapacity);
  calibration_pending_.reserve(kConfigCapacity);
  if (profile_text.size() > 0xFFFF) {
    throw InvalidArgument(fmt::format("profile {} is {} bytes; the configuration memory holds at most 65535",
                                      name, profile_text.size()));
  }
  profile_blob_.assign(profile_text.begin(), profile_text.end());
  // A unit without displacement sensors (force sensors only) holds targets but cannot render
  // them: its observer has nothing to estimate the cells' depths from.
  const bool has_displacement = std::any_of(
      profile_.sensors.begin(), profile_.sensors.end(),
      [](const model::SensorSpec& s) { return s.quantity == model::SensorQuantity::displacement; });
  if (has_displacement) {
    render_model_ = std::make_unique<model::DeviceModel>(profile_);
    render_observer_ = std::make_unique<model::CellObserver>(*render_model_, model::ObserverOptions{});
    render_inverse_ = std::make_unique<model::CellInverse>(*render_model_);
  }
  render_targets_.assign(layout_.fluid_cell_count(), model::CellImpedanceTarget{});
  render_states_.assign(layout_.fluid_cell_count(), model::CellState{});
}

MockDevice::MockDevice(const model::DeviceProfile& profile, std::string_view profile_text,
                       const MockOptions& options, std::unique_ptr<Plant> plant)
    : impl_(std::make_unique<Impl>(profile, profile_text, options, std::move(plant))) {}

std::shared_ptr<MockDevice> MockDevice::make(const MockOptions& options, const model::LoadedProfile& loaded) {
  NetworkPlantOptions plant_options;
  plant_options.perturbation = options.perturbation;
  plant_options.seed = options.seed;
  plant_options.substep_s = options.physics_dt_s;
  // The firmware adds the sensors' noise and quantisation itself (MockOptions).
  plant_options.sensor_noise_scale = 0.0;
  plant_options.quantise_sensors = false;
  auto plant = std::make_unique<NetworkPlant>(loaded.profile, plant_options);
  model::Calibration calibration;
  if (options.calibration_error >= 0.0) {
    calibration = model::measure_calibration(loaded.profile, plant->true_profile(), plant->valve_yield_gain(),
                                             options.calibration_error, options.seed ^ 0xCA11B8A7EULL);
  }
  calibration.version = options.calibration_version;
  calibration.serial = options.serial;
  calibration.profile = loaded.profile.name;
  auto device = std::make_shared<MockDevice>(loaded.profile, loaded.text, options, std::move(plant));
  device->impl_->calibration_blob_ = to_bytes(model::format_calibration(calibration));
  device->impl_->calibration_blob_.reserve(Impl::kConfigCapacity);
  return device;
}

std::shared_ptr<MockDevice> MockDevice::make(const MockOptions& options,
                                             std::string_view profile_name_or_path) {
  return make(options, model::load_profile_with_text(profile_name_or_path));
}

MockDevice::Impl::~Impl() { stop(); }

MockDevice::~MockDevice() = default;

std::unique_ptr<Transport> MockDevice::connect(bool synchronous, const Clock* clock) {
  impl_->synchronous_.store(synchronous, std::memory_order_release);
  impl_->sync_clock_ = clock;
  return std::make_unique<Impl::HostTransport>(*impl_, synchronous);
}

void MockDevice::step(TimePoint now) noexcept { impl_->step(now); }
void MockDevice::start(Clock& clock) { impl_->start(clock); }
void MockDevice::stop() noexcept { impl_->stop(); }
void MockDevice::set_link_up(bool up) noexcept { impl_->set_link_up(up); }

const GridLayout& MockDevice::layout() const noexcept { return impl_->layout_; }
const model::DeviceProfile& MockDevice::profile() const noexcept { return impl_->profile_; }
std::uint8_t MockDevice::state() const noexcept { return impl_->state_.load(std::memory_order_acquire); }
std::uint8_t MockDevice::fault() const noexcept { return impl_->fault_.load(std::memory_order_acquire); }
bool MockDevice::link_up() const noexcept { return impl_->link_up_.load(std::memory_order_acquire); }
double MockDevice::skipped_time_s() const noexcept {
  return static_cast<double>(impl_->skipped_ns_.load(std::memory_order_relaxed)) * 1e-9;
}
double MockDevice::max_coil_temperature_C() const noexcept {
  return impl_->max_coil_C_.load(std::memory_order_relaxed);
}
bool MockDevice::rendering_targets() const noexcept { return impl_->rendering_targets_; }
std::span<const double> MockDevice::commanded_currents() const noexcept { return impl_->commanded_A_; }

MockDevice::HeldTarget MockDevice::held_target(std::size_t cell) const noexcept {
  const std::vector<HeldTarget>& held = impl_->targets_held_;
  return cell < held.size() ? held[cell] : HeldTarget{};
}

MockBusStats MockDevice::bus_stats() const noexcept { return impl_->bus_.stats(); }
void MockDevice::restart_bus_max_wait() noexcept { impl_->bus_.restart_max_wait(); }

MockDevice::FaultCounters MockDevice::fault_counters() const noexcept {
  const Impl& m = *impl_;
  return {m.dropped_.value(), m.duplicated_.value(), m.corrupted_.value(), m.reordered_.value(),
          m.congested_.value()};
}

void MockDevice::finger_indentation(std::span<double> out_m) const noexcept {
  const auto& finger_m = impl_->finger_m_;
  const std::size_t n = std::min(out_m.size(), finger_m.size());
  for (std::size_t i = 0; i < n; ++i) {
    out_m[i] = finger_m[i].load(std::memory_order_relaxed);
  }
}

void MockDevice::set_finger_indentation(std::span<const double> indentation_m) noexcept {
  auto& finger_m = impl_->finger_m_;
  const std::size_t n = std::min(indentation_m.size(), finger_m.size());
  for (std::size_t i = 0; i < n; ++i) {
    finger_m[i].store(indentation_m[i], std::memory_order_relaxed);
  }
}

void MockDevice::true_contact_forces(std::span<double> out_N) const noexcept {
  const auto& truth_N = impl_->truth_N_;
  const std::size_t n = std::min(out_N.size(), truth_N.size());
  for (std::size_t i = 0; i < n; ++i) {
    out_N[i] = truth_N[i].load(std::memory_order_relaxed);
  }
}

void MockDevice::applied_currents(std::span<double> out_A) const noexcept {
  const auto& applied_A = impl_->applied_A_;
  const std::size_t n = std::min(out_A.size(), applied_A.size());
  for (std::size_t i = 0; i < n; ++i) {
    out_A[i] = applied_A[i].load(std::memory_order_relaxed);
  }
}

static_assert(sizeof(MockDevice) == sizeof(SimulatedUnit) + sizeof(void*),
              "MockDevice is its base and one pointer: its state lives in MockDevice::Impl");

void MockDevice::Impl::start(Clock& clock) {
  if (running_.exchange(true)) {
    return;
  }
  thread_ = std::thread([this, &clock] {
    (void)::pthread_setname_np(::pthread_self(), "mrskin-mock");
    // Ten substeps a wake, but at least one telemetry packet: a coarse plant step must not batch them.
    const Duration period = from_seconds(std::min(options_.physics_dt_s * 10.0, options_.telemetry_period_s));
    TimePoint next = clock.now();
    while (running_.load(std::memory_order_acquire)) {
      step(clock.now());
      next += period;
      clock.sleep_until(next);
    }
  });
}

void MockDevice::Impl::stop() noexcept {
  if (running_.exchange(false) && thread_.joinable()) {
    thread_.join();
  }
}

void MockDevice::Impl::set_link_up(bool up) noexcept {
  const bool was = link_up_.exchange(up, std::memory_order_acq_rel);
  if (up && !was) {
    // A re-plugged unit boots: DISABLED, valves released, nothing queued.
    state_.store(static_cast<std::uint8_t>(proto::DeviceState::disabled));
    fault_.store(0);
  }
}

bool MockDevice::Impl::chance(double probability) noexcept {
  return probability > 0.0 && unit_random(fault_rng_) < probability;
}

void MockDevice::Impl::emit(const Datagram& d, TimePoint now) noexcept {
  const MockFaults& f = options_.faults;
  if (chance(f.drop_probability)) {
    dropped_.bump();
    return;
  }
  Datagram out = d;
  if (chance(f.corrupt_probability) && out.length > 0) {
    const std::uint64_t bit = splitmix(fault_rng_) % (static_cast<std::uint64_t>(out.length) * 8U);
    out.bytes[bit / 8U] = static_cast<std::uint8_t>(out.bytes[bit / 8U] ^ (1U << (bit % 8U)));
    corrupted_.bump();
  }
  const int copies = chance(f.duplicate_probability) ? 2 : 1;
  if (copies == 2) {
    duplicated_.bump();
  }
  for (int c = 0; c < copies; ++c) {
    if (!holding_ && chance(f.reorder_probability)) {
      held_ = out;  // goes out after the next datagram
      holding_ = true;
      reordered_.bump();
      continue;
    }
    for (int k = 0; k < (holding_ ? 2 : 1); ++k) {
      bus_.device_sent(k == 0 ? out : held_, now, sink_);
    }
    holding_ = false;
  }
  flush_delayed(now);
}

void MockDevice::Impl::deliver_to_host(const Datagram& d, TimePoint at) noexcept {
  if (delay_count_ == delay_line_.size()) {
    dropped_.bump();  // line full: a bus would lose it too
    return;
  }
  Delayed& slot = delay_line_[(delay_head_ + delay_count_) % delay_line_.size()];
  // A lagging unit heard the host at its own, earlier, time: the injected delay still runs from
  // the real time it answers, or a round trip would look shorter than the delay.
  const bool delayed = options_.faults.delay_s > 0.0;
  slot.due = (lagging_ && delayed ? std::max(at, step_now_) : at) + from_seconds(options_.faults.delay_s);
  slot.datagram = d;
  ++delay_count_;
}

void MockDevice::Impl::flush_delayed(TimePoint now) noexcept {
  while (delay_count_ > 0) {
    const Delayed& slot = delay_line_[delay_head_];
    if (slot.due > now) {
      break;
    }
    // The host is not reading fast enough: like a unit's transmit buffer, the link keeps room
    // for answers (identity, configuration, status, echoes) and drops telemetry first, whose
    // next sample supersedes it.
    const bool telemetry = slot.datagram.length > 1 &&
                           slot.datagram.bytes[1] == static_cast<std::uint8_t>(proto::MessageType::telemetry);
    const bool room = to_host_.size_approx() + (telemetry ? kAnswerReserve : 0) < to_host_.capacity();
    if (!room || !to_host_.try_push(slot.datagram)) {
      congested_.bump();
    }
    delay_head_ = (delay_head_ + 1) % delay_line_.size();
    --delay_count_;
  }
}

void MockDevice::Impl::send_message(const proto::Message& message, bool hold) noexcept {
  if (!link_up_.load(std::memory_order_acquire) || bus_off_until_ > last_step_) {
    return;
  }
  if (packing_) {
    const std::span<std::uint8_t> report = std::span<std::uint8_t>(report_.bytes).first(report_capacity_);
    proto::EncodeResult r = proto::append_packet(message, tx_sequence_, report, report_.length);
    if (r.error == proto::Error::short_buffer && report_.length > 0) {
      flush_report();  // full: this packet starts the next report
      r = proto::append_packet(message, tx_sequence_, report, report_.length);
    }
    if (r.error != proto::Error::ok) {
      return;
    }
    ++tx_sequence_;
    report_.length = static_cast<std::uint16_t>(report_.length + r.bytes);
    if (!hold) {
      flush_report();
    }
    return;
  }
  Datagram d;
  const auto r = proto::encode_packet(message, tx_sequence_, d.bytes);
  if (r.error != proto::Error::ok) {
    return;
  }
  ++tx_sequence_;
  d.length = static_cast<std::uint16_t>(r.bytes);
  emit(d, last_step_);
}

void MockDevice::Impl::flush_report() noexcept {
  if (report_.length == 0) {
    return;
  }
  const Datagram d = report_;
  report_.length = 0;
  held_status_at_ = kNoHeldStatus;
  if (!link_up_.load(std::memory_order_acquire) || bus_off_until_ > last_step_) {
    return;  // lost with the link, as a unit's transmit buffer would be
  }
  emit(d, last_step_);
}

void MockDevice::Impl::send_status() noexcept {
  proto::Status s;
  s.state = state_.load(std::memory_order_relaxed);
  s.fault = fault_.load(std::memory_order_relaxed);
  const bool released =
      std::all_of(commanded_A_.begin(), commanded_A_.end(), [](double a) { return a == 0.0; });
  unsigned flags = proto::kFlagCalibrated;
  if (released) {
    flags |= proto::kFlagValvesReleased;
  }
  if (derated_) {
    flags |= proto::kFlagDerated;
  }
  if (degaussing_) {
    flags |= proto::kFlagDegaussing;
  }
  s.flags = static_cast<std::uint8_t>(flags);
  if (wait_for_telemetry() && held_status_at_ != kNoHeldStatus) {
    // A newer snapshot supersedes the status still waiting for the telemetry report (same place
    // and sequence), so a burst of changes costs no extra report; a fault is never hidden.
    const std::span<std::uint8_t> held(report_.bytes.data() + held_status_at_, kStatusPacketBytes);
    const auto fault = static_cast<std::uint8_t>(proto::DeviceState::fault);
    if (held[proto::kPacketHeaderBytes] != fault || s.state == fault) {
      (void)proto::encode_packet(s, held[2], held);
      return;
    }
  }
  send_message(s, wait_for_telemetry());  // packed: it rides with the next telemetry report
  if (wait_for_telemetry() && report_.length >= kStatusPacketBytes) {
    held_status_at_ = report_.length - kStatusPacketBytes;
  }
}

void MockDevice::Impl::release_valves() noexcept {
  rendering_targets_ = false;
  degaussing_ = false;  // a fault, a disable or a lost host ends a degauss too
  std::fill(commanded_A_.begin(), commanded_A_.end(), 0.0);
  std::fill(coil_A_.begin(), coil_A_.end(), 0.0);  // the driver's fast-off path ignores slew
  plant_->set_valve_currents(coil_A_);
  for (auto& a : applied_A_) {
    a.store(0.0, std::memory_order_relaxed);
  }
}

void MockDevice::Impl::reseed(TimePoint now) noexcept {
  // The host's last currents and targets predate this enable: currents restart at zero and
  // each cell's target is re-seeded from the last reading sent (TargetSeeder), its validity
  // starting now.
  std::fill(commanded_A_.begin(), commanded_A_.end(), 0.0);
  rendering_targets_ = false;            // until the host commands again
  seeder_.fit_displacements(reported_);  // once for every cell
  for (std::size_t c = 0; c < targets_held_.size(); ++c) {
    targets_held_[c].target = seeder_.seed_from_fit(c, reported_, targets_held_[c].target.validity);
    targets_held_[c].validity_start = now;
  }
}

void MockDevice::Impl::render_targets(TimePoint now) noexcept {
  // The firmware's local impedance loop: what it reported to the host is all it measures.
  constexpr model::ContactThresholds kContact{};  // the bridge's defaults
  if (render_observer_->update(reported_, commanded_A_, options_.telemetry_period_s) != model::Status::ok) {
    return;  // the last currents stand
  }
  const std::span<const double> depth_m = render_observer_->indentation_m();
  const std::span<const double> rate_m_per_s = render_observer_->velocity_m_per_s();
  const std::span<const double> force_N = render_observer_->force_N();
  for (std::size_t c = 0; c < render_targets_.size(); ++c) {
    const proto::CellTarget& held = targets_held_[c].target;
    model::CellImpedanceTarget& t = render_targets_[c];
    t.stiffness_N_per_m = held.stiffness * proto::kStiffnessLsb_N_per_m;
    t.surface_offset_m = held.offset * proto::kOffsetLsb_m;
    t.force_ceiling_N = held.ceiling * proto::kCeilingLsb_N;
    t.valid_until_s =
        to_seconds(targets_held_[c].validity_start - start_) + held.validity * proto::kValidityLsb_s;
    const bool contact = kContact.touched(depth_m[c], force_N[c]);
    const double rate = std::abs(rate_m_per_s[c]) < kContact.hold_rate_m_per_s ? 0.0 : rate_m_per_s[c];
    render_states_[c].indentation_m = contact ? depth_m[c] : 0.0;
    render_states_[c].rate_m_per_s = contact ? rate : 0.0;
  }
  if (render_inverse_->solve(render_targets_, render_states_, to_seconds(now - start_)) ==
      model::Status::ok) {
    const std::span<const double> currents = render_inverse_->currents_A();
    for (std::size_t v = 0; v < commanded_A_.size(); ++v) {
      commanded_A_[v] = std::min(currents[v], max_current_A_);
    }
  }
}

void MockDevice::Impl::enter_fault(proto::FaultCode code) noexcept {
  state_.store(static_cast<std::uint8_t>(proto::DeviceState::fault));
  fault_.store(static_cast<std::uint8_t>(code));  // latched until an explicit enable
  release_valves();
  send_status();
  flush_report();  // a fault goes out at once, not with the next sample (bus-off may follow)
}

void MockDevice::Impl::handle_host_input(TimePoint now) noexcept { handle_host_input(now, now); }

void MockDevice::Impl::handle_host_input(TimePoint now, TimePoint advance_to) noexcept {
  HostDatagram d;
  while (to_device_.try_pop(d)) {
    // The host's send time, within what the bus has already run through (its clock never runs
    // back) and now.
    const TimePoint at =
        d.sent.count() != 0 ? std::clamp(d.sent, std::min(bus_.latest_time(), now), now) : now;
    if (lagging_) {
      bus_.host_sent_while_lagging(d.datagram, now, sink_);
    } else {
      bus_.host_sent(d.datagram, at, sink_);
    }
  }
  bus_.advance(advance_to, sink_);
}

void MockDevice::Impl::deliver_to_device(Datagram d, TimePoint at) noexcept {
  const MockFaults& f = options_.faults;
  if (bus_off_until_ > at) {
    return;  // bus-off: the node hears nothing
  }
  if (chance(f.drop_probability)) {
    dropped_.bump();
    return;
  }
  if (chance(f.corrupt_probability) && d.length > 0) {
    const std::uint64_t bit = splitmix(fault_rng_) % (static_cast<std::uint64_t>(d.length) * 8U);
    d.bytes[bit / 8U] = static_cast<std::uint8_t>(d.bytes[bit / 8U] ^ (1U << (bit % 8U)));
    corrupted_.bump();
  }
  handle(d.bytes.data(), d.length, at);
  if (chance(f.duplicate_probability)) {
    duplicated_.bump();
    handle(d.bytes.data(), d.length, at);
  }
}

void MockDevice::Impl::handle(const std::uint8_t* bytes, std::size_t length, TimePoint now) noexcept {
  const std::span<const std::uint8_t> report(bytes, length);
  if (!packing_) {
    handle_packet(proto::decode_first_packet(report), now);  // 1.1: the rest of a report is padding
    return;
  }
  proto::PacketWalker walker(report);
  proto::PacketDecoded p;
  while (walker.next(p)) {
    handle_packet(p, now);
  }
}

void MockDevice::Impl::handle_packet(const proto::PacketDecoded& p, TimePoint now) noexcept {
  if (p.error != proto::Error::ok) {
    return;  // a unit drops what it cannot parse; the host sees no answer
  }
  last_heartbeat_ = now;  // any valid packet proves the host is alive
  const auto state = static_cast<proto::DeviceState>(state_.load(std::memory_order_relaxed));
  if (const auto* request = std::get_if<proto::IdentifyRequest>(&p.message)) {
    answer_identify(*request);
  } else if (const auto* r = std::get_if<proto::StateRequest>(&p.message)) {
    if (degaussing_ && r->request != static_cast<std::uint8_t>(proto::StateRequestCode::degauss)) {
      release_valves();  // any other request ends the degauss first
    }
    switch (static_cast<proto::StateRequestCode>(r->request)) {
      case proto::StateRequestCode::degauss:
        // Disabled units with an H-bridge driver only; others answer with their status alone.
        if (options_.bipolar_driver && !degaussing_ &&
            state_.load() == static_cast<std::uint8_t>(proto::DeviceState::disabled)) {
          degaussing_ = true;
          degauss_elapsed_s_ = 0.0;
        }
        break;
      case proto::StateRequestCode::enable:
        if (std::any_of(coil_C_.begin(), coil_C_.end(), [this](double c) { return c >= options_.fault_C; })) {
          enter_fault(proto::FaultCode::overtemperature);  // too hot to enable: stays latched
          return;
        }
        state_.store(static_cast<std::uint8_t>(proto::DeviceState::enabled));
        fault_.store(0);
        reseed(now);  // no stale command survives an enable
        break;
      case proto::StateRequestCode::disable:
        state_.store(static_cast<std::uint8_t>(proto::DeviceState::disabled));
        release_valves();
        break;
      case proto::StateRequestCode::pause:
        state_.store(static_cast<std::uint8_t>(proto::DeviceState::paused));
        break;
      case proto::StateRequestCode::estop:
        enter_fault(proto::FaultCode::estop);
        return;
    }
    send_status();
  } else if (const auto* v = std::get_if<proto::ValveCurrents>(&p.message)) {
    if (state != proto::DeviceState::enabled) {
      return;  // only an enabled unit drives its coils
    }
    rendering_targets_ = false;  // the host drives the coils itself again
    for (std::size_t i = 0; i < v->count; ++i) {
      const std::size_t valve = v->first + i;
      if (valve < commanded_A_.size()) {
        commanded_A_[valve] = std::min(v->counts[i] * current_lsb_A_, max_current_A_);
      }
    }
  } else if (const auto* c = std::get_if<proto::CellTargets>(&p.message)) {
    if (state != proto::DeviceState::enabled) {
      return;  // as currents: only an enabled unit takes commands
    }
    for (std::size_t i = 0; i < c->count; ++i) {
      const std::size_t cell = c->first + i;
      if (cell < targets_held_.size()) {
        targets_held_[cell] = HeldTarget{c->targets[i], now};
      }
    }
    if (!rendering_targets_ && render_observer_ != nullptr) {
      render_observer_->reset();  // its depth and force history start with this command
      render_inverse_->invalidate();
      rendering_targets_ = true;
    }
  } else if (const auto* h = std::get_if<proto::Heartbeat>(&p.message)) {
    if (options_.bus.kind != MockBusKind::can) {  // classic CAN has no echo: it would cost a sequence number
      send_message(proto::Heartbeat{h->counter}, wait_for_telemetry());  // echo: the host times round trips
    }
  } else {
    handle_config(p.message);
  }
}

void MockDevice::Impl::update_coils(double dt_s) noexcept {
  const MockFaults& f = options_.faults;
  const double max_step_A = max_current_A_ * dt_s / options_.slew_time_s;
  const bool heating = f.overheat_for_s < 0.0 || to_seconds(last_step_ - start_) < f.overheat_for_s;
  double hottest = options_.ambient_C;
  bool derated = false;
  bool overheated = false;
  if (degaussing_) {
    // Half-cycle k holds (-1)^k max_current_A ratio^k; done once it is under half a count.
    const auto k = static_cast<int>(degauss_elapsed_s_ / options_.degauss_step_s);
    const double amplitude_A = max_current_A_ * std::pow(options_.degauss_ratio, k);
    degauss_elapsed_s_ += dt_s;
    if (amplitude_A < 0.5 * current_lsb_A_) {
      degaussing_ = false;
      std::fill(commanded_A_.begin(), commanded_A_.end(), 0.0);
      send_status();
    } else {
      std::fill(commanded_A_.begin(), commanded_A_.end(), k % 2 == 0 ? amplitude_A : -amplitude_A);
    }
  }
  for (std::size_t v = 0; v < coil_A_.size(); ++v) {
    // Current limit falls linearly from derate_start_C to zero at fault_C.
    const double t = coil_C_[v];
    const double limit_fraction =
        std::clamp((options_.fault_C - t) / (options_.fault_C - options_.derate_start_C), 0.0, 1.0);
    // Negative only while degaussing (the H-bridge reversed); the limit holds both ways.
    const double limit_A = max_current_A_ * limit_fraction;
    const double wanted = std::clamp(commanded_A_[v], -limit_A, limit_A);
    derated = derated || std::fabs(wanted) < std::fabs(commanded_A_[v]);
    coil_A_[v] += std::clamp(wanted - coil_A_[v], -max_step_A, max_step_A);
    const double extra_W = heating && static_cast<int>(v) == f.overheat_valve ? f.overheat_power_W : 0.0;
    const double heat_W = coil_resistance_ohm_ * coil_A_[v] * coil_A_[v] + extra_W -
                          (t - options_.ambient_C) / options_.coil_thermal_resistance_K_per_W;
    coil_C_[v] = t + dt_s * heat_W / options_.coil_heat_capacity_J_per_K;
    hottest = std::max(hottest, coil_C_[v]);
    overheated = overheated || coil_C_[v] >= options_.fault_C;
    plant_A_[v] = static_cast<int>(v) == f.leak_valve ? coil_A_[v] * f.leak_current_fraction : coil_A_[v];
  }
  plant_->set_valve_currents(plant_A_);
  for (std::size_t i = 0; i < coil_A_.size(); ++i) {
    applied_A_[i].store(coil_A_[i], std::memory_order_relaxed);
  }
  max_coil_C_.store(hottest, std::memory_order_relaxed);
  if (derated != derated_) {
    derated_ = derated;
    send_status();
  }
  if (overheated && state_.load() != static_cast<std::uint8_t>(proto::DeviceState::fault)) {
    enter_fault(proto::FaultCode::overtemperature);
  }
}

void MockDevice::Impl::emit_telemetry(TimePoint now) noexcept {
  if (packing_ && slots_taken_by_samples() && !bus_.device_slot_free(now)) {
    // As firmware does with a sample that finds its IN endpoint busy (an Identity or another
    // unit-made report took the slot): skipped, never numbered, so the host sees no gap. What
    // waits for a telemetry report (status, echoes, replies) waits for the next sample.
    return;
  }
  plant_->read_sensors(sensor_si_);
  const MockFaults& f = options_.faults;
  const auto time_us =
      static_cast<std::uint32_t>(static_cast<std::uint64_t>(now.count() / 1000) & 0xFFFFFFFFULL);
  for (std::size_t s = 0; s < sensor_si_.size(); ++s) {
    const double sigma =
        static_cast<int>(s) == f.noisy_sensor ? f.noisy_sensor_noise_lsb * sensor_lsb_ : sensor_noise_[s];
    double value = sensor_si_[s] + sigma * gaussian(noise_state_);
    if (static_cast<int>(s) == f.stuck_sensor) {
      value = stuck_value_[s];
    }
    if (static_cast<int>(s) == f.offset_sensor) {
      value += f.offset_sensor_lsb * sensor_lsb_;
    }
    const double counts = std::nearbyint(value / sensor_lsb_);
    sample_counts_[s] = static_cast<std::int16_t>(std::clamp(
        counts, static_cast<double>(proto::kSensorCountMin), static_cast<double>(proto::kSensorCountMax)));
  }
  apply_sensor_deadband();
  std::size_t first = 0;
  while (first < sensor_si_.size()) {
    proto::Telemetry t;
    t.device_time_us = time_us;
    t.first = static_cast<std::uint16_t>(first);
    t.count = static_cast<std::uint8_t>(std::min(proto::kMaxTelemetryValues, sensor_si_.size() - first));
    for (std::size_t i = 0; i < t.count; ++i) {
      t.counts[i] = sample_counts_[first + i];
      reported_[first + i] = static_cast<double>(t.counts[i]) * sensor_lsb_;
    }
    send_message(t, /*hold=*/true);
    first += t.count;
  }
  if (config_replies_ride_telemetry()) {
    append_pending_config_replies();
  }
  flush_report();  // with what waited for it: status, heartbeat echoes, configuration replies
}

void MockDevice::Impl::apply_sensor_deadband() noexcept {
  const int band = sensor_deadband_counts_;
  if (band <= 0 || !packing_) {  // declared to a 1.2 host only, and only then applied
    return;
  }
  constexpr std::size_t kBlock = proto::kCanValuesPerBlock;
  for (std::size_t first = 0; first < sample_counts_.size(); first += kBlock) {
    const std::size_t end = std::min(first + kBlock, sample_counts_.size());
    bool inside = true;
    for (std::size_t s = first; s < end; ++s) {
      inside = inside && std::abs(sample_counts_[s] - block_sent_counts_[s]) <= band;
    }
    const auto b = static_cast<std::ptrdiff_t>(first);
    const auto e = static_cast<std::ptrdiff_t>(end);
    if (inside) {
      std::copy(block_sent_counts_.begin() + b, block_sent_counts_.begin() + e, sample_counts_.begin() + b);
    } else {
      std::copy(sample_counts_.begin() + b, sample_counts_.begin() + e, block_sent_counts_.begin() + b);
    }
  }
}

void MockDevice::Impl::apply_link_faults(TimePoint now) noexcept {
  const MockFaults& f = options_.faults;
  const double t_s = to_seconds(now - start_);
  if (f.disconnect_at_s >= 0.0 && !disconnect_done_ && t_s >= f.disconnect_at_s) {
    if (link_up_.load() && t_s < f.disconnect_at_s + f.disconnect_for_s) {
      set_link_up(false);
    } else if (!link_up_.load() && t_s >= f.disconnect_at_s + f.disconnect_for_s) {
      set_link_up(true);
      release_valves();
      disconnect_done_ = true;
    }
  }
  if (f.bus_off_at_s >= 0.0 && !bus_off_done_ && t_s >= f.bus_off_at_s) {
    bus_off_done_ = true;
    enter_fault(proto::FaultCode::bus_off);
    bus_off_until_ = now + from_seconds(f.bus_off_for_s);
  }
}

void MockDevice::Impl::step(TimePoint now) noexcept {
  if (!started_) {
    started_ = true;
    start_ = now;
    last_step_ = now;
    last_heartbeat_ = now;
    next_telemetry_ = now;
    next_status_ = now;
    plant_->read_sensors(stuck_value_);
    bus_.start(now);
  }
  apply_link_faults(now);
  if (!link_up_.load(std::memory_order_acquire)) {
    HostDatagram drain;
    while (to_device_.try_pop(drain)) {
    }
    bus_.reset();
    packing_ = false;  // a unit that boots again packs only after the next IdentifyRequest
    report_capacity_ = proto::kHidReportBytes;
    pending_read_count_ = 0;
    report_.length = 0;
    held_status_at_ = kNoHeldStatus;
    last_step_ = now;
    last_heartbeat_ = now;
    return;
  }
  // A unit that lags real time (a big plant on a loaded machine) hears what the host queued
  // meanwhile at its own time, outside the bus: on the bus it would wait until the unit had
  // simulated up to the host's clock (palm-64x64 on hid-hs: up to max_catch_up_s of plant a
  // request, past the session's 0.5 s without progress; issue 20), and a burst of a period's
  // reports would overflow the bus's queue. What the bus delivers later reaches the unit within the
  // substeps below. Lagging is more than two telemetry periods behind: a wake a period late, not a
  // threaded unit's usual 1-1.3 periods after its last substep (at one period the 5x5 daemon's
  // currents went outside the bus, its host-to-device load 0.2-5 % instead of 27 %).
  lagging_ = now - last_step_ > 2 * from_seconds(options_.telemetry_period_s);
  step_now_ = now;
  handle_host_input(lagging_ ? last_step_ : now, last_step_);
  const auto state = static_cast<proto::DeviceState>(state_.load(std::memory_order_relaxed));
  // The watchdog runs on the unit's own clock (last_step_), the one its packets are stamped with:
  // behind real time, the unit hears the host at its substeps' times, and now - last_heartbeat_
  // would count the unit's own lag as the host's silence (issue 21).
  if (state == proto::DeviceState::enabled &&
      to_seconds(last_step_ - last_heartbeat_) > options_.heartbeat_timeout_s * options_.time_scale) {
    enter_fault(proto::FaultCode::heartbeat_lost);
  }
  for (std::size_t i = 0; i < finger_m_.size(); ++i) {
    scratch_[i] = finger_m_[i].load(std::memory_order_relaxed);
  }
  plant_->set_finger_indentation(std::span<const double>(scratch_.data(), finger_m_.size()));
  const Duration dt = from_seconds(options_.physics_dt_s);
  const Duration max_behind = from_seconds(options_.max_catch_up_s);
  if (now - last_step_ > max_behind) {
    // Too slow for real time (an overloaded or sanitised build): skip whole substeps rather
    // than spiral, so the unit keeps answering; telemetry resumes at the new time.
    const auto substeps = (now - max_behind - last_step_) / dt;
    if (last_heartbeat_ < last_step_) {
      last_heartbeat_ += substeps * dt;  // time the unit skips is no silence it heard
    }
    last_step_ += substeps * dt;
    skipped_ns_.fetch_add((substeps * dt).count(), std::memory_order_relaxed);
    const Duration period = from_seconds(options_.telemetry_period_s);
    if (next_telemetry_ < last_step_) {
      next_telemetry_ += ((last_step_ - next_telemetry_) / period + 1) * period;
    }
    if (next_status_ + from_seconds(options_.status_period_s) < now) {
      next_status_ = now;
    }
  }
  while (last_step_ + dt <= now) {
    bus_.advance(last_step_, sink_);
    update_coils(options_.physics_dt_s);
    plant_->step(options_.physics_dt_s);
    last_step_ += dt;
    if (last_step_ >= next_telemetry_) {
      emit_telemetry(last_step_);
      if (rendering_targets_ &&
          state_.load(std::memory_order_relaxed) == static_cast<std::uint8_t>(proto::DeviceState::enabled)) {
        render_targets(last_step_);
      }
      next_telemetry_ += from_seconds(options_.telemetry_period_s);
      handle_host_input(last_step_);  // a long catch-up still answers within a period
    } else if (lagging_) {
      handle_host_input(last_step_);  // and within a substep, when it lags (a slow plant's substeps)
    }
  }
  plant_->contact_forces(std::span<double>(scratch_.data(), truth_N_.size()));
  for (std::size_t i = 0; i < truth_N_.size(); ++i) {
    truth_N_[i].store(scratch_[i], std::memory_order_relaxed);
  }
  if (now >= next_status_) {
    send_status();
    next_status_ += from_seconds(options_.status_period_s);
  }
  lagging_ = false;
  bus_.advance(now, sink_);
  flush_delayed(now);
}

}  // namespace mrskin::sim
