#include "mrskin/driver/mock_device.hpp"

#include <algorithm>
#include <cmath>

#include "mrskin/protocol/packet.hpp"
#include "mrskin/protocol/units.hpp"

namespace mrskin {
namespace proto = mrskin::protocol;

namespace {

constexpr std::uint8_t kFirmwareMajor = 0;
constexpr std::uint8_t kFirmwareMinor = 1;
constexpr std::uint8_t kFirmwarePatch = 0;

std::uint64_t splitmix(std::uint64_t& s) noexcept {
  std::uint64_t z = (s += 0x9E3779B97F4A7C15ULL);
  z = (z ^ (z >> 30U)) * 0xBF58476D1CE4E5B9ULL;
  z = (z ^ (z >> 27U)) * 0x94D049BB133111EBULL;
  return z ^ (z >> 31U);
}
// Standard normal by Box-Muller; deterministic for a seed.
double gaussian(std::uint64_t& s) noexcept {
  const double u1 = (static_cast<double>(splitmix(s) >> 11U) + 1.0) * 0x1.0p-53;
  const double u2 = static_cast<double>(splitmix(s) >> 11U) * 0x1.0p-53;
  return std::sqrt(-2.0 * std::log(u1)) * std::cos(6.283185307179586 * u2);
}

}  // namespace

// Host end of the in-process link: pushes into the device's queue, pops from the host's.
class MockDevice::HostTransport final : public Transport {
 public:
  HostTransport(MockDevice& device, bool synchronous) : device_(device), synchronous_(synchronous) {}
  ResultCode send(std::span<const std::uint8_t> bytes) noexcept override {
    if (!device_.link_up_.load(std::memory_order_acquire)) {
      return ResultCode::disconnected;
    }
    if (bytes.size() > kMaxDatagramBytes) {
      return ResultCode::invalid_value;
    }
    Datagram d;
    std::copy(bytes.begin(), bytes.end(), d.bytes.begin());
    d.length = static_cast<std::uint8_t>(bytes.size());
    return device_.to_device_.try_push(d) ? ResultCode::ok : ResultCode::would_block;
  }
  ResultCode receive(Datagram& out) noexcept override {
    if (!device_.link_up_.load(std::memory_order_acquire)) {
      return ResultCode::disconnected;
    }
    if (synchronous_) {
      device_.handle_host_input(device_.last_step_);
    }
    return device_.to_host_.try_pop(out) ? ResultCode::ok : ResultCode::would_block;
  }
  [[nodiscard]] TransportState state() const noexcept override {
    return device_.link_up_.load(std::memory_order_acquire) ? TransportState::open
                                                            : TransportState::disconnected;
  }
  [[nodiscard]] std::string_view uri() const noexcept override { return "mock://"; }

