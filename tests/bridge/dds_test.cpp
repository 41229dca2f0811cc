// ROS 2 over DDS (issue 23): names, the CDR bytes of ROS 2's messages against bytes derived by
// hand, the dds:// source (frames, drops by reason, the fade when the publisher goes) and the
// skin's topics. Loopback only: CYCLONEDDS_URI points at tests/support/cyclonedds-loopback.xml
// before any participant exists; each test has a domain of its own (tests run in parallel).
#include <dds/dds.h>
#include <dds/ddsi/ddsi_serdata.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <string>
#include <thread>
#include <vector>

#include "mrskin/bridge/ros2_topics.hpp"
#include "mrskin/bridge/sources.hpp"
#include "mrskin/bridge/tissue.hpp"
#include "mrskin/driver/errors.hpp"
#include "ros2_messages.h"

namespace {

using namespace mrskin;
using namespace mrskin::bridge;
using namespace std::chrono_literals;

// Topics unique to this process: another run of these tests on the machine (same loopback, same
// domains) must not cross-talk.
const std::string kRun = "t" + std::to_string(::getpid());
std::string rt(const std::string& rest) { return "rt/" + kRun + "/" + rest; }

const bool kLoopback = [] {
  (void)::setenv("CYCLONEDDS_URI", MRSKIN_CYCLONEDDS_LOOPBACK_URI, 1);
  return true;
}();

// Polls cond every 5 ms for up to limit.
bool eventually(const std::function<bool()>& cond, std::chrono::milliseconds limit = 5000ms) {
  const auto end = std::chrono::steady_clock::now() + limit;
  while (std::chrono::steady_clock::now() < end) {
    if (cond()) {
      return true;
    }
    std::this_thread::sleep_for(5ms);
  }
  return cond();
}

std::vector<std::uint8_t> hex(const std::string& text) {
  std::vector<std::uint8_t> out;
  for (std::size_t i = 0; i + 1 < text.size();) {
    if (text[i] == ' ') {
      ++i;
      continue;
    }
    out.push_back(static_cast<std::uint8_t>(std::stoul(text.substr(i, 2), nullptr, 16)));
    i += 2;
  }
  return out;
}

// ---- names ---------------------------------------------------------------------------------

TEST(Ros2Names, FollowRos2sRules) {
  for (const char* ok : {"/PSM1", "psm1/tool", "a_b/c9", "/dvrk/PSM1/body"}) {
    EXPECT_TRUE(valid_ros_name(ok)) << ok;
  }
  for (const char* bad : {"", "/", "1abc", "a//b", "a/", "a-b", "a b", "/psm1/2x", "~/x"}) {
    EXPECT_FALSE(valid_ros_name(bad)) << bad;
  }
}

TEST(DdsSourceUri, BadPartsAreNamed) {
  const auto fails = [](const char* uri, const char* says) {
    try {
      (void)open_stream(uri);
      ADD_FAILURE() << uri << " was accepted";
    } catch (const InvalidArgument& e) {
      EXPECT_NE(std::string(e.what()).find(says), std::string::npos) << e.what();
    }
  };
  fails("dds://psm1?domain=233", "bad domain '233'");
  fails("dds://psm1?domain=-1", "bad domain");
  fails("dds://1psm", "not a ROS 2 name");
  fails("dds://", "missing arm");
  fails("dds://psm1?wrench=/a//b", "not a ROS 2 name");
  fails("dds://psm1?color=red", "dds takes queue=N, domain=N, wrench=TOPIC, pose=TOPIC");
}

// ---- CDR: the bytes on the wire ---------------------------------------------------------------

// Writes sample on a loopback topic and takes the serialized form back: the bytes a ROS 2 node
// receives (encapsulation header first). type_out: the sertype, to decode bytes with.
std::vector<std::uint8_t> wire_bytes(int domain, const dds_topic_descriptor_t* desc, const void* sample,
                                     const std::string& topic_name) {
  const dds_entity_t p = dds_create_participant(domain, nullptr, nullptr);
  EXPECT_GT(p, 0);
  const dds_entity_t t = dds_create_topic(p, desc, topic_name.c_str(), nullptr, nullptr);
  dds_qos_t* q = dds_create_qos();
  dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_SECS(1));
  const dds_entity_t r = dds_create_reader(p, t, q, nullptr);
  const dds_entity_t w = dds_create_writer(p, t, q, nullptr);
  dds_delete_qos(q);
  EXPECT_EQ(dds_write(w, sample), DDS_RETCODE_OK);
  std::vector<std::uint8_t> out;
  ddsi_serdata* sd = nullptr;
  dds_sample_info_t info{};
  EXPECT_TRUE(eventually([&] { return dds_takecdr(r, &sd, 1, &info, DDS_ANY_STATE) == 1; }));
  if (sd != nullptr) {
    out.resize(ddsi_serdata_size(sd));
    ddsi_serdata_to_ser(sd, 0, out.size(), out.data());
    ddsi_serdata_unref(sd);
  }
  (void)dds_delete(p);
  return out;
}

