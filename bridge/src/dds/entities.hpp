// Cyclone DDS's C API, owned: entities deleted on scope exit, return codes turned into typed
// errors at setup, and ROS 2's naming and QoS conventions in one place (docs/sources.md).
// Private to the bridge library.
#pragma once

#include <dds/dds.h>

#include <memory>
#include <string>
#include <string_view>

namespace mrskin::bridge::dds {

// An owned entity (participant, topic, reader, writer, waitset, condition): dds_delete on
// destruction deletes its children too.
class Entity {
 public:
  Entity() = default;
  explicit Entity(dds_entity_t e) noexcept : e_(e) {}
  Entity(const Entity&) = delete;
  Entity& operator=(const Entity&) = delete;
  Entity(Entity&& o) noexcept : e_(o.e_) { o.e_ = 0; }
  Entity& operator=(Entity&& o) noexcept;
  ~Entity() { reset(); }
  [[nodiscard]] dds_entity_t get() const noexcept { return e_; }
  void reset() noexcept;

 private:
  dds_entity_t e_ = 0;
};

// rc when it is an entity or DDS_RETCODE_OK; otherwise throws mrskin::Error naming what failed
// and Cyclone's reason.
dds_entity_t check(dds_entity_t rc, std::string_view what);

// A domain participant. Its configuration comes from CYCLONEDDS_URI as for every Cyclone
// application (docs/sources.md: pin tests to loopback). Throws mrskin::Error with a hint.
Entity make_participant(int domain);

// QoS owned.
struct QosDeleter {
  void operator()(dds_qos_t* q) const noexcept { dds_delete_qos(q); }
};
using Qos = std::unique_ptr<dds_qos_t, QosDeleter>;
// ROS 2's sensor-data profile (rmw_qos_profile_sensor_data): best effort, volatile, keep last 5;
// deadline and liveliness at their defaults (infinite, automatic), or no ROS 2 writer matches.
Qos sensor_data_qos();
// ROS 2's default profile (rmw_qos_profile_default): reliable, volatile, keep last depth; what
// `ros2 topic echo` and rosbag2 ask for by default.
Qos default_qos(int depth);

// ROS 2 names: tokens of [A-Za-z0-9_] (not starting with a digit) joined by '/', absolute or
// relative to the root namespace. True when ROS 2 would accept name.
bool valid_ros_name(std::string_view name) noexcept;
// "/a/b" or "a/b" -> "/a/b". Throws InvalidArgument naming what for a name ROS 2 refuses.
std::string absolute_ros_name(std::string_view name, std::string_view what);
// The DDS topic of a ROS 2 topic (a DDS-based RMW's mapping): "/a/b" -> "rt/a/b".
std::string dds_topic(std::string_view ros_name);

// Cyclone refuses a sample that is not valid CDR for its type before any reader sees it, and says
// so only in its log ("deserialization TOPIC/TYPE failed"). While a watcher is registered, a log
// sink passes each such topic to every watcher (from Cyclone's receive threads) and writes every
// other message to stderr as Cyclone's default sink does.
using MalformedHook = void (*)(void* context, std::string_view dds_topic) noexcept;
void watch_malformed(void* context, MalformedHook hook);
void unwatch_malformed(void* context) noexcept;  // no call for context once it returns

// The largest domain id of the RTPS port mapping (7400 + 250 d + 11 < 65536).
inline constexpr int kMaxDomain = 232;

}  // namespace mrskin::bridge::dds
