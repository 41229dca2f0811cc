// mrskin_fastdds_peer: an interoperability peer built on Fast DDS 2.9, not on Cyclone DDS. It behaves as
// a ROS 2 Humble node on rmw_fastrtps would (topic and type names, XCDR1 encoding, default QoS), so the
// project's Cyclone side is checked against an independent DDS stack and an independent CDR encoder.
// Network safety: the participant talks to 127.0.0.1 only and never uses multicast.

#include <fastcdr/Cdr.h>
#include <fastcdr/FastBuffer.h>
#include <fastcdr/exceptions/Exception.h>
#include <fastcdr/exceptions/NotEnoughMemoryException.h>
#include <fastdds/rtps/common/SerializedPayload.h>
#include <fastdds/rtps/transport/UDPv4TransportDescriptor.h>
#include <fastrtps/utils/IPLocator.h>

#include <algorithm>
#include <atomic>
#include <charconv>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fastdds/dds/domain/DomainParticipant.hpp>
#include <fastdds/dds/domain/DomainParticipantFactory.hpp>
#include <fastdds/dds/domain/qos/DomainParticipantQos.hpp>
#include <fastdds/dds/publisher/DataWriter.hpp>
#include <fastdds/dds/publisher/Publisher.hpp>
#include <fastdds/dds/publisher/qos/DataWriterQos.hpp>
#include <fastdds/dds/subscriber/DataReader.hpp>
#include <fastdds/dds/subscriber/DataReaderListener.hpp>
#include <fastdds/dds/subscriber/SampleInfo.hpp>
#include <fastdds/dds/subscriber/Subscriber.hpp>
#include <fastdds/dds/subscriber/qos/DataReaderQos.hpp>
#include <fastdds/dds/topic/Topic.hpp>
#include <fastdds/dds/topic/TopicDataType.hpp>
#include <fastdds/dds/topic/TypeSupport.hpp>
#include <functional>
#include <iostream>
#include <limits>
#include <memory>
#include <mutex>
#include <optional>
#include <stdexcept>
#include <string>
#include <thread>
#include <type_traits>
#include <vector>

namespace {

namespace dds = eprosima::fastdds::dds;
namespace rtps = eprosima::fastrtps::rtps;
namespace cdr = eprosima::fastcdr;
using eprosima::fastrtps::types::ReturnCode_t;
using Clock = std::chrono::steady_clock;

// ---------------------------------------------------------------------------------------------------
// ROS 2 messages, as rosidl maps them to DDS IDL (pkg::msg::dds_::Name_): final, keyless, XCDR1.

struct Time {
  int32_t sec = 0;
  uint32_t nanosec = 0;
};
struct Header {
  Time stamp;
  std::string frame_id;
};
struct Vector3 {
  double x = 0, y = 0, z = 0;
};
struct Wrench {
  Vector3 force, torque;
};
struct WrenchStamped {
  static constexpr const char* kTypeName = "geometry_msgs::msg::dds_::WrenchStamped_";
  Header header;
  Wrench wrench;
};
// Malformed on purpose (publish-malformed): a WrenchStamped by name, but its frame_id claims
// 1000 bytes that never come. A conforming reader must refuse it.
struct TruncatedWrench {
  static constexpr const char* kTypeName = "geometry_msgs::msg::dds_::WrenchStamped_";
  Time stamp;
  uint32_t frame_id_length = 1000;
};
struct Point {
  double x = 0, y = 0, z = 0;
};
struct Quaternion {
  double x = 0, y = 0, z = 0, w = 1;
};
struct Pose {
  Point position;
  Quaternion orientation;
};
struct PoseStamped {
  static constexpr const char* kTypeName = "geometry_msgs::msg::dds_::PoseStamped_";
  Header header;
  Pose pose;
};
struct MultiArrayDimension {
  std::string label;
  uint32_t size = 0;
  uint32_t stride = 0;
};
struct MultiArrayLayout {
  std::vector<MultiArrayDimension> dim;
  uint32_t data_offset = 0;
};
struct Float64MultiArray {
  static constexpr const char* kTypeName = "std_msgs::msg::dds_::Float64MultiArray_";
  MultiArrayLayout layout;
  std::vector<double> data;
};
struct OperatingState {
  static constexpr const char* kTypeName = "crtk_msgs::msg::dds_::OperatingState_";
  Header header;
  std::string state;
  bool is_homed = false;
  bool is_busy = false;
};

// Field order is wire order. One visitor drives serialisation, deserialisation and sizing, so the three
// cannot disagree.
template <class A>
void visit(A& a, Time& m) {
  a(m.sec), a(m.nanosec);
}
template <class A>
void visit(A& a, Header& m) {
  a(m.stamp), a(m.frame_id);
}
template <class A>
void visit(A& a, Vector3& m) {
  a(m.x), a(m.y), a(m.z);
}
template <class A>
void visit(A& a, Wrench& m) {
  a(m.force), a(m.torque);
}
template <class A>
void visit(A& a, TruncatedWrench& m) {
  a(m.stamp), a(m.frame_id_length);
}
template <class A>
void visit(A& a, WrenchStamped& m) {
  a(m.header), a(m.wrench);
}
template <class A>
void visit(A& a, Point& m) {
  a(m.x), a(m.y), a(m.z);
}
template <class A>
void visit(A& a, Quaternion& m) {
  a(m.x), a(m.y), a(m.z), a(m.w);
}
template <class A>
void visit(A& a, Pose& m) {
  a(m.position), a(m.orientation);
}
template <class A>
void visit(A& a, PoseStamped& m) {
  a(m.header), a(m.pose);
}
template <class A>
void visit(A& a, MultiArrayDimension& m) {
  a(m.label), a(m.size), a(m.stride);
}
template <class A>
void visit(A& a, MultiArrayLayout& m) {
  a(m.dim), a(m.data_offset);
}
template <class A>
void visit(A& a, Float64MultiArray& m) {
  a(m.layout), a(m.data);
}
template <class A>
void visit(A& a, OperatingState& m) {
  a(m.header), a(m.state), a(m.is_homed), a(m.is_busy);
}

template <class T>
struct IsVector : std::false_type {};
template <class E>
struct IsVector<std::vector<E>> : std::true_type {};
template <class T>
constexpr bool kIsPrimitive = std::is_arithmetic_v<T> || std::is_same_v<T, std::string>;

// CDR sequence: uint32 length, then the elements, each aligned to its own size.
class CdrWriter {
 public:
  explicit CdrWriter(cdr::Cdr& c) : cdr_(c) {}
  template <class T>
  void operator()(T& v) {
    if constexpr (kIsPrimitive<T>) {
      cdr_.serialize(v);
    } else if constexpr (IsVector<T>::value) {
      cdr_.serialize(static_cast<uint32_t>(v.size()));
      for (auto& e : v) {
        (*this)(e);
      }
    } else {
      visit(*this, v);
    }
  }