// Decodes bytes (encapsulation header first) as desc's type, through Cyclone's own deserializer.
bool decode(int domain, const dds_topic_descriptor_t* desc, const std::string& topic_name,
            const std::vector<std::uint8_t>& bytes, void* sample) {
  const dds_entity_t p = dds_create_participant(domain, nullptr, nullptr);
  const dds_entity_t t = dds_create_topic(p, desc, topic_name.c_str(), nullptr, nullptr);
  const dds_entity_t r = dds_create_reader(p, t, nullptr, nullptr);
  const dds_entity_t w = dds_create_writer(p, t, nullptr, nullptr);
  // The sertype of the topic: from a sample written and taken in serialized form.
  std::vector<char> zero(desc->m_size, 0);
  (void)dds_write(w, zero.data());
  ddsi_serdata* probe = nullptr;
  dds_sample_info_t info{};
  bool ok = eventually([&] { return dds_takecdr(r, &probe, 1, &info, DDS_ANY_STATE) == 1; });
  if (ok) {
    ddsrt_iovec_t iov{};
    iov.iov_base = const_cast<std::uint8_t*>(bytes.data());  // NOLINT: read only
    iov.iov_len = static_cast<decltype(iov.iov_len)>(bytes.size());
    ddsi_serdata* sd = ddsi_serdata_from_ser_iov(probe->type, SDK_DATA, 1, &iov, bytes.size());
    ok = sd != nullptr && ddsi_serdata_to_sample(sd, sample, nullptr, nullptr);
    if (sd != nullptr) {
      ddsi_serdata_unref(sd);
    }
    ddsi_serdata_unref(probe);
  }
  (void)dds_delete(p);
  return ok;
}

// WrenchStamped, by hand: stamp 1 s + 2 ns, frame_id "psm1" (its length 5 with the NUL at 8, the
// characters from 12 to 16), then the doubles at the next multiple of 8 from the start of the data
// (not of the header): 17 -> 7 bytes of padding -> 24.
const char* const kWrenchBytes =
    "00 01 00 00"                                         // CDR_LE encapsulation, options 0
    " 01 00 00 00  02 00 00 00"                           // 0: sec 1, nanosec 2
    " 05 00 00 00  70 73 6d 31 00  00 00 00 00 00 00 00"  // 8: "psm1\0", pad 7
    " 00 00 00 00 00 00 f8 3f"                            // 24: force.x 1.5
    " 00 00 00 00 00 00 00 c0"                            // 32: force.y -2.0
    " 00 00 00 00 00 00 0a 40"                            // 40: force.z 3.25
    " 00 00 00 00 00 00 00 00"                            // 48: torque.x 0.0
    " 00 00 00 00 00 00 e0 3f"                            // 56: torque.y 0.5
    " 00 00 00 00 00 00 f0 bf";                           // 64: torque.z -1.0

geometry_msgs_msg_dds__WrenchStamped_ example_wrench() {
  geometry_msgs_msg_dds__WrenchStamped_ w{};
  static char frame[] = "psm1";
  w.header.stamp = {1, 2};
  w.header.frame_id = frame;
  w.wrench.force = {1.5, -2.0, 3.25};
  w.wrench.torque = {0.0, 0.5, -1.0};
  return w;
}

