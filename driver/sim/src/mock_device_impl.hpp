// MockDevice's firmware state and logic behind its one pointer (mock_device.hpp). Private to
// libmrskin_sim: mock_device.cpp defines it.
#pragma once

#include <array>
#include <atomic>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <memory>
#include <string_view>
#include <thread>
#include <vector>

#include "mock_bus.hpp"
#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/layout.hpp"
#include "mrskin/driver/model/device_model.hpp"
#include "mrskin/driver/model/inverse.hpp"
#include "mrskin/driver/model/observer.hpp"
#include "mrskin/driver/model/profile.hpp"
#include "mrskin/driver/relaxed_counter.hpp"
#include "mrskin/driver/session.hpp"
#include "mrskin/driver/spsc_queue.hpp"
#include "mrskin/driver/transport.hpp"
#include "mrskin/protocol/messages.hpp"
#include "mrskin/protocol/packet.hpp"
#include "mrskin/sim/mock_device.hpp"
#include "mrskin/sim/plant.hpp"

namespace mrskin::sim {

// A sensor block's values last sent before any was: no 12-bit reading lies within a deadband of it.
inline constexpr std::int16_t kNoBlockSent = std::numeric_limits<std::int16_t>::min();

// Hidden explicitly: a nested class otherwise takes its exported parent's visibility.
struct __attribute__((visibility("hidden"))) MockDevice::Impl {
  // Validates the profile and the faults against the plant (MockDevice's constructor).
  Impl(const model::DeviceProfile& profile, std::string_view profile_text, const MockOptions& options,
       std::unique_ptr<Plant> plant);
  Impl(const Impl&) = delete;
  Impl& operator=(const Impl&) = delete;
  Impl(Impl&&) = delete;
  Impl& operator=(Impl&&) = delete;
  ~Impl();

  // Host end of the in-process link (MockDevice::connect).
  class HostTransport;

  // The public functions that do more than read a member, as documented in mock_device.hpp.
  void step(TimePoint now) noexcept;
  void start(Clock& clock);
  void stop() noexcept;
  void set_link_up(bool up) noexcept;

  // Hands the host's packets to the bus as sent at now, then runs the bus up to advance_to
  // (now when omitted), delivering what it carried (deliver_to_device).
  void handle_host_input(TimePoint now) noexcept;
  void handle_host_input(TimePoint now, TimePoint advance_to) noexcept;
  // What the bus delivers: a host packet reaching the unit at `at` (link faults, then handle),
  // and a unit's packet reaching the host at `at` (the delay line, then the host's queue).
  void deliver_to_device(Datagram d, TimePoint at) noexcept;
  void deliver_to_host(const Datagram& d, TimePoint at) noexcept;
  void handle(const std::uint8_t* bytes, std::size_t length, TimePoint now) noexcept;
  // Sends message as one packet. With packed reports agreed (the host's IdentifyRequest said
  // 1.2), it joins the report being filled (sent first when the packet does not fit), which goes
  // out now unless hold: status and heartbeat echoes wait for the next telemetry report.
  void send_message(const protocol::Message& message, bool hold = false) noexcept;
  void flush_report() noexcept;
  // Status and echoes wait for the telemetry report: with packing agreed, on a framing where a
  // report carries several packets. Classic CAN sends each packet as its own frames anyway, so
  // there they go at once, as in 1.1.
  [[nodiscard]] bool wait_for_telemetry() const noexcept {
    return packing_ && options_.bus.kind != MockBusKind::can;
  }
  // On full-speed USB every slot carries a sample: packed, a ConfigRead that fits beside the
  // telemetry is answered in the next telemetry report, not in a report (and slot) of its own.
  // Before the first step (a synchronous mock's handshake) no sample comes: answers go at once.
  [[nodiscard]] bool config_replies_ride_telemetry() const noexcept {
    return packing_ && slots_taken_by_samples();
  }
  // Full-speed USB, streaming: every IN slot carries a sample. Not a synchronous mock: it takes
  // no step (so sends no sample) while its host is blocked in a setup call.
  [[nodiscard]] bool slots_taken_by_samples() const noexcept {
    return started_ && options_.bus.kind == MockBusKind::hid_fs &&
           !synchronous_.load(std::memory_order_relaxed);
  }
  [[nodiscard]] protocol::ConfigData config_data_for(const protocol::ConfigRead& r) const noexcept;
  void append_pending_config_replies() noexcept;  // into report_, as many as fit, in order
  void handle_packet(const protocol::PacketDecoded& p, TimePoint now) noexcept;
  void answer_identify(const protocol::IdentifyRequest& request) noexcept;  // Identity, UsbSlots, status
  void send_status() noexcept;
  void release_valves() noexcept;
  void emit_telemetry(TimePoint now) noexcept;
  // The deadband (sensor_deadband_counts_) on sample_counts_, block by block, once 1.2 is agreed.
  void apply_sensor_deadband() noexcept;
  void emit(const Datagram& d, TimePoint now) noexcept;
  void flush_delayed(TimePoint now) noexcept;
  void update_coils(double dt_s) noexcept;
  void enter_fault(protocol::FaultCode code) noexcept;
  void apply_link_faults(TimePoint now) noexcept;
  bool chance(double probability) noexcept;
  void handle_config(const protocol::Message& message) noexcept;
  void reseed(TimePoint now) noexcept;
  void render_targets(TimePoint now) noexcept;

