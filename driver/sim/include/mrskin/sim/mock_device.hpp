// The mock device: firmware that speaks protocol v1 packets (HID report framing) over an
// in-process transport, above a simulated Plant. It is our only hardware, so it behaves
// like a unit: identity, heartbeat watchdog, states, current and slew limits, a coil
// thermal model that derates, configuration memory with a versioned calibration, device
// timestamps, and faults injected on demand.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <string_view>

#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/driver/force_truth.hpp"
#include "mrskin/driver/layout.hpp"
#include "mrskin/driver/model/profile.hpp"
#include "mrskin/driver/transport.hpp"
#include "mrskin/protocol/messages.hpp"
#include "mrskin/sim/export.hpp"
#include "mrskin/sim/plant.hpp"

namespace mrskin::sim {

// Faults the mock injects, seeded like everything else (mock://?faults=...).
struct MRSKIN_SIM_API MockFaults {
  double drop_probability = 0.0;         // each datagram, each direction
  double duplicate_probability = 0.0;    // each datagram, each direction
  double corrupt_probability = 0.0;      // one bit flipped, each datagram, each direction
  double reorder_probability = 0.0;      // device->host datagram held back behind the next
  double delay_s = 0.0;                  // extra device->host latency
  double disconnect_at_s = -1.0;         // cable pulled at this device time (< 0: never)...
  double disconnect_for_s = 0.0;         // ...for this long; the unit reboots DISABLED
  int stuck_sensor = -1;                 // this sensor freezes at its first reading
  int noisy_sensor = -1;                 // this sensor gets noisy_sensor_noise_lsb of noise
  double noisy_sensor_noise_lsb = 20.0;  // standard deviation, in the sensor's resolution
  int offset_sensor = -1;                // this sensor reads offset_sensor_lsb off (a shifted zero)
  double offset_sensor_lsb = 80.0;       // 200 um on the 5 x 5's 2.5 um displacement sensors
  int overheat_valve = -1;               // this coil gets overheat_power_W of extra heat...
  double overheat_power_W = 10.0;
  double overheat_for_s = -1.0;  // ...for this long from power-up (< 0: for ever)
  double bus_off_at_s = -1.0;    // bus-off at this device time (< 0: never)
  double bus_off_for_s = 0.1;    // silent this long, then back in FAULT
  // This valve leaks (a worn seal, a gap beside the channel): its field acts as if its coil
  // carried only leak_current_fraction of its current, so it holds far less pressure.
  int leak_valve = -1;
  double leak_current_fraction = 0.2;
  [[nodiscard]] bool any() const noexcept;
};

// The bus between the host and the unit, modelled on the mock's clock (mock://?bus=...): each
// packet costs exactly the HID reports or CAN frames the protocol's encoders make of it, so
// traffic that does not fit the bus shows up as latency and loss (docs/protocol.md, "The mock's
// bus model"). The default stays none until a session's configuration read on hid-fs loses no
// telemetry (its ~90 ConfigData replies each displace a sample: docs/protocol.md); bus=profile
// in a mock:// URI models the bus the profile's [interface] names.
//  - none: an ideal link (every packet delivered when sent), as before the model.
//  - hid_fs: full-speed USB-HID, one 64-byte report per 1 ms frame each way; hid_hs: high speed,
//    kUsbHighSpeedMaxReportsPerMicroframe reports per 125 us microframe each way. A report that
//    finds its frame's slots taken waits for the next free slot; past usb_queue_reports waiting
//    it is dropped and counted.
//  - can, canfd: one shared bus; each frame holds it for its worst-case stuffed time at the bit
//    rates, lowest identifier first among the frames waiting (each node's queue in order).
//    The host's writes get ENOBUFS past can_txqueuelen_frames queued frames (counted), and are
//    retried after the CAN transport's backoff; the unit drops a packet its queue cannot take.
enum class MockBusKind : unsigned char { none, hid_fs, hid_hs, can, canfd };
// "none", "hid-fs", "hid-hs", "can", "canfd": the names mock://?bus= takes.
MRSKIN_SIM_API const char* to_string(MockBusKind kind) noexcept;

struct MockBusOptions {
  MockBusKind kind = MockBusKind::none;    // mock:// without bus= takes the profile's bus instead
  double nominal_bitrate_bit_per_s = 1e6;  // CAN and CAN FD arbitration phase
  double data_bitrate_bit_per_s = 5e6;     // CAN FD data phase
  // Reports that may wait for a slot, each way. Host to device: hidraw's write on usbhid is
  // synchronous (one report a call), so the queue before the bus is the hid transport's send
  // queue (HidTransportOptions::send_queue, 64), as deep as usbhid's HID_OUTPUT_FIFO_SIZE (64).
  // The unit's IN queue gets as many, and keeps one telemetry report waiting at most: a newer
  // sample takes its place (counted dropped).
  std::size_t usb_queue_reports = 64;
  // hid_hs: the bytes of the reports the unit declares in 1.2's UsbSlots (64..1024; 0: 1024, the
  // most a unit may declare), mock://?report_bytes=N. hid_fs: 64 always.
  std::size_t usb_report_bytes = 0;
  // Frames each node queues for the bus: a CAN netdev's default txqueuelen (10) on the host, and
  // as many in the unit's transmit queue, which it feeds from its packets as frames leave.
  std::size_t can_txqueuelen_frames = 10;
  // Packets the host's CAN transport queues before send() refuses (CanTransportOptions), and the
  // unit's packets waiting for its transmit queue (one telemetry sample at most, as on USB).
  std::size_t can_send_queue_packets = 64;
  std::uint8_t can_node = 1;
};

// What the bus model carried and lost. Any thread.
struct MockBusDirection {
  std::uint64_t packets = 0;  // packets delivered
  std::uint64_t carried = 0;  // HID reports or CAN frames that went on the bus
  std::uint64_t bytes = 0;    // bytes they carried: packet bytes in reports, data bytes in frames
  std::uint64_t dropped = 0;  // packets lost to the bus: its queue was full
  std::uint64_t unsent = 0;   // packets with no form on this framing (classic CAN's heartbeat
                              // echo), which a CAN transport drops too
  double max_wait_s = 0.0;    // longest from a packet handed to the bus to its delivery
  double load = 0.0;          // fraction of the bus: USB bytes over the bytes the slots could
                              // carry; CAN the time the bus was busy with this direction
};
struct MockBusStats {
  MockBusKind kind = MockBusKind::none;
  MockBusDirection host_to_device;
  MockBusDirection device_to_host;
  std::uint64_t enobufs = 0;  // CAN: host frame writes refused past txqueuelen (then retried)
  // Host packets the unit heard at its own time, outside the bus and its loads, because its plant
  // lagged real time by more than a telemetry period (what had queued meanwhile would otherwise
  // reach the bus at once and be dropped there; MockDevice::skipped_time_s()).
  std::uint64_t host_while_lagging = 0;
  double elapsed_s = 0.0;  // simulated time the loads are over
};

// A classic CAN unit's default sensor deadband, in counts (docs/protocol.md, "Sensor deadband
// (1.2)"): what brings the 5x5's traffic under half the bus at 1 Mbit/s.
inline constexpr int kClassicCanSensorDeadbandCounts = 2;

// How the unit behaves. What it is (grid, current range and resolution, sensors, coil
// resistance) comes from its device profile, not from here.
struct MockOptions {
  std::uint64_t seed = 1;
  double perturbation = 0.15;        // plant parameters within +-15 % of nominal
  double physics_dt_s = 1e-4;        // plant substep
  double telemetry_period_s = 1e-3;  // one telemetry packet per period
  double max_catch_up_s = 0.05;      // a step() further behind skips the excess (skipped_time_s())
  double status_period_s = 0.1;      // status also goes out on every change
  double heartbeat_timeout_s = 0.1;  // valves released after this silence
  double sensor_noise_scale = 1.0;   // multiplies the profile's noise_std (0: noise-free)
  // The unit's sensor deadband, in counts (mock://?deadband=N, 0 to 100; 0: none), declared to a
  // 1.2 host (protocol 1.2's SensorDeadband) and applied only once one said 1.2: a block of 4
  // sensors (a classic CAN sensor block) whose every reading is within N counts of the values last
  // sent in it is sent with those values again, so 1.2's delta blocks leave it out. The host sees
  // readings up to N counts stale (docs/protocol.md, "Sensor deadband (1.2)"). -1: the bus's
  // default, kClassicCanSensorDeadbandCounts on classic CAN (bus.kind can), none elsewhere.
  int sensor_deadband_counts = -1;
  std::uint32_t serial = 0x4D520001;
  double slew_time_s = 2.5e-3;  // current driver's slew limit: a full-scale step takes this long
  // Coil thermal model: C dT/dt = R I^2 + P_extra - (T - T_ambient) / R_th (R: the profile's).
  double coil_heat_capacity_J_per_K = 0.5;
  double coil_thermal_resistance_K_per_W = 20.0;
  double ambient_C = 25.0;
  double derate_start_C = 80.0;  // current limit falls linearly from here...
  double fault_C = 100.0;        // ...to zero here, where the unit faults
  double time_scale = 1.0;       // multiplies every timeout (slow environments, VMs)
  MockFaults faults{};
  std::uint16_t calibration_version = 1;
  // The factory calibration stored on the unit: its plant's parameters measured to this
  // relative spread (model::measure_calibration). Negative: store the nominal calibration
  // (every ratio 1), as an uncalibrated unit would.
  double calibration_error = 0.01;
  // An H-bridge coil driver: the unit takes StateRequest degauss (protocol 1.1) while disabled
  // and runs a decaying alternating current through every coil. false: a unipolar driver, which
  // ignores the request (mock://?bipolar=0).
  bool bipolar_driver = true;
  // The protocol major version the unit reports in its Identity (mock://?protocol_major=N): a
  // unit from another major release, which a host must refuse (ProtocolMismatch).
  std::uint8_t protocol_major = protocol::kVersionMajor;
  // The protocol minor version the unit reports (mock://?protocol_minor=N, 0..kVersionMinor).
  // Below 2 it is a 1.1 unit: it never packs reports and reads only the first packet of each.
  std::uint8_t protocol_minor = protocol::kVersionMinor;
  // mock://?finger=SCENE: the scene whose script the simulated finger follows while the stream
  // comes from elsewhere. The driver only carries the name; the bridge's tools run the script.
  std::string finger_scene;
  MockBusOptions bus{};          // mock://?bus=...&bitrate=...
  double degauss_step_s = 0.02;  // each half-cycle's hold (about 4 coil time constants)
  double degauss_ratio = 0.85;   // amplitude ratio between half-cycles, from max_current_A
};

class MRSKIN_SIM_API MockDevice final : public SimulatedUnit {
 public:
  // A unit built to profile, whose configuration memory holds profile_text (read back by the
  // host during the handshake) and a versioned calibration. The plant has one sensor per
  // profile sensor. Throws InvalidArgument when the profile does not fit protocol v1 (current
  // range above 4095 counts, sensors of several quantities or resolutions) or the plant.
  MockDevice(const model::DeviceProfile& profile, std::string_view profile_text, const MockOptions& options,
             std::unique_ptr<Plant> plant);
  // A unit on the perturbed network plant (NetworkPlant: the profile's reference physics with
  // parameters spread by options.perturbation, seeded by options.seed), built to a profile
  // (default: the default profile). Throws InvalidArgument naming the profile on failure.
  static std::shared_ptr<MockDevice> make(const MockOptions& options,
                                          std::string_view profile_name_or_path = "");
  static std::shared_ptr<MockDevice> make(const MockOptions& options, const model::LoadedProfile& loaded);
  MockDevice(const MockDevice&) = delete;
  MockDevice& operator=(const MockDevice&) = delete;
  MockDevice(MockDevice&&) = delete;
  MockDevice& operator=(MockDevice&&) = delete;
  ~MockDevice() override;

