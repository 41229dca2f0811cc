// Sensor faults from the readings and the observer's residuals. Each displacement
// sensor is tested on every fresh reading:
//   - stuck: the same reading over and over. A live sensor's noise moves its quantised reading:
//     the run length is set so that a healthy sensor repeats that long with probability
//     false_alarm_probability (from the profile's noise and resolution). A profile whose noise is
//     far below its resolution cannot tell a stuck sensor at rest: stuck_run_readings() says how
//     long it takes. A unit with a declared deadband (protocol 1.2's SensorDeadband) repeats a
//     reading for as long as the value stays within the band: a repeat counts towards the run only
//     while the observer's residual for the sensor lies beyond what the band explains (the band in
//     the residual's sigmas, the observer's: max(noise, resolution / sqrt 12), plus
//     kDeadbandMarginSigma), so a stuck sensor is found once the finger moves its
//     value away from the stuck one, and never while a healthy one rests inside the band.
//   - noisy: the mean square of the reading's second difference (6 sigma^2 for white noise, and
//     next to nothing from a finger's motion at 1 kHz) over noise_ratio_limit times its expected
//     value. Spaced by the unit's clock when update() is given it: a host that reads only the
//     newest of several readings sees them unevenly spaced, and a moving finger is no noise.
//   - offset: the observer's residual for this sensor (its reading less what the fitted depths
//     predict), averaged, beyond offset_limit_sigma. Depths are never negative and every cell is
//     read by more than one sensor on the built-in profiles, so one sensor's shifted zero is left
//     as a residual on that sensor, mostly; where the fit splits it between two sensors, the blame
//     goes to the one its neighbours oppose (docs/reliability.md).
// A fault latches until reset(): a sensor that comes and goes must not slip back into the fit.
// A fluid leak cannot be seen here: with the pads pressed by a finger, the sensors read the
// finger's shape whatever the valves hold (docs/reliability.md).
#pragma once

#include <cstddef>
#include <cstdint>
#include <limits>
#include <memory>
#include <span>

#include "mrskin/bridge/export.hpp"
#include "mrskin/driver/layout.hpp"
#include "mrskin/driver/model/profile.hpp"

namespace mrskin::bridge {

enum class SensorFault : std::uint8_t { none = 0, stuck = 1, noisy = 2, offset = 3 };
MRSKIN_BRIDGE_API const char* to_string(SensorFault fault) noexcept;

struct SensorFaultOptions {
  bool enabled = true;
  // A healthy sensor repeats its reading for the stuck run with at most this probability.
  double false_alarm_probability = 1e-12;
  // Noisy: mean square second difference over 6 sigma^2, averaged over noise_window_readings.
  double noise_ratio_limit = 25.0;  // the noise 5 times the profile's
  double noise_window_readings = 16.0;
  // Offset: the residual's mean, in the sensor's sigmas, averaged over offset_window_readings.
  double offset_limit_sigma = 15.0;
  double offset_window_readings = 40.0;
};

class MRSKIN_BRIDGE_API SensorFaultMonitor {
 public:
  static constexpr std::size_t npos = std::numeric_limits<std::size_t>::max();

  // A repeat within the deadband counts towards a stuck run only past this many sigmas beyond it.
  static constexpr double kDeadbandMarginSigma = 4.0;

  // Setup: throws InvalidArgument on options out of range. reading_deadband: the unit's declared
  // sensor deadband in the readings' SI unit (DeviceInfo::sensor_deadband_counts x sensor_lsb),
  // 0 for none.
  SensorFaultMonitor(const model::DeviceProfile& profile, const GridLayout& layout,
                     const SensorFaultOptions& options, double reading_deadband = 0.0);
  // Copies are deep (each has its own state); a moved-from monitor can only be assigned to or
  // destroyed.
  SensorFaultMonitor(const SensorFaultMonitor& other);
  SensorFaultMonitor& operator=(const SensorFaultMonitor& other);
  SensorFaultMonitor(SensorFaultMonitor&& other) noexcept;
  SensorFaultMonitor& operator=(SensorFaultMonitor&& other) noexcept;
  ~SensorFaultMonitor();

  // One fresh set of readings (SI, the profile's order) and the observer's residuals for them
  // (CellObserver::sensor_residual_sigma()). Returns the sensor that became faulty on this
  // reading, or npos. At most one sensor per call (the others are judged again next time, once
  // the observer has left the faulty one out). Real-time safe.
  std::size_t update(std::span<const double> readings, std::span<const double> residual_sigma) noexcept;
  // The same, with the unit's clock at the readings' sampling (DeviceSession::sensor_device_time_us,
  // us, wrapping): the noise test spaces its second difference by it, so readings a late host
  // skipped over are no noise. Without it, readings are taken as evenly spaced.
  std::size_t update(std::span<const double> readings, std::span<const double> residual_sigma,
                     std::uint32_t device_time_us) noexcept;
  void reset() noexcept;
  // The unit's declared deadband again (after a reconnect: the unit declares it anew), in the
  // readings' unit; a negative or non-finite value is taken as 0. Real-time safe.
  void set_reading_deadband(double reading_deadband) noexcept;
  // After a gap in the readings (the bridge halted, the link down): the tests start again from
  // the next reading, the latched faults stay.
  void restart_history() noexcept;

  [[nodiscard]] SensorFault fault(std::size_t sensor) const noexcept;
  [[nodiscard]] std::size_t faulty_count() const noexcept;
  // Displacement sensors watched and not faulty (those the observer's fit still uses).
  [[nodiscard]] std::size_t healthy_count() const noexcept;
  // The first fluid cell whose last healthy displacement sensor failed, or npos: while every cell
  // the profile reads is read by one, the bridge goes on without the faulty sensors.
  [[nodiscard]] std::size_t unobservable_cell() const noexcept;
  // The fluid cells a sensor reads (its valve's cells, or its own cell).
  [[nodiscard]] std::span<const std::size_t> cells_of_sensor(std::size_t sensor) const noexcept;
  // The stuck test's run, in readings (npos for a sensor the tests do not watch).
  [[nodiscard]] std::size_t stuck_run_readings(std::size_t sensor) const noexcept;
  // The tests' running figures (tick thread): the noise ratio and the mean residual, in sigmas.
  [[nodiscard]] double noise_ratio(std::size_t sensor) const noexcept;
  [[nodiscard]] double mean_residual_sigma(std::size_t sensor) const noexcept;
  // What the last fault's test measured (for the log): the repeated reading (stuck), the noise
  // ratio (noisy) or the mean residual in sigmas (offset).
  [[nodiscard]] double evidence(std::size_t sensor) const noexcept;

 private:
  // Everything else lives behind one pointer: a console linked against this header keeps its
  // ABI when the monitor's state changes (docs/api.md, "ABI").
  class Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace mrskin::bridge
