#include "mrskin/bridge/ros2_topics.hpp"

#include <array>
#include <string>
#include <vector>

#include "entities.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/relaxed_counter.hpp"
#include "ros2_messages.h"

namespace mrskin::bridge {

namespace {

using OperatingState = crtk_msgs_msg_dds__OperatingState_;
using Float64MultiArray = std_msgs_msg_dds__Float64MultiArray_;
using Dimension = std_msgs_msg_dds__MultiArrayDimension_;

constexpr int kDepth = 10;  // ROS 2's default history depth

dds::Entity make(int domain) {
  if (domain < 0 || domain > dds::kMaxDomain) {
    throw InvalidArgument("DDS domain " + std::to_string(domain) + " is not a domain id (0 to " +
                          std::to_string(dds::kMaxDomain) + ")");
  }
  return dds::make_participant(domain);
}

dds_entity_t make_writer(dds_entity_t p, const dds_topic_descriptor_t* desc, const std::string& ros_topic,
                         const dds_qos_t* qos) {
  const std::string topic = dds::dds_topic(ros_topic);
  const dds_entity_t t =
      dds::check(dds_create_topic(p, desc, topic.c_str(), nullptr, nullptr), "creating topic " + topic);
  return dds::check(dds_create_writer(p, t, qos, nullptr), "creating a writer of " + topic);
}

builtin_interfaces_msg_dds__Time_ ros_time(std::int64_t ns) noexcept {
  builtin_interfaces_msg_dds__Time_ t{};
  const std::int64_t sec = ns >= 0 ? ns / 1'000'000'000 : 0;
  t.sec = static_cast<std::int32_t>(sec);
  t.nanosec = ns >= 0 ? static_cast<std::uint32_t>(ns % 1'000'000'000) : 0U;
  return t;
}

}  // namespace

struct __attribute__((visibility("hidden"))) SkinPublisher::Impl {
  explicit Impl(const SkinTopicsOptions& o)
      : ns(dds::absolute_ros_name(o.ns, "skin namespace")), participant(make(o.domain)) {
    const dds_entity_t p = participant.get();
    const dds::Qos qos = dds::default_qos(kDepth);
    state = writer(p, &crtk_msgs_msg_dds__OperatingState__desc, "/operating_state", qos.get());
    for (std::size_t i = 0; i < arrays.size(); ++i) {
      arrays.at(i) = writer(p, &std_msgs_msg_dds__Float64MultiArray__desc,
                            std::string("/cell_force/") + kLeaves.at(i), qos.get());
    }
  }

  dds_entity_t writer(dds_entity_t p, const dds_topic_descriptor_t* desc, const std::string& leaf,
                      const dds_qos_t* qos) const {
    return make_writer(p, desc, ns + leaf, qos);
  }

  bool write_array(dds_entity_t w, int rows, int cols, std::span<const double> values) noexcept {
    const auto n = static_cast<std::uint32_t>(rows) * static_cast<std::uint32_t>(cols);
    if (values.size() != n) {
      return false;
    }
    std::array<Dimension, 2> dims{};
    dims[0] = Dimension{row_label.data(), static_cast<std::uint32_t>(rows), n};
    dims[1] = Dimension{col_label.data(), static_cast<std::uint32_t>(cols), static_cast<std::uint32_t>(cols)};
    Float64MultiArray m{};
    m.layout.dim._maximum = m.layout.dim._length = 2;
    m.layout.dim._buffer = dims.data();
    m.layout.dim._release = false;
    m.layout.data_offset = 0;
    m.data._maximum = m.data._length = n;
    m.data._buffer =
        const_cast<double*>(values.data());  // NOLINT(cppcoreguidelines-pro-type-const-cast): read only
    m.data._release = false;
    return dds_write(w, &m) == DDS_RETCODE_OK;
  }

