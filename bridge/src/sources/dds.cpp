// dds://ARM: a CRTK follower's measured wrench and pose, as ROS 2 publishes them over DDS
// (geometry_msgs/WrenchStamped on /ARM/measured_cf, geometry_msgs/PoseStamped on /ARM/measured_cp),
// read with Cyclone DDS and ROS 2's sensor-data QoS. The force vector and the pose enter the same
// mapping as OpenIGTLink's: rotated into the tissue frame, the normal component is the contact force.
// Staleness is measured from arrival (the mapped stamp never runs ahead of it); the header stamps
// give the order. A writer lost (matched count down, or no writer alive) fades the bridge at once.
#include <fmt/format.h>
#include <pthread.h>

#include <array>
#include <cmath>
#include <cstring>
#include <thread>

#include "../dds/entities.hpp"
#include "core.hpp"
#include "mrskin/driver/errors.hpp"
#include "ros2_messages.h"

namespace mrskin::bridge::sources {
namespace {

using WrenchStamped = geometry_msgs_msg_dds__WrenchStamped_;
using PoseStamped = geometry_msgs_msg_dds__PoseStamped_;

constexpr std::uint32_t kBatch = 32;  // samples taken per dds_take

bool finite3(double x, double y, double z) noexcept {
  return std::isfinite(x) && std::isfinite(y) && std::isfinite(z);
}

// One reader of a topic, with what its log lines need.
struct Channel {
  dds_entity_t reader = 0;
  std::string topic;  // the DDS topic, rt/...
  std::string ros_type;
  std::uint32_t matched = 0;
};

class DdsSource final : public QueuedSource {
 public:
  DdsSource(const std::string& wrench_topic, const std::string& pose_topic, const SourceOptions& options,
            Clock* clock)
      : QueuedSource(options, clock),
        participant_(dds::make_participant(options.dds_domain)),
        force_gate_(options.restart_after_out_of_order),
        pose_gate_(options.restart_after_out_of_order),
        mapper_(options.offset_drift_s_per_s) {
    const dds_entity_t p = participant_.get();
    const dds::Qos qos = dds::sensor_data_qos();
    wrench_ = open(p, &geometry_msgs_msg_dds__WrenchStamped__desc, wrench_topic, qos.get(),
                   "geometry_msgs/msg/WrenchStamped");
    pose_ = open(p, &geometry_msgs_msg_dds__PoseStamped__desc, pose_topic, qos.get(),
                 "geometry_msgs/msg/PoseStamped");
    // Discovery: a writer on our topic with another type never matches; say so.
    publications_ = dds::check(dds_create_reader(p, DDS_BUILTIN_TOPIC_DCPSPUBLICATION, nullptr, nullptr),
                               "reading the publications seen");
    waitset_ = dds::check(dds_create_waitset(p), "creating a waitset");
    stop_ = dds::check(dds_create_guardcondition(p), "creating a guard condition");
    for (const dds_entity_t e : {wrench_.reader, pose_.reader}) {
      (void)dds::check(dds_set_status_mask(e, DDS_DATA_AVAILABLE_STATUS | DDS_SUBSCRIPTION_MATCHED_STATUS),
                       "setting a status mask");
    }
    (void)dds::check(dds_set_status_mask(publications_, DDS_DATA_AVAILABLE_STATUS), "setting a status mask");
    for (const dds_entity_t e : {wrench_.reader, pose_.reader, publications_, stop_}) {
      (void)dds::check(dds_waitset_attach(waitset_, e, e), "attaching to the waitset");
    }
    events_.add(false, fmt::format("dds: listening on {} and {} (domain {})", wrench_.topic, pose_.topic,
                                   options.dds_domain));
    dds::watch_malformed(this, [](void* self, std::string_view topic) noexcept {
      static_cast<DdsSource*>(self)->malformed(topic);
    });
    try {
      thread_ = std::thread([this] {
        (void)::pthread_setname_np(::pthread_self(), "mrskin-dds");
        run();
      });
    } catch (...) {
      dds::unwatch_malformed(this);  // no destructor runs: leave no hook to this object behind
      throw;
    }
  }
  DdsSource(const DdsSource&) = delete;
  DdsSource& operator=(const DdsSource&) = delete;
  DdsSource(DdsSource&&) = delete;
  DdsSource& operator=(DdsSource&&) = delete;
  ~DdsSource() override {
    dds::unwatch_malformed(this);
    (void)dds_set_guardcondition(stop_, true);
    thread_.join();
  }  // participant_ deletes every entity under it

 private:
  static Channel open(dds_entity_t p, const dds_topic_descriptor_t* desc, const std::string& ros_topic,
                      const dds_qos_t* qos, const char* ros_type) {
    Channel c;
    c.topic = dds::dds_topic(ros_topic);
    c.ros_type = ros_type;
    const dds_entity_t topic =
        dds::check(dds_create_topic(p, desc, c.topic.c_str(), nullptr, nullptr), "creating topic " + c.topic);
    c.reader = dds::check(dds_create_reader(p, topic, qos, nullptr), "creating a reader of " + c.topic);
    return c;
  }