  // The host's end of the link. With synchronous == true (single-threaded tests), the
  // firmware answers requests inside the host's receive() call; telemetry and physics
  // still advance only in step().
  // clock (optional, synchronous mode) dates what the firmware does inside receive().
  std::unique_ptr<Transport> connect(bool synchronous, const Clock* clock = nullptr);

  // Handles host packets, advances the plant to now and emits telemetry. Not thread-safe
  // against itself: call it from one thread, or use start().
  void step(TimePoint now) noexcept;
  // Runs step() on its own thread at the physics rate against clock until stop().
  void start(Clock& clock);
  void stop() noexcept;

  // Finger input, m per fluid cell; callable from any thread.
  void set_finger_indentation(std::span<const double> indentation_m) noexcept;
  // The finger input last set, m per fluid cell; callable from any thread.
  void finger_indentation(std::span<double> out_m) const noexcept;
  // Ground truth: the plant's contact force per fluid cell, N; callable from any thread.
  void true_contact_forces(std::span<double> out_N) const noexcept;
  // Coil currents the plant sees now, A.
  void applied_currents(std::span<double> out_A) const noexcept;

  [[nodiscard]] const GridLayout& layout() const noexcept;
  // The profile the unit was built to (as stored in its configuration memory).
  [[nodiscard]] const model::DeviceProfile& profile() const noexcept;
  [[nodiscard]] std::uint8_t state() const noexcept;
  [[nodiscard]] std::uint8_t fault() const noexcept;
  // Pulls (false) or re-plugs (true) the cable. A re-plugged unit boots DISABLED.
  void set_link_up(bool up) noexcept;
  [[nodiscard]] bool link_up() const noexcept;
  // Simulated time skipped because step() fell further behind than max_catch_up_s, s; any
  // thread. Zero when stepped at least every max_catch_up_s (every test rig).
  [[nodiscard]] double skipped_time_s() const noexcept;
  // Hottest coil temperature, deg C; callable from any thread.
  [[nodiscard]] double max_coil_temperature_C() const noexcept;
  // Datagrams the fault injector dropped, duplicated, corrupted, reordered (both directions),
  // and the device->host datagrams the link lost because the host was not reading.
  struct FaultCounters {
    std::uint64_t dropped = 0;
    std::uint64_t duplicated = 0;
    std::uint64_t corrupted = 0;
    std::uint64_t reordered = 0;
    std::uint64_t congested = 0;  // device->host datagrams lost because the host did not read
  };
  [[nodiscard]] FaultCounters fault_counters() const noexcept;
  // The bus model's counts and loads since the unit started (mock://?bus=...).
  [[nodiscard]] MockBusStats bus_stats() const noexcept;
  // MockBusStats' longest waits count from now on (any thread): mrskin-bridged's loop leaves
  // out the open's handshake and configuration reads.
  void restart_bus_max_wait() noexcept;

