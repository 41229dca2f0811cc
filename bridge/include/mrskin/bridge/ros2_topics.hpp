// ROS 2 topics over DDS, without ROS installed (Cyclone DDS underneath, ROS 2's mapping: topics
// under rt/, types pkg::msg::dds_::Type_, plain CDR). The participant's configuration comes from
// CYCLONEDDS_URI, as for every Cyclone application.
//
// SkinPublisher: the skin for ROS 2 tools (ros2 topic echo, rosbag2) and any number of
// consoles, without ROS installed (docs/sources.md, "The skin's topics"). Under a namespace NS:
//   NS/operating_state       crtk_msgs/msg/OperatingState: DISABLED, ENABLED, PAUSED or FAULT
//   NS/cell_force/target     std_msgs/msg/Float64MultiArray: per cell, the force the bridge asks, N
//   NS/cell_force/estimated  the same layout: the force the observer estimates from the sensors, N
//   NS/cell_force/true       the same layout: the mock's true contact force, N (the mock only)
// Arrays are rows x cols, row-major (dim[0] "row", dim[1] "col"), NaN where no fluid cell is.
// Reliable, volatile, keep-last: what ROS 2's default QoS asks, so default-QoS tools match.
// Off the tick: publish() allocates, and may wait up to 10 ms for a slow reliable reader.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <string_view>

#include "mrskin/bridge/export.hpp"

namespace mrskin::bridge {

struct SkinTopicsOptions {
  std::string ns = "/mrskin";  // a ROS 2 namespace
  int domain = 0;              // 0..232
};

struct SkinFrame {
  std::int64_t stamp_ns = 0;       // the header stamp: wall-clock time since the epoch, as ROS 2 stamps
  const char* state = "DISABLED";  // a CRTK operating state
  bool busy = false;
  int rows = 0;
  int cols = 0;
  std::span<const double> target_N;     // rows x cols
  std::span<const double> estimated_N;  // rows x cols
  std::span<const double> true_N;       // rows x cols; empty: not published
};

// True when ROS 2 accepts name as a topic or namespace: tokens of [A-Za-z0-9_], not starting
// with a digit, joined by '/', absolute or relative.
MRSKIN_BRIDGE_API bool valid_ros_name(std::string_view name) noexcept;

class MRSKIN_BRIDGE_API SkinPublisher {
 public:
  // Joins the DDS domain (configured by CYCLONEDDS_URI) and creates the writers. Throws
  // InvalidArgument for a bad namespace or domain, mrskin::Error when DDS cannot start.
  explicit SkinPublisher(const SkinTopicsOptions& options);
  SkinPublisher(const SkinPublisher&) = delete;
  SkinPublisher& operator=(const SkinPublisher&) = delete;
  SkinPublisher(SkinPublisher&&) = delete;
  SkinPublisher& operator=(SkinPublisher&&) = delete;
  ~SkinPublisher();
  // False when a write failed (counted in failures()); never throws.
  bool publish(const SkinFrame& frame) noexcept;
  // Readers matched on operating_state: the consoles and tools listening.
  [[nodiscard]] int subscribers() const noexcept;
  [[nodiscard]] std::uint64_t published() const noexcept;
  [[nodiscard]] std::uint64_t failures() const noexcept;
  [[nodiscard]] const std::string& ns() const noexcept;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// A CRTK follower arm as a robot publishes it (what mrskin-follower sends and dds:// reads):
//   ARM/measured_cf  geometry_msgs/msg/WrenchStamped, N and N m, in the arm's base frame
//   ARM/measured_cp  geometry_msgs/msg/PoseStamped, m
// With ROS 2's default QoS for a publisher (reliable, volatile, keep last 10).
struct FollowerSample {
  std::int64_t stamp_ns = 0;  // the header stamp
  std::array<double, 3> force_N{};
  std::array<double, 3> torque_N_m{};
  std::array<double, 3> position_m{};
  std::array<double, 4> orientation_xyzw{0.0, 0.0, 0.0, 1.0};
};

class MRSKIN_BRIDGE_API FollowerPublisher {
 public:
  // arm: a ROS 2 namespace (PSM1, /dvrk/PSM1). Throws InvalidArgument for a bad name or domain,
  // mrskin::Error when DDS cannot start.
  FollowerPublisher(const std::string& arm, int domain);
  FollowerPublisher(const FollowerPublisher&) = delete;
  FollowerPublisher& operator=(const FollowerPublisher&) = delete;
  FollowerPublisher(FollowerPublisher&&) = delete;
  FollowerPublisher& operator=(FollowerPublisher&&) = delete;
  ~FollowerPublisher();
  // The pose, then the wrench. False when a write failed; never throws.
  bool publish(const FollowerSample& sample) noexcept;
  // Readers matched on the wrench topic.
  [[nodiscard]] int subscribers() const noexcept;
  [[nodiscard]] const std::string& wrench_topic() const noexcept;  // the ROS 2 names
  [[nodiscard]] const std::string& pose_topic() const noexcept;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace mrskin::bridge