  static constexpr std::array<const char*, 3> kLeaves{"target", "estimated", "true"};
  std::string ns;
  dds::Entity participant;
  dds_entity_t state = 0;
  std::array<dds_entity_t, 3> arrays{};
  std::array<char, 4> row_label{'r', 'o', 'w', '\0'};
  std::array<char, 4> col_label{'c', 'o', 'l', '\0'};
  std::string state_text;
  std::string frame_id;
  RelaxedCounter published;
  RelaxedCounter failures;
};

bool valid_ros_name(std::string_view name) noexcept { return dds::valid_ros_name(name); }

SkinPublisher::SkinPublisher(const SkinTopicsOptions& options) : impl_(std::make_unique<Impl>(options)) {}

SkinPublisher::~SkinPublisher() = default;

bool SkinPublisher::publish(const SkinFrame& f) noexcept {
  Impl& d = *impl_;
  bool ok = true;
  try {
    d.state_text = f.state != nullptr ? f.state : "";
  } catch (...) {
    ok = false;
  }
  OperatingState s{};
  s.header.stamp = ros_time(f.stamp_ns);
  s.header.frame_id = d.frame_id.data();
  s.state = d.state_text.data();
  s.is_homed = true;  // the skin has no axes to home
  s.is_busy = f.busy;
  ok = ok && dds_write(d.state, &s) == DDS_RETCODE_OK;
  ok = d.write_array(d.arrays[0], f.rows, f.cols, f.target_N) && ok;
  ok = d.write_array(d.arrays[1], f.rows, f.cols, f.estimated_N) && ok;
  if (!f.true_N.empty()) {
    ok = d.write_array(d.arrays[2], f.rows, f.cols, f.true_N) && ok;
  }
  (ok ? d.published : d.failures).bump();
  return ok;
}

int SkinPublisher::subscribers() const noexcept {
  dds_publication_matched_status_t st{};
  return dds_get_publication_matched_status(impl_->state, &st) == DDS_RETCODE_OK
             ? static_cast<int>(st.current_count)
             : 0;
}

std::uint64_t SkinPublisher::published() const noexcept { return impl_->published.value(); }
std::uint64_t SkinPublisher::failures() const noexcept { return impl_->failures.value(); }
const std::string& SkinPublisher::ns() const noexcept { return impl_->ns; }

struct __attribute__((visibility("hidden"))) FollowerPublisher::Impl {
  Impl(const std::string& arm, int domain)
      : wrench_topic(dds::absolute_ros_name(arm, "arm") + "/measured_cf"),
        pose_topic(dds::absolute_ros_name(arm, "arm") + "/measured_cp"),
        participant(make(domain)) {
    const dds::Qos qos = dds::default_qos(kDepth);
    wrench =
        make_writer(participant.get(), &geometry_msgs_msg_dds__WrenchStamped__desc, wrench_topic, qos.get());
    pose = make_writer(participant.get(), &geometry_msgs_msg_dds__PoseStamped__desc, pose_topic, qos.get());
    const std::string name = dds::absolute_ros_name(arm, "arm");
    frame_id = name.substr(name.rfind('/') + 1) + "_base";
  }
  std::string wrench_topic;
  std::string pose_topic;
  dds::Entity participant;
  dds_entity_t wrench = 0;
  dds_entity_t pose = 0;
  std::string frame_id;
};

FollowerPublisher::FollowerPublisher(const std::string& arm, int domain)
    : impl_(std::make_unique<Impl>(arm, domain)) {}

FollowerPublisher::~FollowerPublisher() = default;

bool FollowerPublisher::publish(const FollowerSample& s) noexcept {
  Impl& d = *impl_;
  geometry_msgs_msg_dds__PoseStamped_ pose{};
  pose.header.stamp = ros_time(s.stamp_ns);
  pose.header.frame_id = d.frame_id.data();
  pose.pose.position = {s.position_m[0], s.position_m[1], s.position_m[2]};
  pose.pose.orientation = {s.orientation_xyzw[0], s.orientation_xyzw[1], s.orientation_xyzw[2],
                           s.orientation_xyzw[3]};
  geometry_msgs_msg_dds__WrenchStamped_ wrench{};
  wrench.header = pose.header;
  wrench.wrench.force = {s.force_N[0], s.force_N[1], s.force_N[2]};
  wrench.wrench.torque = {s.torque_N_m[0], s.torque_N_m[1], s.torque_N_m[2]};
  const bool pose_ok = dds_write(d.pose, &pose) == DDS_RETCODE_OK;
  return dds_write(d.wrench, &wrench) == DDS_RETCODE_OK && pose_ok;
}

int FollowerPublisher::subscribers() const noexcept {
  dds_publication_matched_status_t st{};
  return dds_get_publication_matched_status(impl_->wrench, &st) == DDS_RETCODE_OK
             ? static_cast<int>(st.current_count)
             : 0;
}

const std::string& FollowerPublisher::wrench_topic() const noexcept { return impl_->wrench_topic; }
const std::string& FollowerPublisher::pose_topic() const noexcept { return impl_->pose_topic; }

}  // namespace mrskin::bridge