  // --- firmware state, for tests: call from the thread that steps the device ---------------
  // The per-cell impedance target the firmware holds and when its validity started. Once the
  // host sends targets (and until it sends currents again, or the unit leaves ENABLED) the
  // firmware renders them every telemetry period: its own observer on the readings it reports
  // and CellInverse on the nominal profile set the coil commands (rendering_targets()).
  struct HeldTarget {
    protocol::CellTarget target{};
    TimePoint validity_start{};
  };
  [[nodiscard]] HeldTarget held_target(std::size_t cell) const noexcept;
  [[nodiscard]] bool rendering_targets() const noexcept;
  // Currents the host commanded (before slew limit and derating), A.
  [[nodiscard]] std::span<const double> commanded_currents() const noexcept;

 private:
  // The firmware's state and logic (mock_device_impl.hpp): a new member there leaves this
  // class's layout, and a console built against it, unchanged.
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// The mock device's ground truth for the bridge's scoring: its plant's contact forces and the
// finger it was given.
class MRSKIN_SIM_API MockDeviceTruth final : public ForceTruth {
 public:
  explicit MockDeviceTruth(const MockDevice& mock) noexcept : mock_(mock) {}
  void true_forces(std::span<double> out_N) const noexcept override { mock_.true_contact_forces(out_N); }
  bool finger_indentation(std::span<double> out_m) const noexcept override {
    mock_.finger_indentation(out_m);
    return true;
  }

 private:
  const MockDevice& mock_;
};

}  // namespace mrskin::sim