TEST(Ros2Cdr, WrenchStampedEncodesAsDerivedByHand) {
  const geometry_msgs_msg_dds__WrenchStamped_ w = example_wrench();
  EXPECT_STREQ(geometry_msgs_msg_dds__WrenchStamped__desc.m_typename,
               "geometry_msgs::msg::dds_::WrenchStamped_");
  EXPECT_EQ(wire_bytes(40, &geometry_msgs_msg_dds__WrenchStamped__desc, &w, rt("cdr/wrench")),
            hex(kWrenchBytes));
}

TEST(Ros2Cdr, WrenchStampedDecodesFromBytesDerivedByHand) {
  geometry_msgs_msg_dds__WrenchStamped_ w{};
  ASSERT_TRUE(
      decode(40, &geometry_msgs_msg_dds__WrenchStamped__desc, rt("cdr/wrench_in"), hex(kWrenchBytes), &w));
  EXPECT_EQ(w.header.stamp.sec, 1);
  EXPECT_EQ(w.header.stamp.nanosec, 2U);
  EXPECT_STREQ(w.header.frame_id, "psm1");
  EXPECT_EQ(w.wrench.force.x, 1.5);
  EXPECT_EQ(w.wrench.force.y, -2.0);
  EXPECT_EQ(w.wrench.force.z, 3.25);
  EXPECT_EQ(w.wrench.torque.y, 0.5);
  EXPECT_EQ(w.wrench.torque.z, -1.0);
  dds_sample_free(&w, &geometry_msgs_msg_dds__WrenchStamped__desc, DDS_FREE_CONTENTS);
}

// PoseStamped: stamp 7 s + 0.5 s, frame_id "" (length 1: its NUL at 12), 13 -> 3 bytes of padding
// -> the position at 16.
const char* const kPoseBytes =
    "00 01 00 00"
    " 07 00 00 00  00 65 cd 1d"   // sec 7, nanosec 500000000
    " 01 00 00 00  00  00 00 00"  // "" then pad 3
    " fc a9 f1 d2 4d 62 50 3f"    // position.x 0.001
    " fc a9 f1 d2 4d 62 60 bf"    // position.y -0.002
    " fc a9 f1 d2 4d 62 70 bf"    // position.z -0.004
    " 00 00 00 00 00 00 00 00  00 00 00 00 00 00 00 00  00 00 00 00 00 00 00 00"
    " 00 00 00 00 00 00 f0 3f";  // orientation (0, 0, 0, 1)

TEST(Ros2Cdr, PoseStampedEncodesAndDecodesAsDerivedByHand) {
  geometry_msgs_msg_dds__PoseStamped_ pose{};
  static char empty[] = "";
  pose.header.stamp = {7, 500'000'000U};
  pose.header.frame_id = empty;
  pose.pose.position = {0.001, -0.002, -0.004};
  pose.pose.orientation = {0.0, 0.0, 0.0, 1.0};
  EXPECT_EQ(wire_bytes(41, &geometry_msgs_msg_dds__PoseStamped__desc, &pose, rt("cdr/pose")),
            hex(kPoseBytes));
  geometry_msgs_msg_dds__PoseStamped_ back{};
  ASSERT_TRUE(
      decode(41, &geometry_msgs_msg_dds__PoseStamped__desc, rt("cdr/pose_in"), hex(kPoseBytes), &back));
  EXPECT_EQ(back.header.stamp.nanosec, 500'000'000U);
  EXPECT_EQ(back.pose.position.y, -0.002);
  EXPECT_EQ(back.pose.orientation.w, 1.0);
  dds_sample_free(&back, &geometry_msgs_msg_dds__PoseStamped__desc, DDS_FREE_CONTENTS);
}