  void run() noexcept {
    std::array<dds_attach_t, 4> triggered{};
    for (;;) {
      (void)dds_waitset_wait(waitset_, triggered.data(), triggered.size(), DDS_MSECS(500));
      bool stopping = false;
      if (dds_read_guardcondition(stop_, &stopping) < 0 || stopping) {
        return;
      }
      flush_pending();
      take_publications();
      take(pose_, [this](const void* s, TimePoint) { pose(*static_cast<const PoseStamped*>(s)); });
      take(wrench_, [this](const void* s, TimePoint arrival) {
        wrench(*static_cast<const WrenchStamped*>(s), arrival);
      });
      matched(pose_);
      matched(wrench_);
    }
  }

  template <class Each>
  void take(const Channel& c, Each&& each) noexcept {
    std::array<void*, kBatch> samples{};
    std::array<dds_sample_info_t, kBatch> infos{};
    for (;;) {
      samples[0] = nullptr;  // loaned from the reader
      const dds_return_t n = dds_take(c.reader, samples.data(), infos.data(), kBatch, kBatch);
      if (n <= 0) {
        return;
      }
      const TimePoint arrival = now();
      for (std::size_t i = 0; i < static_cast<std::size_t>(n); ++i) {
        if (infos.at(i).valid_data) {
          each(samples.at(i), arrival);
        } else if (infos.at(i).instance_state != DDS_IST_ALIVE) {
          end(c, "no writer is alive any more");
        }
      }
      (void)dds_return_loan(c.reader, samples.data(), n);
      if (static_cast<std::uint32_t>(n) < kBatch) {
        return;
      }
    }
  }

  void matched(Channel& c) noexcept {
    dds_subscription_matched_status_t st{};
    if (dds_get_subscription_matched_status(c.reader, &st) < 0 || st.current_count == c.matched) {
      return;
    }
    if (st.current_count > c.matched) {
      stats_.connections.bump(std::uint64_t{st.current_count - c.matched});
      note(false,
           [&] { return fmt::format("dds: a publisher matched on {} ({} now)", c.topic, st.current_count); });
    } else {
      stats_.disconnects.bump(std::uint64_t{c.matched - st.current_count});
      end(c, fmt::format("a publisher went away ({} left)", st.current_count));
    }
    c.matched = st.current_count;
  }

  // The follower stopped: the bridge fades now rather than after its hold.
  template <class Why>
  void end(const Channel& c, const Why& why) noexcept {
    note(true, [&] { return fmt::format("dds: {} on {}: fading to released", why, c.topic); });
    if (last_sent_.valid && !last_sent_.ended) {
      last_sent_.ended = true;
      enqueue(last_sent_);
    }
  }

  void take_publications() noexcept {
    std::array<void*, kBatch> samples{};
    std::array<dds_sample_info_t, kBatch> infos{};
    samples[0] = nullptr;
    const dds_return_t n = dds_take(publications_, samples.data(), infos.data(), kBatch, kBatch);
    if (n <= 0) {
      return;
    }
    for (std::size_t i = 0; i < static_cast<std::size_t>(n); ++i) {
      if (!infos.at(i).valid_data || infos.at(i).instance_state != DDS_IST_ALIVE) {
        continue;
      }
      const auto* ep = static_cast<const dds_builtintopic_endpoint_t*>(samples.at(i));
      for (const Channel* c : {&wrench_, &pose_}) {
        if (ep->topic_name != nullptr && ep->type_name != nullptr && c->topic == ep->topic_name &&
            std::strcmp(ep->type_name, expected_type(*c)) != 0) {
          stats_.count(DropReason::type);
          events_.once(static_cast<unsigned>(EventKey::dds_type), true, [&] {
            return fmt::format(
                "dds: a publisher on {} sends {}, which never matches: dds:// reads {} there (or "
                "set wrench= / pose= to the topic that carries it)",
                c->topic, ep->type_name, c->ros_type);
          });
        }
      }
    }
    (void)dds_return_loan(publications_, samples.data(), n);
  }

  // A sample on one of our topics that the DDS stack could not deserialize (Cyclone's receive
  // thread): counted, and the first explained.
  void malformed(std::string_view topic) noexcept {
    for (const Channel* c : {&wrench_, &pose_}) {
      if (c->topic == topic) {
        drop(stats_, events_, DropReason::format, [&] {
          return fmt::format(
              "dds: a sample on {} that is not valid CDR for {} was refused by the DDS stack (the "
              "publisher's "
              "type differs from ROS 2's definition?)",
              c->topic, c->ros_type);
        });
      }
    }
  }