 private:
  cdr::Cdr& cdr_;
};

class CdrReader {
 public:
  CdrReader(cdr::Cdr& c, size_t buffer_size) : cdr_(c), size_(buffer_size) {}
  template <class T>
  void operator()(T& v) {
    if constexpr (kIsPrimitive<T>) {
      cdr_.deserialize(v);
    } else if constexpr (IsVector<T>::value) {
      uint32_t n = 0;
      cdr_.deserialize(n);
      // Every element takes at least one byte: a corrupt length must not trigger a huge allocation.
      if (n > size_ - cdr_.getSerializedDataLength()) {
        throw cdr::exception::NotEnoughMemoryException("sequence longer than the payload");
      }
      v.resize(n);
      for (auto& e : v) {
        (*this)(e);
      }
    } else {
      visit(*this, v);
    }
  }

 private:
  cdr::Cdr& cdr_;
  size_t size_;
};

// Exact XCDR1 size after the encapsulation header (Fast DDS sizes the payload from it).
class CdrSizer {
 public:
  template <class T>
  void operator()(T& v) {
    if constexpr (std::is_same_v<T, std::string>) {
      align(4);
      size += 4 + v.size() + 1;
    } else if constexpr (std::is_arithmetic_v<T>) {
      align(sizeof(T));
      size += sizeof(T);
    } else if constexpr (IsVector<T>::value) {
      align(4);
      size += 4;
      for (auto& e : v) {
        (*this)(e);
      }
    } else {
      visit(*this, v);
    }
  }
  size_t size = 0;

 private:
  void align(size_t n) { size = (size + n - 1) / n * n; }
};

constexpr uint32_t kEncapsulationSize = 4;
constexpr uint32_t kMaxPayload = 64 * 1024 + kEncapsulationSize;

// The TopicDataType fastddsgen 2.x would generate for M, written by hand (fastddsgen is not in Debian).
template <class M>
class RosType final : public dds::TopicDataType {
 public:
  RosType() {
    setName(M::kTypeName);
    m_typeSize = kMaxPayload;
    m_isGetKeyDefined = false;
    // No XTypes TypeObject/TypeInformation: endpoints match by type name, as with Cyclone's ROS 2 types.
    auto_fill_type_object(false);
    auto_fill_type_information(false);
  }