// Float64MultiArray: a sequence of structs holding strings, then a sequence of doubles whose
// first element aligns to 8 after the length.
TEST(Ros2Cdr, Float64MultiArrayEncodesAsDerivedByHand) {
  static char row[] = "row";
  static char col[] = "col";
  std::array<std_msgs_msg_dds__MultiArrayDimension_, 2> dims{{{row, 2, 4}, {col, 2, 2}}};
  std::array<double, 4> data{0.0, 1.0, 2.5, NAN};
  std_msgs_msg_dds__Float64MultiArray_ m{};
  m.layout.dim._length = m.layout.dim._maximum = 2;
  m.layout.dim._buffer = dims.data();
  m.data._length = m.data._maximum = 4;
  m.data._buffer = data.data();
  const char* const bytes =
      "00 01 00 00"
      " 02 00 00 00"                                       // 0: two dimensions
      " 04 00 00 00 72 6f 77 00  02 00 00 00 04 00 00 00"  // 4: "row", size 2, stride 4
      " 04 00 00 00 63 6f 6c 00  02 00 00 00 02 00 00 00"  // 20: "col", size 2, stride 2
      " 00 00 00 00"                                       // 36: data_offset 0
      " 04 00 00 00"                                       // 40: four doubles, first at 48 (not 44)
      " 00 00 00 00"                                       // 44: pad
      " 00 00 00 00 00 00 00 00  00 00 00 00 00 00 f0 3f  00 00 00 00 00 00 04 40"
      " 00 00 00 00 00 00 f8 7f";  // NaN (the quiet NaN's bits)
  EXPECT_EQ(wire_bytes(42, &std_msgs_msg_dds__Float64MultiArray__desc, &m, rt("cdr/array")), hex(bytes));
}

#ifdef MRSKIN_FASTDDS_PEER
// The same messages from an independent encoder: Fast CDR, in the Fast DDS peer
// (tests/interop). XCDR1 lets an encoder pad the payload to a multiple of 4 and say how much in
// the options' two low bits: Cyclone does, Fast CDR 1.0 does not; the bytes agree without it.
std::vector<std::uint8_t> peer_bytes(const std::string& type) {
  std::string text;
  if (std::FILE* p = ::popen((std::string(MRSKIN_FASTDDS_PEER) + " dump-cdr " + type).c_str(), "r")) {
    std::array<char, 4096> buf{};
    while (std::fgets(buf.data(), static_cast<int>(buf.size()), p) != nullptr) {
      text += buf.data();
    }
    EXPECT_EQ(::pclose(p), 0) << type;
  }
  return hex(text);
}

std::vector<std::uint8_t> unpadded(std::vector<std::uint8_t> b) {
  if (b.size() >= 4) {
    const std::size_t pad = b[3] & 3U;
    b[3] = static_cast<std::uint8_t>(b[3] & ~3U);
    b.resize(b.size() - std::min(pad, b.size() - 4));
  }
  return b;
}

TEST(Ros2Cdr, AFastCdrEncoderWritesTheSameBytesAndCycloneDecodesThem) {
  static char arm[] = "arm";
  static char empty[] = "";
  static char enabled[] = "ENABLED";
  geometry_msgs_msg_dds__WrenchStamped_ w = example_wrench();
  w.header.frame_id = arm;
  EXPECT_EQ(unpadded(wire_bytes(46, &geometry_msgs_msg_dds__WrenchStamped__desc, &w, rt("peer/wrench"))),
            unpadded(peer_bytes("wrench")));
  EXPECT_EQ(unpadded(peer_bytes("pose")), unpadded(hex(kPoseBytes)));
  crtk_msgs_msg_dds__OperatingState_ st{};
  st.header.stamp = {3, 4};
  st.header.frame_id = empty;
  st.state = enabled;
  st.is_homed = true;
  st.is_busy = false;
  const std::vector<std::uint8_t> peer_state = peer_bytes("state");
  EXPECT_EQ(unpadded(wire_bytes(46, &crtk_msgs_msg_dds__OperatingState__desc, &st, rt("peer/state"))),
            unpadded(peer_state));
  crtk_msgs_msg_dds__OperatingState_ back{};
  ASSERT_TRUE(decode(46, &crtk_msgs_msg_dds__OperatingState__desc, rt("peer/state_in"), peer_state, &back));
  EXPECT_STREQ(back.state, "ENABLED");
  EXPECT_TRUE(back.is_homed);
  EXPECT_EQ(back.header.stamp.nanosec, 4U);
  dds_sample_free(&back, &crtk_msgs_msg_dds__OperatingState__desc, DDS_FREE_CONTENTS);
  std_msgs_msg_dds__Float64MultiArray_ array{};
  ASSERT_TRUE(decode(46, &std_msgs_msg_dds__Float64MultiArray__desc, rt("peer/array_in"), peer_bytes("array"),
                     &array));
  ASSERT_EQ(array.data._length, 4U);
  EXPECT_EQ(array.data._buffer[2], 2.5);
  EXPECT_TRUE(std::isnan(array.data._buffer[3]));
  ASSERT_EQ(array.layout.dim._length, 2U);
  EXPECT_STREQ(array.layout.dim._buffer[1].label, "col");
  dds_sample_free(&array, &std_msgs_msg_dds__Float64MultiArray__desc, DDS_FREE_CONTENTS);
}

