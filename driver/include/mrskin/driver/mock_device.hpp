// The mock device: firmware that speaks protocol v1 packets (HID report framing) over an
// in-process transport, above a simulated Plant. It is our only hardware, so it behaves
// like a unit: identity, heartbeat watchdog, states, current limits, timestamps.
#pragma once

#include <atomic>
#include <cstdint>
#include <memory>
#include <span>
#include <thread>
#include <vector>

#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/layout.hpp"
#include "mrskin/driver/plant.hpp"
#include "mrskin/driver/spsc_queue.hpp"
#include "mrskin/driver/transport.hpp"
#include "mrskin/protocol/messages.hpp"

namespace mrskin {

struct MockOptions {
  std::uint64_t seed = 1;
  double perturbation = 0.15;        // plant parameters within +-15 % of nominal
  double physics_dt_s = 1e-4;        // plant substep
  double telemetry_period_s = 1e-3;  // one telemetry packet per period
  double status_period_s = 0.1;      // status also goes out on every change
  double heartbeat_timeout_s = 0.1;  // valves released after this silence
  double max_current_A = 0.5;
  double current_lsb_A = 125e-6;
  double sensor_lsb_m = 2.5e-6;
  double sensor_noise_m = 1e-6;  // standard deviation, before quantisation
  std::uint32_t serial = 0x4D520001;
};

class MockDevice {
 public:
  MockDevice(const GridLayout& layout, const MockOptions& options, std::unique_ptr<Plant> plant);
  // The placeholder plant on a layout (default the paper's 5 x 5).
  static std::shared_ptr<MockDevice> make_placeholder(const MockOptions& options, int rows = 5, int cols = 5);
  MockDevice(const MockDevice&) = delete;
  MockDevice& operator=(const MockDevice&) = delete;
  MockDevice(MockDevice&&) = delete;
  MockDevice& operator=(MockDevice&&) = delete;
  ~MockDevice();

  // The host's end of the link. With synchronous == true (single-threaded tests), the
  // firmware answers requests inside the host's receive() call; telemetry and physics
  // still advance only in step().
  std::unique_ptr<Transport> connect(bool synchronous);

  // Handles host packets, advances the plant to now and emits telemetry. Not thread-safe
  // against itself: call it from one thread, or use start().
  void step(TimePoint now) noexcept;
  // Runs step() on its own thread at the physics rate against clock until stop().
  void start(Clock& clock);
  void stop() noexcept;

  // Finger input, m per fluid cell; callable from any thread.
  void set_finger_indentation(std::span<const double> indentation_m) noexcept;
  // Ground truth: the plant's contact force per fluid cell, N; callable from any thread.
  void true_contact_forces(std::span<double> out_N) const noexcept;
  // Coil currents the plant sees now, A.
  void applied_currents(std::span<double> out_A) const noexcept;

  [[nodiscard]] const GridLayout& layout() const noexcept { return layout_; }
  [[nodiscard]] std::uint8_t state() const noexcept { return state_.load(std::memory_order_acquire); }
  [[nodiscard]] std::uint8_t fault() const noexcept { return fault_.load(std::memory_order_acquire); }
  // Stop answering (simulates a host going silent is done by the host; this is the device
  // pulling its cable).
  void set_link_up(bool up) noexcept { link_up_.store(up, std::memory_order_release); }

 private:
  class HostTransport;
  friend class HostTransport;
  void handle_host_input(TimePoint now) noexcept;
  void handle(const std::uint8_t* bytes, std::size_t length, TimePoint now) noexcept;
  void send_message(const protocol::Message& message) noexcept;
  void send_status() noexcept;
  void release_valves() noexcept;
  void emit_telemetry(TimePoint now) noexcept;

  GridLayout layout_;
  MockOptions options_;
  std::unique_ptr<Plant> plant_;
  SpscQueue<Datagram> to_device_{256};
  SpscQueue<Datagram> to_host_{1024};
  std::vector<double> commanded_A_;
  std::vector<double> sensor_si_;
  std::vector<std::atomic<double>> finger_m_;
  std::vector<std::atomic<double>> truth_N_;
  std::vector<std::atomic<double>> applied_A_;
  std::vector<double> scratch_;
  std::atomic<std::uint8_t> state_{0};
  std::atomic<std::uint8_t> fault_{0};
  std::atomic<bool> link_up_{true};
  std::atomic<bool> synchronous_{false};
  std::atomic<bool> running_{false};
  std::thread thread_;
  TimePoint last_step_{};
  TimePoint last_heartbeat_{};
  TimePoint next_telemetry_{};
  TimePoint next_status_{};
  bool started_ = false;
  std::uint8_t tx_sequence_ = 0;
  std::uint64_t noise_state_;
};

}  // namespace mrskin
