// Robot stream sources named by URI (docs/sources.md): scene://NAME, udp://HOST:PORT,
// replay://FILE, igtl://HOST:PORT (client) and igtl-listen://HOST:PORT (server). Network sources
// read on their own I/O thread, validate every sample (untrusted input: dropped and counted, never
// a crash or a stall) and hand it to the tick through a wait-free SPSC queue; latest() drains it
// without blocking, allocating, locking or logging.
#pragma once

#include <array>
#include <atomic>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include "mrskin/bridge/drop_reason.hpp"
#include "mrskin/bridge/export.hpp"
#include "mrskin/bridge/scene.hpp"
#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/relaxed_counter.hpp"
#include "mrskin/driver/spsc_queue.hpp"

namespace mrskin::bridge {

struct SourceOptions {
  // Plausible ranges; a sample outside them is dropped as out_of_range.
  double max_force_N = 20.0;  // force must be in [0, max_force_N]
  double max_abs_indentation_m = 0.05;
  double max_abs_contact_m = 1.0;  // |contact_x_m|, |contact_y_m|
  double max_tip_radius_m = 0.05;  // tip radius in [0, max]
  // Tip radius reported by sources whose format does not carry one (OpenIGTLink).
  double tip_radius_m = 3e-3;
  std::size_t queue_capacity = 256;  // samples between the I/O thread and the tick
  // Robot clock -> host clock: the offset is the minimum of (arrival - robot stamp) seen so far,
  // allowed to rise by this much per second of host time so that it follows clock drift.
  double offset_drift_s_per_s = 1e-4;
  // A stream whose stamps go backwards this many times in a row restarted (a robot reboot):
  // ordering and the clock offset start over.
  std::uint32_t restart_after_out_of_order = 100;
  // OpenIGTLink: the device name each message kind is taken from ("*": any name). URI keys
  // force_device, pose_device, map_device and pose_tool; the daemon's [stream] table.
  std::string igtl_force_device = "ContactForce";  // SENSOR: 1 value (normal), 3 (force), 6 (wrench)
  std::string igtl_pose_device = "InstrumentTip";  // TRANSFORM, POSITION, QTDATA, TDATA; mm
  std::string igtl_map_device = "TactileArray";    // NDARRAY rows x cols, Pa
  std::string igtl_pose_tool = "*";                // QTDATA/TDATA element name ("*": the first)
  // The robot's frame in the tissue frame: a force vector f and a position p reported in the
  // robot's frame are taken as R f and R p + origin. Row-major; identity: the robot reports in
  // the tissue frame (z along the tissue's outward normal, the surface at z = 0).
  std::array<double, 9> robot_to_tissue{1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0};
  std::array<double, 3> robot_origin_m{0.0, 0.0, 0.0};
  // dds://ARM: the DDS domain (0..232) and the ROS 2 topics ("" : CRTK's /ARM/measured_cf and
  // /ARM/measured_cp). URI keys domain, wrench, pose.
  int dds_domain = 0;
  std::string dds_wrench_topic;
  std::string dds_pose_topic;
  double tactile_pitch_m = 2e-3;          // NDARRAY cell pitch (square cells)
  std::size_t max_message_bytes = 65536;  // larger bodies: oversized, connection closed
  double reconnect_min_s = 0.05;          // igtl:// backoff, doubling up to max
  double reconnect_max_s = 2.0;
  // Replay.
  bool replay_loop = false;       // start over at the end instead of holding the last sample
  bool replay_max_speed = false;  // one sample per latest() call, stamped `now`
  std::size_t max_replay_samples = 2'000'000;
};

// A snapshot of a source's counters.
struct SourceStats {
  std::uint64_t accepted = 0;
  DropCounts drops{};                  // by DropReason (drop_reason.hpp)
  std::uint64_t poses = 0;             // pose messages taken (OpenIGTLink; a pose alone makes no sample)
  std::uint64_t restarts = 0;          // stream restarts (see restart_after_out_of_order)
  std::uint64_t connections = 0;       // OpenIGTLink connections made or accepted; DDS writers matched
  std::uint64_t disconnects = 0;       // and lost
  std::uint64_t connect_failures = 0;  // igtl://: attempts that failed (resolve, refused, timeout)
  [[nodiscard]] std::uint64_t of(DropReason r) const noexcept {
    return drops.at(static_cast<std::size_t>(r));
  }
  [[nodiscard]] std::uint64_t dropped() const noexcept {
    std::uint64_t n = 0;
    for (const std::uint64_t d : drops) {
      n += d;
    }
    return n;
  }
};

// What a source has to say to its operator: the first drop of each reason with its fix ("SENSOR
// from device 'X' ignored: set force_device=X"), connections, failures to connect. Numbered from 1.
struct SourceEvent {
  std::uint64_t seq = 0;
  bool warning = false;  // a drop or a failure; else information (a connection)
  std::string text;
};

// Called from a source's I/O thread after it queued a sample (e.g. to wake the loop early).
using ArrivalHook = void (*)(void* context) noexcept;

// A source with counters. stats() may be read from any thread.
class MRSKIN_BRIDGE_API StreamSource : public SlaveSource {
 public:
  [[nodiscard]] virtual SourceStats stats() const noexcept = 0;
  // Set before samples flow (not synchronised with an I/O thread already pushing).
  virtual void set_arrival_hook(ArrivalHook /*hook*/, void* /*context*/) noexcept {}
  // The port a listening source is bound to (useful with port 0), else 0.
  [[nodiscard]] virtual std::uint16_t local_port() const noexcept { return 0; }
  // Off the tick (allocates, locks): the events numbered after seq, oldest first (the last 64
  // are kept). event_count() is their count so far, wait-free: poll it, then fetch.
  [[nodiscard]] virtual std::vector<SourceEvent> events_after(std::uint64_t seq) const = 0;
  [[nodiscard]] virtual std::uint64_t event_count() const noexcept = 0;
  // Off the tick: the latest warning ("" when none): why no sample may be arriving.
  [[nodiscard]] virtual std::string last_warning() const = 0;
};

// Opens a source. Throws InvalidArgument for a bad URI (naming the bad part and listing the
// schemes), and mrskin::Error when a socket cannot be bound or a replay file read. clock: the
// loop's clock (arrival times, replay timing); nullptr: CLOCK_MONOTONIC.
// Query options (after '?'): udp/igtl*: queue=N; igtl*: force_device, pose_device, map_device,
// pose_tool (NAME or *), rpy_deg=ROLL,PITCH,YAW (the robot's frame, docs/sources.md); replay:
// speed=max|1, loop=0|1.
MRSKIN_BRIDGE_API std::unique_ptr<SlaveSource> make_source(std::string_view uri,
                                                           const SourceOptions& options = {},
                                                           Clock* clock = nullptr);
// The same for udp://, replay://, igtl:// and igtl-listen:// only, with the counters in reach.
MRSKIN_BRIDGE_API std::unique_ptr<StreamSource> open_stream(std::string_view uri,
                                                            const SourceOptions& options = {},
                                                            Clock* clock = nullptr);
// Checks a source URI as make_source would take it, opening nothing (no socket, no DDS
// participant): a scene's name, a query, an endpoint, a ROS 2 name, and that a replay file is
// readable. Throws as make_source does (InvalidArgument for the URI, mrskin::Error for the file).
MRSKIN_BRIDGE_API void check_source_uri(std::string_view uri, const SourceOptions& options = {});
// The robot's frame from roll, pitch and yaw in degrees (R = Rz(yaw) Ry(pitch) Rx(roll)), for
// SourceOptions::robot_to_tissue. Throws InvalidArgument for a value that is not finite.
MRSKIN_BRIDGE_API std::array<double, 9> rotation_from_rpy_deg(double roll_deg, double pitch_deg,
                                                              double yaw_deg);
// Every scheme make_source accepts, for messages and --help.
MRSKIN_BRIDGE_API std::span<const std::string_view> source_schemes() noexcept;

// ---- UDP datagram, format version 1 (docs/sources.md) ----------------------------------------
struct UdpSample {
  std::uint32_t sequence = 0;
  std::int64_t stamp_ns = 0;  // robot clock
  double force_N = 0.0;
  double indentation_m = 0.0;
  double contact_x_m = 0.0;
  double contact_y_m = 0.0;
  double tip_radius_m = 0.0;
};
inline constexpr std::size_t kUdpDatagramBytes = 68;
inline constexpr std::uint16_t kUdpVersion = 1;
// Little-endian, CRC-32C over bytes 0..63 at offset 64.
MRSKIN_BRIDGE_API std::array<std::uint8_t, kUdpDatagramBytes> encode_udp_sample(
    const UdpSample& sample) noexcept;
// CRC-32C (Castagnoli, reflected, init and final xor 0xFFFFFFFF); "123456789" -> 0xE3069283.
MRSKIN_BRIDGE_API std::uint32_t crc32c(std::span<const std::uint8_t> data) noexcept;

// ---- recording --------------------------------------------------------------------------------
// Records the samples the daemon uses to a replay file (format v1, docs/sources.md). record() is
// for the tick thread: wait-free, no allocation; a writer thread writes the file.
class MRSKIN_BRIDGE_API SampleRecorder {
 public:
  // Throws mrskin::Error when the file cannot be created.
  explicit SampleRecorder(const std::string& path, std::size_t capacity = 4096);
  SampleRecorder(const SampleRecorder&) = delete;
  SampleRecorder& operator=(const SampleRecorder&) = delete;
  SampleRecorder(SampleRecorder&&) = delete;
  SampleRecorder& operator=(SampleRecorder&&) = delete;
  ~SampleRecorder();  // close()
  // Queues a valid sample whose stamp differs from the previous one; false when the queue was full
  // (counted) or the sample was skipped.
  bool record(const SlaveSample& sample) noexcept;
  // Writes what is queued, closes the file and joins the writer. Idempotent; call it once the
  // tick no longer records.
  void close() noexcept;
  [[nodiscard]] std::uint64_t written() const noexcept { return written_.value(); }
  [[nodiscard]] std::uint64_t dropped() const noexcept { return dropped_.value(); }

 private:
  void run() noexcept;
  SpscQueue<SlaveSample> queue_;
  std::FILE* file_ = nullptr;
  std::atomic<bool> stop_{false};
  RelaxedCounter written_;
  RelaxedCounter dropped_;
  TimePoint last_stamp_{};
  bool have_last_ = false;
  std::thread writer_;
};

}  // namespace mrskin::bridge