  bool serialize(void* data, rtps::SerializedPayload_t* payload) override {
    cdr::FastBuffer buffer(reinterpret_cast<char*>(payload->data), payload->max_size);
    cdr::Cdr ser(buffer, cdr::Cdr::DEFAULT_ENDIAN, cdr::Cdr::DDS_CDR);
    payload->encapsulation = ser.endianness() == cdr::Cdr::BIG_ENDIANNESS ? CDR_BE : CDR_LE;
    try {
      ser.serialize_encapsulation();
      CdrWriter writer(ser);
      writer(*static_cast<M*>(data));
    } catch (const cdr::exception::Exception&) {
      return false;
    }
    payload->length = static_cast<uint32_t>(ser.getSerializedDataLength());
    return true;
  }

  bool deserialize(rtps::SerializedPayload_t* payload, void* data) override {
    cdr::FastBuffer buffer(reinterpret_cast<char*>(payload->data), payload->length);
    cdr::Cdr deser(buffer, cdr::Cdr::DEFAULT_ENDIAN, cdr::Cdr::DDS_CDR);
    try {
      deser.read_encapsulation();
      payload->encapsulation = deser.endianness() == cdr::Cdr::BIG_ENDIANNESS ? CDR_BE : CDR_LE;
      CdrReader reader(deser, payload->length);
      reader(*static_cast<M*>(data));
    } catch (const cdr::exception::Exception&) {
      return false;
    }
    return true;
  }

  std::function<uint32_t()> getSerializedSizeProvider(void* data) override {
    return [data]() {
      CdrSizer sizer;
      sizer(*static_cast<M*>(data));
      return static_cast<uint32_t>(sizer.size) + kEncapsulationSize;
    };
  }

  void* createData() override { return new M(); }
  void deleteData(void* data) override { delete static_cast<M*>(data); }
  bool getKey(void* /*data*/, rtps::InstanceHandle_t* /*ihandle*/, bool /*force_md5*/) override {
    return false;
  }
};

// ---------------------------------------------------------------------------------------------------
// Participant confined to loopback.

std::atomic<bool> g_stop{false};
static_assert(std::atomic<bool>::is_always_lock_free);

void on_signal(int /*signal*/) { g_stop = true; }

void install_signal_handlers() {
  struct sigaction sa {};
  sa.sa_handler = on_signal;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGINT, &sa, nullptr);
  sigaction(SIGTERM, &sa, nullptr);
}

// Sleeps up to `s` seconds; false once a signal asked us to stop.
bool sleep_for_s(double s) {
  std::this_thread::sleep_for(std::chrono::duration<double>(s));
  return !g_stop;
}

rtps::Locator_t loopback(uint32_t port) {
  rtps::Locator_t locator;
  rtps::IPLocator::createLocator(LOCATOR_KIND_UDPv4, "127.0.0.1", port, locator);
  return locator;
}

// RTPS well-known ports (PB 7400, DG 250, PG 2, d0 10).
uint32_t discovery_port(uint32_t domain, uint32_t index) { return 7400 + 250 * domain + 10 + 2 * index; }
constexpr uint32_t kPeerIndices = 20;  // Cyclone's MaxAutoParticipantIndex 19

dds::DomainParticipantQos loopback_participant_qos(uint32_t domain) {
  dds::DomainParticipantQos qos;
  qos.name("mrskin_fastdds_peer");
  const std::string enclave = "enclave=/;";  // what rmw_fastrtps puts in the participant's user data
  qos.user_data().data_vec(std::vector<rtps::octet>(enclave.begin(), enclave.end()));

  // No builtin transports: they would add shared memory and every interface.
  qos.transport().use_builtin_transports = false;
  auto udp = std::make_shared<eprosima::fastdds::rtps::UDPv4TransportDescriptor>();
  udp->interfaceWhiteList = {"127.0.0.1"};
  udp->TTL = 0;  // belt and braces: a multicast datagram could not leave the host
  qos.transport().user_transports = {udp};

  auto& wire = qos.wire_protocol();
  auto& builtin = wire.builtin;
  builtin.metatrafficMulticastLocatorList.clear();
  builtin.metatrafficUnicastLocatorList.clear();
  builtin.metatrafficUnicastLocatorList.push_back(loopback(0));  // port 0: Fast DDS fills the RTPS port
  builtin.avoid_builtin_multicast = true;
  builtin.initialPeersList.clear();
  for (uint32_t i = 0; i < kPeerIndices; ++i) {
    builtin.initialPeersList.push_back(loopback(discovery_port(domain, i)));
  }
  wire.default_unicast_locator_list.clear();
  wire.default_unicast_locator_list.push_back(loopback(0));
  wire.default_multicast_locator_list.clear();
  // Drop locators announced by remote peers that our transport may not use (non-loopback).
  wire.ignore_non_matching_locators = true;
  return qos;
}