  model::DeviceProfile profile_;
  GridLayout layout_;
  MockOptions options_;
  double max_current_A_ = 0.0;
  double current_lsb_A_ = 0.0;
  double sensor_lsb_ = 0.0;           // the sensors' resolution, in their SI unit
  std::vector<double> sensor_noise_;  // standard deviation per sensor, SI
  double coil_resistance_ohm_ = 0.0;
  TargetSeeder seeder_;
  std::vector<HeldTarget> targets_held_;
  // Target rendering: the nominal model (the firmware knows no more than the host).
  std::unique_ptr<model::DeviceModel> render_model_;
  std::unique_ptr<model::CellObserver> render_observer_;
  std::unique_ptr<model::CellInverse> render_inverse_;
  std::vector<model::CellImpedanceTarget> render_targets_;
  std::vector<model::CellState> render_states_;
  bool rendering_targets_ = false;
  std::vector<double> reported_;                 // last telemetry sent, SI (what the host saw)
  std::vector<std::int16_t> block_sent_counts_;  // the deadband: each block's values last sent
  int sensor_deadband_counts_ = 0;               // MockOptions::sensor_deadband_counts, resolved
  std::vector<std::int16_t> sample_counts_;      // this sample's readings, counts
  std::unique_ptr<Plant> plant_;
  // The bus between host and unit (mock_bus.hpp) and where it delivers.
  class Sink final : public BusSink {
   public:
    explicit Sink(Impl& impl) noexcept : impl_(impl) {}
    void deliver_to_device(const Datagram& d, TimePoint at) noexcept override {
      impl_.deliver_to_device(d, at);
    }
    void deliver_to_host(const Datagram& d, TimePoint at) noexcept override { impl_.deliver_to_host(d, at); }

   private:
    Impl& impl_;
  };
  MockBus bus_;
  Sink sink_{*this};
  // A host's packet and when the host sent it, on the host's clock (0: at the unit's time).
  struct HostDatagram {
    Datagram datagram;
    TimePoint sent{};
  };
  SpscQueue<HostDatagram> to_device_{256};
  SpscQueue<Datagram> to_host_{1024};
  std::vector<double> commanded_A_;
  std::vector<double> coil_A_;   // after slew limit and derating
  std::vector<double> plant_A_;  // what the plant's field sees (coil_A_ less a leak fault)
  std::vector<double> coil_C_;
  std::vector<double> stuck_value_;
  struct Delayed {
    TimePoint due{};
    Datagram datagram{};
  };
  std::vector<Delayed> delay_line_;  // ring, preallocated
  std::size_t delay_head_ = 0;
  std::size_t delay_count_ = 0;
  Datagram held_{};  // reorder: the datagram held back
  bool holding_ = false;
  std::vector<std::uint8_t> calibration_blob_;
  std::vector<std::uint8_t> calibration_pending_;  // a write in progress
  std::vector<std::uint8_t> profile_blob_;
  std::atomic<double> max_coil_C_{25.0};
  RelaxedCounter dropped_;
  RelaxedCounter duplicated_;
  RelaxedCounter corrupted_;
  RelaxedCounter reordered_;
  RelaxedCounter congested_;
  std::atomic<std::int64_t> skipped_ns_{0};
  bool lagging_ = false;  // within step(): the unit lags real time by more than two telemetry periods
  TimePoint step_now_{};  // within step(): the real time it was called at
  std::uint64_t fault_rng_;
  TimePoint start_{};
  TimePoint bus_off_until_{};
  bool bus_off_done_ = false;
  bool disconnect_done_ = false;
  bool derated_ = false;
  bool degaussing_ = false;
  double degauss_elapsed_s_ = 0.0;
  std::vector<double> sensor_si_;
  std::vector<std::atomic<double>> finger_m_;
  std::vector<std::atomic<double>> truth_N_;
  std::vector<std::atomic<double>> applied_A_;
  std::vector<double> scratch_;
  std::atomic<std::uint8_t> state_{0};
  std::atomic<std::uint8_t> fault_{0};
  std::atomic<bool> link_up_{true};
  std::atomic<bool> synchronous_{false};
  const Clock* sync_clock_ = nullptr;
  std::atomic<bool> running_{false};
  std::thread thread_;
  TimePoint last_step_{};
  TimePoint last_heartbeat_{};
  TimePoint next_telemetry_{};
  TimePoint next_status_{};
  bool started_ = false;
  std::uint8_t tx_sequence_ = 0;
  bool packing_ = false;  // the host's IdentifyRequest declared 1.2 and this unit speaks it
  Datagram report_{};     // packed report being filled (length: bytes used)
  // The bytes report_ may use: 64 until this unit has declared larger reports (UsbSlots, 1.2).
  std::size_t report_capacity_ = protocol::kHidReportBytes;
  static constexpr std::size_t kNoHeldStatus = ~std::size_t{0};
  std::size_t held_status_at_ = kNoHeldStatus;  // where the status waiting in report_ starts
  // ConfigReads waiting for a telemetry report (config_replies_ride_telemetry), oldest first; a
  // host keeps at most 16 in flight.
  static constexpr std::size_t kPendingConfigReads = 32;
  static constexpr std::size_t kConfigCapacity = 4096;  // bytes of configuration memory per blob
  std::array<protocol::ConfigRead, kPendingConfigReads> pending_reads_{};
  std::size_t pending_read_count_ = 0;
  std::size_t config_bytes_beside_telemetry_ = 0;  // the largest reply that rides (bus_budget.hpp)
  std::uint64_t noise_state_;
};

}  // namespace mrskin::sim