// Malformed samples from a peer (a WrenchStamped whose frame_id claims 1000 bytes that never
// come): Cyclone refuses them before any reader; the source counts them from Cyclone's report.
TEST(DdsSource, MalformedSamplesFromAPeerAreCounted) {
  std::unique_ptr<StreamSource> src = open_stream("dds://" + kRun + "/arm5?domain=47");
  std::thread peer([] {
    const std::string command = std::string(MRSKIN_FASTDDS_PEER) + " publish-malformed --arm " + kRun +
                                "/arm5 --domain 47 --rate 200 --duration 2 --wait-match 10 > /dev/null 2>&1";
    (void)std::system(command.c_str());  // NOLINT(cert-env33-c): the test's own peer
  });
  EXPECT_TRUE(eventually([&] { return src->stats().of(DropReason::format) > 0; }, 10000ms));
  peer.join();
  EXPECT_EQ(src->stats().accepted, 0U);
  bool said = false;
  for (const SourceEvent& e : src->events_after(0)) {
    said = said || e.text.find("not valid CDR for geometry_msgs/msg/WrenchStamped") != std::string::npos;
  }
  EXPECT_TRUE(said);
}
#endif

// ---- the dds:// source --------------------------------------------------------------------------

// A raw writer of WrenchStamped on a topic, for what FollowerPublisher never sends.
struct RawWriter {
  RawWriter(int domain, const char* topic)
      : participant(dds_create_participant(domain, nullptr, nullptr)),
        writer(dds_create_writer(participant,
                                 dds_create_topic(participant, &geometry_msgs_msg_dds__WrenchStamped__desc,
                                                  topic, nullptr, nullptr),
                                 nullptr, nullptr)) {}
  RawWriter(const RawWriter&) = delete;
  RawWriter& operator=(const RawWriter&) = delete;
  ~RawWriter() { (void)dds_delete(participant); }
  bool write(std::int32_t sec, std::uint32_t nanosec, double fz) const {
    geometry_msgs_msg_dds__WrenchStamped_ w{};
    static char frame[] = "";
    w.header.stamp = {sec, nanosec};
    w.header.frame_id = frame;
    w.wrench.force = {0.0, 0.0, fz};
    return dds_write(writer, &w) == DDS_RETCODE_OK;
  }
  dds_entity_t participant = 0;
  dds_entity_t writer = 0;
};