// ROS 2 default publisher/subscription QoS (rmw_qos_profile_default) as rmw_fastrtps (Humble) sets it.
dds::DataWriterQos ros_default_writer_qos() {
  dds::DataWriterQos qos = dds::DATAWRITER_QOS_DEFAULT;
  qos.reliability().kind = dds::RELIABLE_RELIABILITY_QOS;
  qos.durability().kind = dds::VOLATILE_DURABILITY_QOS;  // Fast DDS's own default is transient local
  qos.history().kind = dds::KEEP_LAST_HISTORY_QOS;
  qos.history().depth = 10;
  qos.publish_mode().kind = dds::SYNCHRONOUS_PUBLISH_MODE;
  qos.endpoint().history_memory_policy = rtps::PREALLOCATED_WITH_REALLOC_MEMORY_MODE;
  qos.data_sharing().off();
  return qos;
}

dds::DataReaderQos reader_qos(dds::ReliabilityQosPolicyKind reliability, int32_t depth) {
  dds::DataReaderQos qos = dds::DATAREADER_QOS_DEFAULT;
  qos.reliability().kind = reliability;
  qos.durability().kind = dds::VOLATILE_DURABILITY_QOS;
  qos.history().kind = dds::KEEP_LAST_HISTORY_QOS;
  qos.history().depth = depth;
  qos.endpoint().history_memory_policy = rtps::PREALLOCATED_WITH_REALLOC_MEMORY_MODE;
  qos.data_sharing().off();
  return qos;
}
dds::DataReaderQos ros_default_reader_qos() { return reader_qos(dds::RELIABLE_RELIABILITY_QOS, 10); }
dds::DataReaderQos ros_sensor_data_qos() { return reader_qos(dds::BEST_EFFORT_RELIABILITY_QOS, 5); }

// Owns one participant and everything in it; destroy it before any listener it uses.
class Participant {
 public:
  explicit Participant(uint32_t domain) {
    auto* factory = dds::DomainParticipantFactory::get_instance();
    participant_ = factory->create_participant(domain, loopback_participant_qos(domain));
    if (participant_ == nullptr) {
      throw std::runtime_error("cannot create the Fast DDS participant");
    }
  }
  ~Participant() {
    participant_->delete_contained_entities();
    dds::DomainParticipantFactory::get_instance()->delete_participant(participant_);
  }
  Participant(const Participant&) = delete;
  Participant& operator=(const Participant&) = delete;

  template <class M>
  dds::DataWriter* writer(const std::string& topic_name, const dds::DataWriterQos& qos) {
    if (publisher_ == nullptr) {
      publisher_ = participant_->create_publisher(dds::PUBLISHER_QOS_DEFAULT);
    }
    if (publisher_ == nullptr) {
      throw std::runtime_error("cannot create the publisher");
    }
    auto* w = publisher_->create_datawriter(topic<M>(topic_name), qos);
    if (w == nullptr) {
      throw std::runtime_error("cannot create a writer on " + topic_name);
    }
    return w;
  }

  template <class M>
  dds::DataReader* reader(const std::string& topic_name, const dds::DataReaderQos& qos,
                          dds::DataReaderListener* listener) {
    if (subscriber_ == nullptr) {
      subscriber_ = participant_->create_subscriber(dds::SUBSCRIBER_QOS_DEFAULT);
    }
    if (subscriber_ == nullptr) {
      throw std::runtime_error("cannot create the subscriber");
    }
    auto* r = subscriber_->create_datareader(topic<M>(topic_name), qos, listener);
    if (r == nullptr) {
      throw std::runtime_error("cannot create a reader on " + topic_name);
    }
    return r;
  }

 private:
  template <class M>
  dds::Topic* topic(const std::string& name) {
    if (participant_->find_type(M::kTypeName).empty()) {
      dds::TypeSupport type(new RosType<M>());
      if (type.register_type(participant_) != ReturnCode_t::RETCODE_OK) {
        throw std::runtime_error(std::string("cannot register ") + M::kTypeName);
      }
    }
    auto* t = participant_->create_topic(name, M::kTypeName, dds::TOPIC_QOS_DEFAULT);
    if (t == nullptr) {
      throw std::runtime_error("cannot create topic " + name);
    }
    return t;
  }

  dds::DomainParticipant* participant_ = nullptr;
  dds::Publisher* publisher_ = nullptr;
  dds::Subscriber* subscriber_ = nullptr;
};

// Counts the valid samples of one topic and keeps the last one (listener threads write, main reads).
template <class M>
class Tally final : public dds::DataReaderListener {
 public:
  void on_data_available(dds::DataReader* reader) override {
    M sample;
    dds::SampleInfo info;
    while (reader->take_next_sample(&sample, &info) == ReturnCode_t::RETCODE_OK) {
      if (!info.valid_data) {
        continue;
      }
      std::lock_guard lock(mutex_);
      last_ = sample;
      ++count_;
    }
  }
  uint64_t count() const { return count_; }
  std::optional<M> last() const {
    std::lock_guard lock(mutex_);
    return last_;
  }