  [[nodiscard]] const char* expected_type(const Channel& c) const noexcept {
    return &c == &wrench_ ? geometry_msgs_msg_dds__WrenchStamped__desc.m_typename
                          : geometry_msgs_msg_dds__PoseStamped__desc.m_typename;
  }

  // The header's stamp in ns; 0 when unstamped (sec = nanosec = 0: many publishers leave it so),
  // -1 when malformed (counted).
  std::int64_t stamp_ns(const builtin_interfaces_msg_dds__Time_& t, const Channel& c) noexcept {
    if (t.sec < 0 || t.nanosec >= 1'000'000'000U) {
      drop(stats_, events_, DropReason::stamp, [&] {
        return fmt::format("dds: a sample on {} dropped: its header stamp {} s + {} ns is not a time",
                           c.topic, t.sec, t.nanosec);
      });
      return -1;
    }
    return std::int64_t{t.sec} * 1'000'000'000 + std::int64_t{t.nanosec};
  }

  bool ordered(OrderGate& gate, std::int64_t ns, const Channel& c) noexcept {
    if (ns == 0) {
      return true;  // unstamped: arrival order
    }
    return admit(gate, ns, mapper_, stats_, events_, &c == &wrench_ ? "dds: a wrench" : "dds: a pose");
  }

  void pose(const PoseStamped& m) noexcept {
    const auto& p = m.pose.position;
    const auto& q = m.pose.orientation;
    if (!finite3(p.x, p.y, p.z) || !finite3(q.x, q.y, q.z) || !std::isfinite(q.w)) {
      drop(stats_, events_, DropReason::non_finite, [&] {
        return fmt::format("dds: a pose on {} dropped: NaN or Inf in its position or orientation",
                           pose_.topic);
      });
      return;
    }
    const std::int64_t ns = stamp_ns(m.header.stamp, pose_);
    const std::array<double, 3> t = rotate(options_.robot_to_tissue, p.x, p.y, p.z);
    SlaveSample check;
    check.contact_x_m = t[0] + options_.robot_origin_m[0];
    check.contact_y_m = t[1] + options_.robot_origin_m[1];
    check.indentation_m = -(t[2] + options_.robot_origin_m[2]);
    if (ns < 0 || !values_ok(check, options_, stats_, events_) || !ordered(pose_gate_, ns, pose_)) {
      return;
    }
    where_ = check;
    stats_.poses.bump();
  }

  void wrench(const WrenchStamped& m, TimePoint arrival) noexcept {
    const auto& f = m.wrench.force;
    const auto& tq = m.wrench.torque;
    if (!finite3(f.x, f.y, f.z) || !finite3(tq.x, tq.y, tq.z)) {
      drop(stats_, events_, DropReason::non_finite, [&] {
        return fmt::format("dds: a wrench on {} dropped: NaN or Inf in its force or torque", wrench_.topic);
      });
      return;
    }
    const std::int64_t ns = stamp_ns(m.header.stamp, wrench_);
    if (ns < 0) {
      return;
    }
    // The force the tissue exerts on the tool, rotated into the tissue frame: its component along
    // the outward normal is the contact force; pulling (< 0) is no contact.
    const double normal_N = rotate(options_.robot_to_tissue, f.x, f.y, f.z)[2];
    SlaveSample s = where_;
    s.force_N = std::max(normal_N, 0.0);
    s.tip_radius_m = options_.tip_radius_m;
    if (!values_ok(s, options_, stats_, events_) || !ordered(force_gate_, ns, wrench_)) {
      return;
    }
    s.stamp = ns == 0 ? arrival : mapper_.map(ns, arrival);
    s.received = arrival;
    s.valid = true;
    s.ended = false;
    publish(s);
    last_sent_ = s;
  }

  template <class MakeText>
  void note(bool warning, MakeText&& make_text) noexcept {
    try {
      events_.add(warning, make_text());
    } catch (...) {  // NOLINT(bugprone-empty-catch): an event lost to a full heap
    }
  }

  dds::Entity participant_;
  Channel wrench_;
  Channel pose_;
  dds_entity_t publications_ = 0;
  dds_entity_t waitset_ = 0;
  dds_entity_t stop_ = 0;
  OrderGate force_gate_;
  OrderGate pose_gate_;
  ClockMapper mapper_;
  SlaveSample where_{};      // the latest pose: contact point and indentation
  SlaveSample last_sent_{};  // the latest sample published
  std::thread thread_;
};

}  // namespace

std::unique_ptr<StreamSource> open_dds(const std::string& wrench_topic, const std::string& pose_topic,
                                       const SourceOptions& options, Clock* clock) {
  return std::make_unique<DdsSource>(wrench_topic, pose_topic, options, clock);
}

}  // namespace mrskin::bridge::sources