 private:
  MockDevice& device_;
  bool synchronous_;
};

MockDevice::MockDevice(const GridLayout& layout, const MockOptions& options, std::unique_ptr<Plant> plant)
    : layout_(layout),
      options_(options),
      plant_(std::move(plant)),
      commanded_A_(layout.valve_count(), 0.0),
      sensor_si_(plant_->sensor_count(), 0.0),
      finger_m_(layout.fluid_cell_count()),
      truth_N_(layout.fluid_cell_count()),
      applied_A_(layout.valve_count()),
      scratch_(std::max(layout.fluid_cell_count(), layout.valve_count()), 0.0),
      noise_state_(options.seed ^ 0xA5A5A5A5ULL) {
  for (auto& f : finger_m_) {
    f.store(0.0);
  }
  for (auto& t : truth_N_) {
    t.store(0.0);
  }
  for (auto& a : applied_A_) {
    a.store(0.0);
  }
}

std::shared_ptr<MockDevice> MockDevice::make_placeholder(const MockOptions& options, int rows, int cols) {
  const GridLayout layout(rows, cols);
  auto plant =
      std::make_unique<PlaceholderPlant>(layout, PlaceholderParams{}, options.perturbation, options.seed);
  return std::make_shared<MockDevice>(layout, options, std::move(plant));
}

MockDevice::~MockDevice() { stop(); }

std::unique_ptr<Transport> MockDevice::connect(bool synchronous) {
  synchronous_.store(synchronous, std::memory_order_release);
  return std::make_unique<HostTransport>(*this, synchronous);
}

void MockDevice::start(Clock& clock) {
  if (running_.exchange(true)) {
    return;
  }
  thread_ = std::thread([this, &clock] {
    const Duration period = from_seconds(options_.physics_dt_s * 10.0);
    TimePoint next = clock.now();
    while (running_.load(std::memory_order_acquire)) {
      step(clock.now());
      next += period;
      clock.sleep_until(next);
    }
  });
}

void MockDevice::stop() noexcept {
  if (running_.exchange(false) && thread_.joinable()) {
    thread_.join();
  }
}

void MockDevice::set_finger_indentation(std::span<const double> indentation_m) noexcept {
  const std::size_t n = std::min(indentation_m.size(), finger_m_.size());
  for (std::size_t i = 0; i < n; ++i) {
    finger_m_[i].store(indentation_m[i], std::memory_order_relaxed);
  }
}

void MockDevice::true_contact_forces(std::span<double> out_N) const noexcept {
  const std::size_t n = std::min(out_N.size(), truth_N_.size());
  for (std::size_t i = 0; i < n; ++i) {
    out_N[i] = truth_N_[i].load(std::memory_order_relaxed);
  }
}

void MockDevice::applied_currents(std::span<double> out_A) const noexcept {
  const std::size_t n = std::min(out_A.size(), applied_A_.size());
  for (std::size_t i = 0; i < n; ++i) {
    out_A[i] = applied_A_[i].load(std::memory_order_relaxed);
  }
}

void MockDevice::send_message(const proto::Message& message) noexcept {
  if (!link_up_.load(std::memory_order_acquire)) {
    return;
  }
  Datagram d;
  const auto r = proto::encode_packet(message, tx_sequence_, d.bytes);
  if (r.error != proto::Error::ok) {
    return;
  }
  ++tx_sequence_;
  d.length = static_cast<std::uint8_t>(r.bytes);
  (void)to_host_.try_push(d);  // a full queue drops the datagram, as a bus would
}

void MockDevice::send_status() noexcept {
  proto::Status s;
  s.state = state_.load(std::memory_order_relaxed);
  s.fault = fault_.load(std::memory_order_relaxed);
  const bool released =
      std::all_of(commanded_A_.begin(), commanded_A_.end(), [](double a) { return a == 0.0; });
  s.flags = released ? proto::kFlagValvesReleased : 0;
  send_message(s);
}

void MockDevice::release_valves() noexcept {
  std::fill(commanded_A_.begin(), commanded_A_.end(), 0.0);
  plant_->set_valve_currents(commanded_A_);
  for (auto& a : applied_A_) {
    a.store(0.0, std::memory_order_relaxed);
  }
}

void MockDevice::handle_host_input(TimePoint now) noexcept {
  Datagram d;
  while (to_device_.try_pop(d)) {
    handle(d.bytes.data(), d.length, now);
  }
}

void MockDevice::handle(const std::uint8_t* bytes, std::size_t length, TimePoint now) noexcept {
  const proto::PacketDecoded p = proto::decode_packet(std::span<const std::uint8_t>(bytes, length));
  if (p.error != proto::Error::ok) {
    return;  // a unit drops what it cannot parse; the host sees no answer
  }
  last_heartbeat_ = now;  // any valid packet proves the host is alive
  const auto state = static_cast<proto::DeviceState>(state_.load(std::memory_order_relaxed));
  if (std::holds_alternative<proto::IdentifyRequest>(p.message)) {
    proto::Identity id;
    id.fw_major = kFirmwareMajor;
    id.fw_minor = kFirmwareMinor;
    id.fw_patch = kFirmwarePatch;
    id.rows = static_cast<std::uint8_t>(layout_.rows());
    id.cols = static_cast<std::uint8_t>(layout_.cols());
    id.fluid_cells = static_cast<std::uint16_t>(layout_.fluid_cell_count());
    id.valves = static_cast<std::uint16_t>(layout_.valve_count());
    id.sensors = static_cast<std::uint16_t>(sensor_si_.size());
    id.serial = options_.serial;
    id.current_lsb_nA = static_cast<std::uint32_t>(std::lround(options_.current_lsb_A * 1e9));
    id.current_max_counts = static_cast<std::uint16_t>(std::min<long>(
        std::lround(options_.max_current_A / options_.current_lsb_A), proto::kCurrentCountMax));
    id.sensor_quantity = static_cast<std::uint8_t>(proto::SensorQuantity::displacement_m);
    id.sensor_lsb_nano = static_cast<std::uint32_t>(std::lround(options_.sensor_lsb_m * 1e9));
    id.heartbeat_timeout_ms = static_cast<std::uint16_t>(std::lround(options_.heartbeat_timeout_s * 1e3));
    id.telemetry_rate_hz = static_cast<std::uint16_t>(std::lround(1.0 / options_.telemetry_period_s));
    send_message(id);
    send_status();
  } else if (const auto* r = std::get_if<proto::StateRequest>(&p.message)) {
    switch (static_cast<proto::StateRequestCode>(r->request)) {
      case proto::StateRequestCode::enable:
        state_.store(static_cast<std::uint8_t>(proto::DeviceState::enabled));
        fault_.store(0);
        break;
      case proto::StateRequestCode::disable:
        state_.store(static_cast<std::uint8_t>(proto::DeviceState::disabled));
        release_valves();
        break;
      case proto::StateRequestCode::pause:
        state_.store(static_cast<std::uint8_t>(proto::DeviceState::paused));
        break;
      case proto::StateRequestCode::estop:
        state_.store(static_cast<std::uint8_t>(proto::DeviceState::fault));
        fault_.store(static_cast<std::uint8_t>(proto::FaultCode::estop));
        release_valves();
        break;
    }
    send_status();
  } else if (const auto* v = std::get_if<proto::ValveCurrents>(&p.message)) {
    if (state != proto::DeviceState::enabled) {
      return;  // only an enabled unit drives its coils
    }
    const double lsb = options_.current_lsb_A;
    for (std::size_t i = 0; i < v->count; ++i) {
      const std::size_t valve = v->first + i;
      if (valve < commanded_A_.size()) {
        commanded_A_[valve] = std::min(v->counts[i] * lsb, options_.max_current_A);
      }
    }
    plant_->set_valve_currents(commanded_A_);
    for (std::size_t i = 0; i < commanded_A_.size(); ++i) {
      applied_A_[i].store(commanded_A_[i], std::memory_order_relaxed);
    }
  }
  // Heartbeat needs nothing beyond refreshing the watchdog above.
}

void MockDevice::emit_telemetry(TimePoint now) noexcept {
  plant_->read_sensors(sensor_si_);
  const auto time_us =
      static_cast<std::uint32_t>(static_cast<std::uint64_t>(now.count() / 1000) & 0xFFFFFFFFULL);
  std::size_t first = 0;
  while (first < sensor_si_.size()) {
    proto::Telemetry t;
    t.device_time_us = time_us;
    t.first = static_cast<std::uint16_t>(first);
    t.count = static_cast<std::uint8_t>(std::min(proto::kMaxTelemetryValues, sensor_si_.size() - first));
    for (std::size_t i = 0; i < t.count; ++i) {
      const double noisy = sensor_si_[first + i] + options_.sensor_noise_m * gaussian(noise_state_);
      const double counts = std::nearbyint(noisy / options_.sensor_lsb_m);
      t.counts[i] = static_cast<std::int16_t>(std::clamp(counts, static_cast<double>(proto::kSensorCountMin),
                                                         static_cast<double>(proto::kSensorCountMax)));
    }
    send_message(t);
    first += t.count;
  }
}

void MockDevice::step(TimePoint now) noexcept {
  if (!started_) {
    started_ = true;
    last_step_ = now;
    last_heartbeat_ = now;
    next_telemetry_ = now;
    next_status_ = now;
  }
  handle_host_input(now);
  const auto state = static_cast<proto::DeviceState>(state_.load(std::memory_order_relaxed));
  if (state == proto::DeviceState::enabled &&
      to_seconds(now - last_heartbeat_) > options_.heartbeat_timeout_s) {
    state_.store(static_cast<std::uint8_t>(proto::DeviceState::fault));
    fault_.store(static_cast<std::uint8_t>(proto::FaultCode::heartbeat_lost));
    release_valves();
    send_status();
  }
  for (std::size_t i = 0; i < finger_m_.size(); ++i) {
    scratch_[i] = finger_m_[i].load(std::memory_order_relaxed);
  }
  plant_->set_finger_indentation(std::span<const double>(scratch_.data(), finger_m_.size()));
  const Duration dt = from_seconds(options_.physics_dt_s);
  while (last_step_ + dt <= now) {
    plant_->step(options_.physics_dt_s);
    last_step_ += dt;
    if (last_step_ >= next_telemetry_) {
      emit_telemetry(last_step_);
      next_telemetry_ += from_seconds(options_.telemetry_period_s);
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
}

}  // namespace mrskin