 private:
  mutable std::mutex mutex_;
  std::atomic<uint64_t> count_{0};
  std::optional<M> last_;
};

// ---------------------------------------------------------------------------------------------------
// Formatting.

std::string num(double v) {
  char buf[64];
  const auto r = std::to_chars(buf, buf + sizeof buf, v);
  return {buf, r.ptr};
}

std::string describe(const OperatingState& m) {
  return m.state + " (homed=" + (m.is_homed ? "true" : "false") + " busy=" + (m.is_busy ? "true" : "false") +
         ")";
}

std::string describe(const Float64MultiArray& m) {
  std::string dims;
  for (const auto& d : m.layout.dim) {
    dims += (dims.empty() ? "" : ",") + d.label + ":" + std::to_string(d.size);
  }
  std::optional<double> max;
  for (double v : m.data) {
    if (std::isfinite(v) && (!max || v > *max)) {
      max = v;
    }
  }
  return "dims=[" + dims + "] size=" + std::to_string(m.data.size()) + " max=" + (max ? num(*max) : "none");
}

std::string describe(const WrenchStamped& m) {
  const auto& f = m.wrench.force;
  std::string nanosec = std::to_string(m.header.stamp.nanosec);
  nanosec.insert(0, nanosec.size() < 9 ? 9 - nanosec.size() : 0, '0');
  return "force=(" + num(f.x) + "," + num(f.y) + "," + num(f.z) +
         ") stamp=" + std::to_string(m.header.stamp.sec) + "." + nanosec + " frame=" + m.header.frame_id;
}

std::string describe(const PoseStamped& m) {
  const auto& p = m.pose.position;
  return "position=(" + num(p.x) + "," + num(p.y) + "," + num(p.z) + ") frame=" + m.header.frame_id;
}

template <class M>
void report(const std::string& topic, const Tally<M>& tally) {
  const auto last = tally.last();
  std::cout << topic << " count=" << tally.count() << " last=" << (last ? describe(*last) : "none") << '\n';
}

// ---------------------------------------------------------------------------------------------------
// Modes.

struct Options {
  std::string mode;
  std::string name;  // --arm or --ns
  uint32_t domain = 0;
  double rate_hz = 1000;
  double duration_s = 10;
  double wait_match_s = 10;
  int32_t subscribers = 1;  // publish: wait for this many matched subscribers (up to --wait-match)
  uint64_t min_samples = 1;
  std::string cdr_type;
};

// Test contact profile, period 3.5 s: press 1 s to 4 mm, hold 1 s, release 1 s, rest 0.5 s.
struct Contact {
  double depth_m;
  double rate_m_per_s;
};
Contact contact_at(double t) {
  if (t < 1) {
    return {4e-3 * t, 4e-3};
  }
  if (t < 2) {
    return {4e-3, 0};
  }
  if (t < 3) {
    return {4e-3 * (3 - t), -4e-3};
  }
  return {0, 0};
}

// publish-malformed: --duration seconds of truncated wrenches at --rate on ARM/measured_cf.
int run_publish_malformed(const Options& o) {
  Participant participant(o.domain);
  auto* cf = participant.writer<TruncatedWrench>("rt/" + o.name + "/measured_cf", ros_default_writer_qos());
  const auto deadline = Clock::now() + std::chrono::duration<double>(o.wait_match_s);
  dds::PublicationMatchedStatus matched;
  while (cf->get_publication_matched_status(matched) == ReturnCode_t::RETCODE_OK &&
         matched.current_count == 0 && Clock::now() < deadline && sleep_for_s(0.01)) {
  }
  const auto periods = static_cast<uint64_t>(std::llround(o.duration_s * o.rate_hz));
  uint64_t sent = 0;
  TruncatedWrench m;
  for (uint64_t k = 0; k < periods && !g_stop; ++k) {
    m.stamp.sec = 1000 + static_cast<int32_t>(k);
    sent += cf->write(&m) ? 1 : 0;
    sleep_for_s(1.0 / o.rate_hz);
  }
  std::cout << "published " << sent << " malformed wrenches\n";
  return 0;
}