TEST(DdsSource, ReadsACrtkArmInTheRobotsFrameAndFadesWhenItGoes) {
  // The robot's frame turned over (roll 180): its -z is the tissue's outward normal.
  std::unique_ptr<StreamSource> src = open_stream("dds://" + kRun + "/arm1?domain=43&rpy_deg=180,0,0");
  auto follower = std::make_unique<FollowerPublisher>("/" + kRun + "/arm1", 43);
  ASSERT_TRUE(eventually([&] { return follower->subscribers() == 1 && src->stats().connections == 2; }))
      << src->stats().connections;
  SlaveSample s;
  std::int64_t stamp_ns = 5'000'000'000;
  const auto send = [&](double fx, double fz, double z_m) {
    FollowerSample f;
    f.stamp_ns = stamp_ns += 1'000'000;
    f.force_N = {fx, 0.2, fz};
    f.position_m = {0.01, 0.02, z_m};
    return follower->publish(f);
  };
  // Best effort on loopback: resend until one arrives.
  ASSERT_TRUE(eventually([&] { return send(0.1, -1.5, 0.004) && src->latest(TimePoint{}, s) && s.valid; }));
  EXPECT_NEAR(s.force_N, 1.5, 1e-12);  // R (0.1, 0.2, -1.5) = (0.1, -0.2, 1.5)
  EXPECT_NEAR(s.indentation_m, 0.004, 1e-12);
  EXPECT_NEAR(s.contact_x_m, 0.01, 1e-12);
  EXPECT_NEAR(s.contact_y_m, -0.02, 1e-12);
  EXPECT_FALSE(s.ended);
  // Pulling is no contact; NaN is dropped and counted.
  ASSERT_TRUE(
      eventually([&] { return send(0.0, 0.5, 0.004) && src->latest(TimePoint{}, s) && s.force_N == 0.0; }));
  ASSERT_TRUE(
      eventually([&] { return send(NAN, -1.0, 0.004) && src->stats().of(DropReason::non_finite) > 0; }));
  // A malformed stamp, an older one: dropped by reason.
  RawWriter raw(43, rt("arm1/measured_cf").c_str());
  ASSERT_TRUE(eventually(
      [&] { return raw.write(1, 1'000'000'000U, 1.0) && src->stats().of(DropReason::stamp) > 0; }));
  ASSERT_TRUE(
      eventually([&] { return raw.write(1, 0, -1.0) && src->stats().of(DropReason::out_of_order) > 0; }));
  const std::uint64_t accepted = src->stats().accepted;
  EXPECT_GE(accepted, 2U);
  // The follower stops: the source says so, and its last sample carries the end.
  follower.reset();
  ASSERT_TRUE(eventually([&] { return src->latest(TimePoint{}, s) && s.ended; }));
  EXPECT_GE(src->stats().disconnects, 1U);
  bool faded = false;
  for (const SourceEvent& e : src->events_after(0)) {
    faded = faded || e.text.find("fading to released") != std::string::npos;
  }
  EXPECT_TRUE(faded);
  EXPECT_NE(src->last_warning().find("dds:"), std::string::npos) << src->last_warning();
}

TEST(DdsSource, AWriterOfAnotherTypeIsCountedAndNamed) {
  std::unique_ptr<StreamSource> src = open_stream("dds://" + kRun + "/arm2?domain=44");
  const dds_entity_t p = dds_create_participant(44, nullptr, nullptr);
  const dds_entity_t t = dds_create_topic(p, &std_msgs_msg_dds__Float64MultiArray__desc,
                                          rt("arm2/measured_cf").c_str(), nullptr, nullptr);
  ASSERT_GT(t, 0) << dds_strretcode(t);
  const dds_entity_t w = dds_create_writer(p, t, nullptr, nullptr);
  ASSERT_GT(w, 0);
  EXPECT_TRUE(eventually([&] { return src->stats().of(DropReason::type) > 0; }));
  EXPECT_NE(src->last_warning().find("std_msgs::msg::dds_::Float64MultiArray_"), std::string::npos)
      << src->last_warning();
  (void)dds_delete(p);
}

// ---- the stale policy's end ---------------------------------------------------------------------

TEST(TissueEstimatorEnd, AnEndedStreamFadesWithoutItsHold) {
  TissueEstimatorOptions o;  // hold 0.1 s, fade 0.2 s
  TissueEstimator est(o);
  ASSERT_TRUE(est.push(TissueSample{1.0, 0.5, 1e-3}));
  EXPECT_EQ(est.estimate(1.05).freshness, TissueFreshness::holding);
  est.end_stream(1.01);
  const TissueEstimate e = est.estimate(1.05);  // 0.04 s into the fade
  EXPECT_EQ(e.freshness, TissueFreshness::fading);
  EXPECT_NEAR(e.scale, 0.8, 1e-9);
  EXPECT_NEAR(e.valid_until_s, 1.21, 1e-9);
  EXPECT_EQ(est.estimate(1.22).freshness, TissueFreshness::safe);
  ASSERT_TRUE(est.push(TissueSample{1.3, 0.5, 1e-3}));  // the stream is back
  EXPECT_EQ(est.estimate(1.35).freshness, TissueFreshness::holding);
}

// ---- the skin's topics --------------------------------------------------------------------------

TEST(SkinPublisher, PublishesStateAndGridsThatACycloneReaderDecodes) {
  SkinTopicsOptions o;
  o.ns = "/" + kRun + "/skin";
  o.domain = 45;
  SkinPublisher pub(o);
  const dds_entity_t p = dds_create_participant(45, nullptr, nullptr);
  dds_qos_t* q = dds_create_qos();
  dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_SECS(1));
  const dds_entity_t state_reader =
      dds_create_reader(p,
                        dds_create_topic(p, &crtk_msgs_msg_dds__OperatingState__desc,
                                         rt("skin/operating_state").c_str(), nullptr, nullptr),
                        q, nullptr);
  const dds_entity_t target_reader =
      dds_create_reader(p,
                        dds_create_topic(p, &std_msgs_msg_dds__Float64MultiArray__desc,
                                         rt("skin/cell_force/target").c_str(), nullptr, nullptr),
                        q, nullptr);
  dds_delete_qos(q);
  ASSERT_TRUE(eventually([&] { return pub.subscribers() == 1; }));
  std::vector<double> target{NAN, 0.5, NAN, 1.25};
  std::vector<double> estimated{NAN, 0.4, NAN, 1.2};
  SkinFrame f;
  f.stamp_ns = 1'700'000'000'123'456'789;
  f.state = "ENABLED";
  f.rows = 2;
  f.cols = 2;
  f.target_N = target;
  f.estimated_N = estimated;
  ASSERT_TRUE(pub.publish(f));
  void* sample = nullptr;
  dds_sample_info_t info{};
  ASSERT_TRUE(eventually([&] { return dds_take(state_reader, &sample, &info, 1, 1) == 1; }));
  const auto* st = static_cast<const crtk_msgs_msg_dds__OperatingState_*>(sample);
  EXPECT_STREQ(st->state, "ENABLED");
  EXPECT_EQ(st->header.stamp.sec, 1'700'000'000);
  EXPECT_EQ(st->header.stamp.nanosec, 123'456'789U);
  EXPECT_TRUE(st->is_homed);
  (void)dds_return_loan(state_reader, &sample, 1);
  sample = nullptr;
  ASSERT_TRUE(eventually([&] { return dds_take(target_reader, &sample, &info, 1, 1) == 1; }));
  const auto* m = static_cast<const std_msgs_msg_dds__Float64MultiArray_*>(sample);
  ASSERT_EQ(m->layout.dim._length, 2U);
  EXPECT_STREQ(m->layout.dim._buffer[0].label, "row");
  EXPECT_EQ(m->layout.dim._buffer[0].stride, 4U);
  EXPECT_STREQ(m->layout.dim._buffer[1].label, "col");
  ASSERT_EQ(m->data._length, 4U);
  EXPECT_TRUE(std::isnan(m->data._buffer[0]));
  EXPECT_EQ(m->data._buffer[3], 1.25);
  (void)dds_return_loan(target_reader, &sample, 1);
  EXPECT_EQ(pub.published(), 1U);
  // A frame whose arrays do not fit its grid is a failure, not a crash.
  f.rows = 3;
  EXPECT_FALSE(pub.publish(f));
  EXPECT_EQ(pub.failures(), 1U);
  (void)dds_delete(p);
}

TEST(SkinPublisher, ABadNamespaceOrDomainIsRefusedAtSetup) {
  SkinTopicsOptions o;
  o.ns = "/skin//left";
  EXPECT_THROW(SkinPublisher{o}, InvalidArgument);
  o.ns = "/skin";
  o.domain = 300;
  EXPECT_THROW(SkinPublisher{o}, InvalidArgument);
}

}  // namespace