int run_publish(const Options& o) {
  Participant participant(o.domain);
  const std::string prefix = "rt/" + o.name + "/";
  const std::string frame = o.name + "_base";
  auto* cp = participant.writer<PoseStamped>(prefix + "measured_cp", ros_default_writer_qos());
  auto* cf = participant.writer<WrenchStamped>(prefix + "measured_cf", ros_default_writer_qos());

  const auto wait_start = Clock::now();
  const auto match_deadline = wait_start + std::chrono::duration<double>(o.wait_match_s);
  dds::PublicationMatchedStatus matched;
  while (cf->get_publication_matched_status(matched) == ReturnCode_t::RETCODE_OK &&
         matched.current_count < o.subscribers && Clock::now() < match_deadline && sleep_for_s(0.01)) {
  }
  if (matched.current_count > 0) {
    const std::chrono::duration<double> waited = Clock::now() - wait_start;
    std::cout << "matched " << matched.current_count << " subscriber(s) on " << prefix << "measured_cf after "
              << num(std::round(waited.count() * 1000) / 1000) << " s\n";
  } else if (!g_stop) {
    std::cout << "no subscriber on " << prefix << "measured_cf after " << num(o.wait_match_s)
              << " s; publishing anyway\n";
  }

  PoseStamped pose;
  pose.header.frame_id = frame;
  WrenchStamped wrench;
  wrench.header.frame_id = frame;
  wrench.wrench.force.x = 0.04;
  wrench.wrench.force.y = -0.025;

  const auto periods = static_cast<uint64_t>(std::llround(o.duration_s * o.rate_hz));
  const auto start = Clock::now();
  uint64_t poses = 0;
  uint64_t wrenches = 0;
  for (uint64_t k = 0; k < periods && !g_stop; ++k) {
    const double elapsed = static_cast<double>(k) / o.rate_hz;
    std::this_thread::sleep_until(
        start + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(elapsed)));
    const Contact c = contact_at(std::fmod(elapsed, 3.5));
    const double normal = c.depth_m > 0 ? std::max(0.0, 300 * c.depth_m + 0.5 * c.rate_m_per_s) : 0.0;
    // Stamps of a clock starting at 1000 s: integer nanoseconds keep them strictly increasing.
    const int64_t ns = 1'000'000'000'000 + std::llround(static_cast<double>(k) * 1e9 / o.rate_hz);
    const Time stamp{static_cast<int32_t>(ns / 1'000'000'000), static_cast<uint32_t>(ns % 1'000'000'000)};

    pose.header.stamp = stamp;
    pose.pose.position.z = -c.depth_m;
    poses += cp->write(&pose) ? 1 : 0;
    wrench.header.stamp = stamp;
    wrench.wrench.force.z = normal;
    wrenches += cf->write(&wrench) ? 1 : 0;
  }
  std::cout << "published " << wrenches << " wrenches, " << poses << " poses\n";
  return 0;
}

int run_subscribe(const Options& o) {
  const std::string prefix = "rt/" + o.name + "/";
  const std::string state_topic = prefix + "operating_state";
  const std::string target_topic = prefix + "cell_force/target";
  const std::string estimated_topic = prefix + "cell_force/estimated";
  const std::string true_topic = prefix + "cell_force/true";
  Tally<OperatingState> state;
  Tally<Float64MultiArray> target;
  Tally<Float64MultiArray> estimated;
  Tally<Float64MultiArray> truth;
  const auto enough = [&] {
    return state.count() >= o.min_samples && target.count() >= o.min_samples &&
           estimated.count() >= o.min_samples;
  };
  {
    Participant participant(o.domain);  // destroyed before the tallies it calls back into
    participant.reader<OperatingState>(state_topic, ros_default_reader_qos(), &state);
    participant.reader<Float64MultiArray>(target_topic, ros_default_reader_qos(), &target);
    participant.reader<Float64MultiArray>(estimated_topic, ros_default_reader_qos(), &estimated);
    participant.reader<Float64MultiArray>(true_topic, ros_default_reader_qos(), &truth);
    const auto deadline = Clock::now() + std::chrono::duration<double>(o.duration_s);
    while (!enough() && Clock::now() < deadline && sleep_for_s(0.01)) {
    }
  }
  report(state_topic, state);
  report(target_topic, target);
  report(estimated_topic, estimated);
  report(true_topic, truth);
  return enough() ? 0 : 1;
}

// Hidden: a ROS 2 consumer of the follower's topics (sensor-data QoS), to test `publish` peer to peer.
int run_listen_follower(const Options& o) {
  const std::string prefix = "rt/" + o.name + "/";
  Tally<WrenchStamped> wrenches;
  Tally<PoseStamped> poses;
  {
    Participant participant(o.domain);
    participant.reader<WrenchStamped>(prefix + "measured_cf", ros_sensor_data_qos(), &wrenches);
    participant.reader<PoseStamped>(prefix + "measured_cp", ros_sensor_data_qos(), &poses);
    const auto deadline = Clock::now() + std::chrono::duration<double>(o.duration_s);
    while (Clock::now() < deadline && sleep_for_s(std::min(0.01, o.duration_s))) {
    }
  }
  report(prefix + "measured_cf", wrenches);
  report(prefix + "measured_cp", poses);
  return wrenches.count() > 0 && poses.count() > 0 ? 0 : 1;
}

// Serialises M, checks the size provider and a decode/re-encode round trip, prints the bytes.
template <class M>
bool dump(M message) {
  RosType<M> type;
  rtps::SerializedPayload_t payload(type.m_typeSize);
  if (!type.serialize(&message, &payload)) {
    return false;
  }
  const uint32_t predicted = type.getSerializedSizeProvider(&message)();
  M decoded;
  rtps::SerializedPayload_t again(type.m_typeSize);
  if (!type.deserialize(&payload, &decoded) || !type.serialize(&decoded, &again)) {
    return false;
  }
  if (predicted != payload.length || again.length != payload.length ||
      std::memcmp(again.data, payload.data, payload.length) != 0) {
    std::cerr << "self-check failed for " << M::kTypeName << " (size " << payload.length << ", predicted "
              << predicted << ")\n";
    return false;
  }
  constexpr const char* kHex = "0123456789abcdef";
  std::string line;
  for (uint32_t i = 0; i < payload.length; ++i) {
    if (i > 0) {
      line += ' ';
    }
    line += kHex[payload.data[i] >> 4];
    line += kHex[payload.data[i] & 0xf];
  }
  std::cout << line << '\n';
  return true;
}

int run_dump_cdr(const Options& o) {
  bool ok = false;
  if (o.cdr_type == "wrench") {
    WrenchStamped m;
    m.header = {{1, 2}, "arm"};
    m.wrench = {{1.5, -2.0, 3.25}, {0.0, 0.5, -1.0}};
    ok = dump(m);
  } else if (o.cdr_type == "pose") {
    PoseStamped m;
    m.header = {{7, 500'000'000}, ""};
    m.pose = {{0.001, -0.002, -0.004}, {0, 0, 0, 1}};
    ok = dump(m);
  } else if (o.cdr_type == "array") {
    Float64MultiArray m;
    m.layout.dim = {{"row", 2, 4}, {"col", 2, 2}};
    m.layout.data_offset = 0;
    m.data = {0.0, 1.0, 2.5, std::numeric_limits<double>::quiet_NaN()};
    ok = dump(m);
  } else if (o.cdr_type == "state") {
    OperatingState m;
    m.header = {{3, 4}, ""};
    m.state = "ENABLED";
    m.is_homed = true;
    m.is_busy = false;
    ok = dump(m);
  }
  return ok ? 0 : 1;
}

// ---------------------------------------------------------------------------------------------------
// Command line.

constexpr const char* kUsage = R"(usage:
  mrskin_fastdds_peer publish --arm NAME [--domain N=0] [--rate HZ=1000] [--duration S=10] [--wait-match S=10] [--subscribers N=1]
      A ROS 2 (rmw_fastrtps) CRTK follower: publishes rt/NAME/measured_cp (PoseStamped) and
      rt/NAME/measured_cf (WrenchStamped), reliable keep-last 10, a press/hold/release cycle of 3.5 s.
  mrskin_fastdds_peer publish-malformed --arm NAME [--domain N=0] [--rate HZ=1000] [--duration S=10] [--wait-match S=10]
  mrskin_fastdds_peer subscribe --ns NAME [--domain N=0] [--duration S=10] [--min N=1]
      Reads rt/NAME/operating_state and rt/NAME/cell_force/{target,estimated,true}; exit 0 when the
      first three each received at least N samples, else 1.
  mrskin_fastdds_peer dump-cdr wrench|pose|array|state
      Prints the XCDR1 payload (encapsulation header included) of a fixed example, as hex.
Fast DDS 2.9 on UDP over 127.0.0.1 only, no multicast, no shared memory.
Exit status: 0 success, 1 failure, 2 bad usage.
)";

struct UsageError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

double parse_number(const std::string& option, const std::string& text, double lo, double hi) {
  char* end = nullptr;
  const double v = std::strtod(text.c_str(), &end);
  if (text.empty() || end != text.c_str() + text.size() || !std::isfinite(v) || v < lo || v > hi) {
    throw UsageError(option + " wants a number in [" + num(lo) + ", " + num(hi) + "], not '" + text + "'");
  }
  return v;
}

uint64_t parse_integer(const std::string& option, const std::string& text, uint64_t lo, uint64_t hi) {
  uint64_t v = 0;
  const auto r = std::from_chars(text.data(), text.data() + text.size(), v);
  if (text.empty() || r.ec != std::errc() || r.ptr != text.data() + text.size() || v < lo || v > hi) {
    throw UsageError(option + " wants an integer in [" + std::to_string(lo) + ", " + std::to_string(hi) +
                     "], not '" + text + "'");
  }
  return v;
}

// ROS 2 name tokens ([A-Za-z_][A-Za-z0-9_]*) joined by '/', no leading or trailing '/'.
bool valid_ros_name(const std::string& name) {
  bool token_start = true;
  for (char c : name) {
    const bool alpha = (c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z') || c == '_';
    const bool digit = c >= '0' && c <= '9';
    if (c == '/') {
      if (token_start) {
        return false;
      }
      token_start = true;
    } else if (alpha || (digit && !token_start)) {
      token_start = false;
    } else {
      return false;
    }
  }
  return !token_start;
}

Options parse(int argc, char** argv) {
  const std::vector<std::string> args(argv + 1, argv + argc);
  if (args.empty()) {
    throw UsageError("missing mode");
  }
  Options o;
  o.mode = args[0];
  std::vector<std::string> accepted;  // options of this mode, each followed by a value
  std::string name_option;
  if (o.mode == "publish") {
    name_option = "--arm";
    accepted = {"--arm", "--domain", "--rate", "--duration", "--wait-match", "--subscribers"};
  } else if (o.mode == "publish-malformed") {
    name_option = "--arm";
    accepted = {"--arm", "--domain", "--rate", "--duration", "--wait-match"};
  } else if (o.mode == "subscribe") {
    name_option = "--ns";
    accepted = {"--ns", "--domain", "--duration", "--min"};
  } else if (o.mode == "listen-follower") {
    name_option = "--arm";
    accepted = {"--arm", "--domain", "--duration"};
  } else if (o.mode == "dump-cdr") {
    if (args.size() != 2) {
      throw UsageError("dump-cdr wants exactly one TYPE");
    }
    o.cdr_type = args[1];
    if (o.cdr_type != "wrench" && o.cdr_type != "pose" && o.cdr_type != "array" && o.cdr_type != "state") {
      throw UsageError("unknown dump-cdr TYPE '" + o.cdr_type + "'");
    }
    return o;
  } else {
    throw UsageError("unknown mode '" + o.mode + "'");
  }
  for (size_t i = 1; i < args.size(); i += 2) {
    const std::string& key = args[i];
    if (std::find(accepted.begin(), accepted.end(), key) == accepted.end()) {
      throw UsageError("unknown option '" + key + "' for " + o.mode);
    }
    if (i + 1 >= args.size()) {
      throw UsageError(key + " wants a value");
    }
    const std::string& value = args[i + 1];
    if (key == name_option) {
      o.name = value;
    } else if (key == "--domain") {
      o.domain = static_cast<uint32_t>(parse_integer(key, value, 0, 232));  // RTPS ports stay below 65536
    } else if (key == "--rate") {
      o.rate_hz = parse_number(key, value, 1e-3, 1e5);
    } else if (key == "--duration") {
      o.duration_s = parse_number(key, value, 0, 86400);
    } else if (key == "--wait-match") {
      o.wait_match_s = parse_number(key, value, 0, 3600);
    } else if (key == "--subscribers") {
      o.subscribers = static_cast<int32_t>(parse_number(key, value, 1, 100));
    } else if (key == "--min") {
      o.min_samples = parse_integer(key, value, 1, 1'000'000'000);
    }
  }
  if (!valid_ros_name(o.name)) {
    throw UsageError(name_option + " wants a ROS 2 name (e.g. psm1), not '" + o.name + "'");
  }
  return o;
}

// Fast DDS reads these at participant creation; any could add non-loopback peers or override our QoS.
void neutralise_fastdds_environment() {
  unsetenv("ROS_DISCOVERY_SERVER");
  unsetenv("FASTDDS_ENVIRONMENT_FILE");
  unsetenv("FASTRTPS_DEFAULT_PROFILES_FILE");
  setenv("SKIP_DEFAULT_XML_FILE", "1", 1);
}

}  // namespace

int main(int argc, char** argv) {
  for (int i = 1; i < argc; ++i) {
    if (std::strcmp(argv[i], "--help") == 0 || std::strcmp(argv[i], "-h") == 0) {
      std::cout << kUsage;
      return 0;
    }
  }
  Options options;
  try {
    options = parse(argc, argv);
  } catch (const UsageError& e) {
    std::cerr << "mrskin_fastdds_peer: " << e.what() << "\n" << kUsage;
    return 2;
  }
  std::setvbuf(stdout, nullptr, _IOLBF, 0);  // lines reach a pipe while the peer runs
  neutralise_fastdds_environment();
  install_signal_handlers();
  try {
    if (options.mode == "publish") {
      return run_publish(options);
    }
    if (options.mode == "publish-malformed") {
      return run_publish_malformed(options);
    }
    if (options.mode == "subscribe") {
      return run_subscribe(options);
    }
    if (options.mode == "listen-follower") {
      return run_listen_follower(options);
    }
    return run_dump_cdr(options);
  } catch (const std::exception& e) {
    std::cerr << "mrskin_fastdds_peer: " << e.what() << '\n';
    return 1;
  }
}
