// The mock's bus model (mock://?bus=..., driver/sim/src/mock_bus.hpp): URI parsing, USB report
// slots and their queue, CAN frame times, arbitration and the txqueuelen's ENOBUFS. The model is
// private to libmrskin_sim: this test compiles its source again (tests/driver/CMakeLists.txt).
// Simulated time only; every expectation is computed here from the bus's rules.
#include "mock_bus.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cstdint>
#include <initializer_list>
#include <memory>
#include <string>
#include <vector>

#include "mrskin/driver/device.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/protocol/can.hpp"
#include "mrskin/protocol/packed_report.hpp"
#include "mrskin/protocol/packet.hpp"
#include "mrskin/sim/mock_device.hpp"
#include "mrskin/sim/open_mock.hpp"

namespace mrskin::sim {
namespace {
namespace proto = mrskin::protocol;

using std::chrono::microseconds;
using std::chrono::milliseconds;

struct Delivery {
  Datagram datagram;
  TimePoint at{};
  bool to_device = false;
};

class Recorder final : public BusSink {
 public:
  void deliver_to_device(const Datagram& d, TimePoint at) noexcept override { log.push_back({d, at, true}); }
  void deliver_to_host(const Datagram& d, TimePoint at) noexcept override { log.push_back({d, at, false}); }
  std::vector<Delivery> log;
};

MockBusOptions bus_options(MockBusKind kind) {
  MockBusOptions options;
  options.kind = kind;
  return options;
}

// A bus started at time 0 and what it delivers.
struct Rig {
  explicit Rig(const MockBusOptions& options) : bus(options) { bus.start(TimePoint{0}); }
  MockBus bus;
  Recorder sink;
};

Datagram packet(const proto::Message& m, std::uint8_t sequence = 0) {
  Datagram d;
  const proto::EncodeResult r = proto::encode_packet(m, sequence, d.bytes);
  EXPECT_EQ(r.error, proto::Error::ok);
  d.length = static_cast<std::uint16_t>(r.bytes);
  return d;
}

proto::ValveCurrents twelve_currents() {
  proto::ValveCurrents v;
  v.first = 0;
  v.count = 12;
  for (std::size_t i = 0; i < 12; ++i) {
    v.counts[i] = static_cast<std::uint16_t>(100 * i);
  }
  return v;
}

proto::MessageType type_of(const Datagram& d) { return static_cast<proto::MessageType>(d.bytes[1]); }

// Worst-case length of a classic CAN data frame with an 11-bit identifier and n data bytes,
// interframe space included (Davis, Burns, Bril, Lukkien, "Controller Area Network (CAN)
// schedulability analysis: refuted, revisited and revised", Real-Time Systems 35, 2007):
// 44 + 8n bits from SOF to the end of EOF, of which the 34 + 8n from SOF to the CRC may carry a
// stuff bit after every 4 bits at worst, plus 3 bits of interframe space.
std::size_t classic_worst_case_bits(std::size_t n) { return 44 + 8 * n + (34 + 8 * n - 1) / 4 + 3; }

// --- mock://?bus=...&bitrate=... -----------------------------------------------------------------

TEST(MockBusUri, DefaultsAndEveryKind) {
  EXPECT_EQ(parse_mock_uri("mock://").options.bus.kind, MockBusKind::none);
  EXPECT_FALSE(parse_mock_uri("mock://?bus=hid-fs").profile_bus);
  EXPECT_TRUE(parse_mock_uri("mock://?bus=profile").profile_bus);  // open_device reads the profile
  EXPECT_EQ(parse_mock_uri("mock://?bus=none").options.bus.kind, MockBusKind::none);
  EXPECT_EQ(parse_mock_uri("mock://?bus=hid-fs").options.bus.kind, MockBusKind::hid_fs);
  EXPECT_EQ(parse_mock_uri("mock://?bus=hid-hs").options.bus.kind, MockBusKind::hid_hs);
  const MockUri can = parse_mock_uri("mock://mr-skin-5x5?seed=3&bus=can");
  EXPECT_EQ(can.options.bus.kind, MockBusKind::can);
  EXPECT_DOUBLE_EQ(can.options.bus.nominal_bitrate_bit_per_s, 1e6);
  EXPECT_EQ(can.profile, "mr-skin-5x5");
  const MockUri fd = parse_mock_uri("mock://?bus=canfd");
  EXPECT_DOUBLE_EQ(fd.options.bus.nominal_bitrate_bit_per_s, 1e6);
  EXPECT_DOUBLE_EQ(fd.options.bus.data_bitrate_bit_per_s, 5e6);
}

TEST(MockBusUri, BitRates) {
  EXPECT_DOUBLE_EQ(parse_mock_uri("mock://?bus=can&bitrate=500000").options.bus.nominal_bitrate_bit_per_s,
                   5e5);
  // The bit rate may come before the bus.
  const MockUri fd = parse_mock_uri("mock://?bitrate=500000/2000000&bus=canfd");
  EXPECT_DOUBLE_EQ(fd.options.bus.nominal_bitrate_bit_per_s, 5e5);
  EXPECT_DOUBLE_EQ(fd.options.bus.data_bitrate_bit_per_s, 2e6);
  EXPECT_DOUBLE_EQ(parse_mock_uri("mock://?bus=canfd&bitrate=250000").options.bus.data_bitrate_bit_per_s,
                   5e6);
}

// The message of a refusal at open.
std::string refusal(const std::string& uri) {
  try {
    (void)parse_mock_uri(uri);
  } catch (const InvalidArgument& e) {
    return e.what();
  }
  return "(accepted)";
}

TEST(MockBusUri, BadValuesAreRefusedSayingWhatIsAccepted) {
  const std::string kinds = refusal("mock://?bus=usb");
  EXPECT_NE(kinds.find("'usb'"), std::string::npos) << kinds;
  EXPECT_NE(kinds.find("use none, hid-fs, hid-hs, can, canfd or profile (the default: "), std::string::npos)
      << kinds;
  EXPECT_NE(refusal("mock://?bus=").find("hid-fs"), std::string::npos);
  const std::string on_usb = refusal("mock://?bus=hid-fs&bitrate=1000000");
  EXPECT_NE(on_usb.find("bitrate applies to bus=can"), std::string::npos) << on_usb;
  EXPECT_NE(refusal("mock://?bitrate=1000000").find("bitrate applies to"), std::string::npos);
  EXPECT_NE(refusal("mock://?bus=can&bitrate=1000000/5000000").find("B/D is for canfd"), std::string::npos);
  EXPECT_NE(refusal("mock://?bus=can&bitrate=2000000").find("outside 10000 to 1000000"), std::string::npos);
  EXPECT_NE(refusal("mock://?bus=can&bitrate=fast").find("bad value"), std::string::npos);
  EXPECT_NE(refusal("mock://?bus=canfd&bitrate=1000000/500000").find("at least the nominal"),
            std::string::npos);
  EXPECT_NE(refusal("mock://?bus=canfd&bitrate=1000000/20000000").find("outside"), std::string::npos);
  EXPECT_NE(refusal("mock://?bus=can&bitrate=").find("needs a value"), std::string::npos);
  // report_bytes: what a high-speed unit declares (UsbSlots), 64..1024 whole bytes.
  EXPECT_EQ(parse_mock_uri("mock://?bus=hid-hs&report_bytes=512").options.bus.usb_report_bytes, 512U);
  for (const char* bad : {"63", "1025", "100.5", "nan", "x"}) {
    EXPECT_NE(refusal(std::string("mock://?bus=hid-hs&report_bytes=") + bad).find("report_bytes"),
              std::string::npos)
        << bad;
  }
  // deadband: the unit's sensor deadband in counts, 0..100 whole.
  EXPECT_EQ(parse_mock_uri("mock://?bus=can&deadband=2").options.sensor_deadband_counts, 2);
  for (const char* bad : {"-1", "101", "1.5", "nan", "x"}) {
    EXPECT_NE(refusal(std::string("mock://?deadband=") + bad).find("deadband"), std::string::npos) << bad;
  }
  // Built directly, a unit refuses a band it could not declare (SensorDeadband holds 0..100).
  for (const int bad : {-2, 101, 258}) {
    MockOptions o;
    o.sensor_deadband_counts = bad;
    EXPECT_THROW((void)MockDevice::make(o), InvalidArgument) << bad;
  }
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  try {
    (void)open_device("mock://?bus=hid-fs&report_bytes=512", clock, open);
    ADD_FAILURE() << "report_bytes on a full-speed unit";
  } catch (const InvalidArgument& e) {
    EXPECT_NE(std::string(e.what()).find("applies to a high-speed unit (bus=hid-hs), not bus=hid-fs"),
              std::string::npos)
        << e.what();
  }
}

// --- USB ---------------------------------------------------------------------------------------

// Two reports a 1 ms frame host to device on full speed: one slot a frame, so the second waits;
// the wait grows a frame every frame until usb_queue_reports wait, then one report a frame is
// dropped and counted.
TEST(MockBusUsb, TwoReportsAFrameQueueThenDrop) {
  MockBusOptions options = bus_options(MockBusKind::hid_fs);
  options.usb_queue_reports = 8;
  Rig rig(options);
  auto& [bus, sink] = rig;
  constexpr int kFrames = 40;
  std::vector<TimePoint> sent;
  for (int k = 0; k < kFrames; ++k) {
    const TimePoint t{milliseconds(k)};
    for (int r = 0; r < 2; ++r) {
      bus.host_sent(packet(proto::Heartbeat{static_cast<std::uint16_t>(sent.size())}), t, sink);
      sent.push_back(t);
    }
    bus.advance(t, sink);
  }
  bus.advance(TimePoint{milliseconds(kFrames + 20)}, sink);
  // Reports go out in order, one a frame: report i of those carried in frame i.
  ASSERT_FALSE(sink.log.empty());
  for (std::size_t i = 0; i < sink.log.size(); ++i) {
    EXPECT_TRUE(sink.log[i].to_device);
    EXPECT_EQ(sink.log[i].at, TimePoint{milliseconds(static_cast<int>(i))}) << i;
  }
  // Report 2k + r (frame k) is the (2k + r)th in the slots' order while none is dropped: it
  // waits k + r frames. The first dropped is the one that would be the 9th waiting: 2k + 1 - (k
  // + 1) = k = 8, in frame 8; from there on, each frame one is carried and one dropped.
  const std::size_t carried_before_drops = 2 * 8 + 1;
  const MockBusStats s = bus.stats();
  EXPECT_EQ(s.host_to_device.dropped, static_cast<std::uint64_t>(kFrames - 8));
  EXPECT_EQ(s.host_to_device.packets, sink.log.size());
  EXPECT_EQ(s.host_to_device.packets + s.host_to_device.dropped, sent.size());
  EXPECT_GE(sink.log.size(), carried_before_drops);
  // The longest wait: usb_queue_reports frames (a report behind 8 waiting ones).
  EXPECT_DOUBLE_EQ(s.host_to_device.max_wait_s, 8e-3);
  // Which reports were delivered: the heartbeat counters are the order they were sent in.
  for (std::size_t i = 0; i + 1 < sink.log.size(); ++i) {
    EXPECT_LT(sink.log[i].datagram.bytes[4], sink.log[i + 1].datagram.bytes[4]);
  }
  // No more than one report a frame, and the bytes carried are the packets' (8-byte heartbeats).
  EXPECT_EQ(s.host_to_device.bytes, 8U * sink.log.size());
  EXPECT_EQ(s.device_to_host.packets, 0U);
}

// A report that finds its frame's slot free is delivered when it is sent: the model changes
// nothing for a stream that fits.
TEST(MockBusUsb, AFreeSlotDeliversAtOnce) {
  Rig rig(bus_options(MockBusKind::hid_fs));
  auto& [bus, sink] = rig;
  for (int k = 0; k < 10; ++k) {
    const TimePoint t = TimePoint{milliseconds(k)} + microseconds(300);
    bus.device_sent(packet(proto::Heartbeat{static_cast<std::uint16_t>(k)}), t, sink);
    bus.host_sent(packet(proto::Heartbeat{static_cast<std::uint16_t>(k)}), t, sink);
    bus.advance(t, sink);
    ASSERT_EQ(sink.log.size(), 2U * (k + 1));
    EXPECT_EQ(sink.log[2 * static_cast<std::size_t>(k)].at, t);
    EXPECT_EQ(sink.log[2 * static_cast<std::size_t>(k) + 1].at, t);
  }
  const MockBusStats s = bus.stats();
  EXPECT_EQ(s.host_to_device.max_wait_s, 0.0);
  EXPECT_EQ(s.device_to_host.max_wait_s, 0.0);
  // 8 bytes a frame of the 64 a full-speed frame's report carries, over 9.3 ms.
  EXPECT_NEAR(s.device_to_host.load, 80.0 / (9.3e-3 * 64000.0), 1e-9);
}

// High speed: three reports a 125 us microframe (the figure a unit may declare).
TEST(MockBusUsb, HighSpeedCarriesThreeReportsAMicroframe) {
  Rig rig(bus_options(MockBusKind::hid_hs));
  auto& [bus, sink] = rig;
  for (int i = 0; i < 7; ++i) {
    bus.device_sent(packet(proto::Heartbeat{static_cast<std::uint16_t>(i)}), TimePoint{0}, sink);
  }
  bus.advance(TimePoint{milliseconds(1)}, sink);
  ASSERT_EQ(sink.log.size(), 7U);
  const std::array<std::int64_t, 7> due_us = {0, 0, 0, 125, 125, 125, 250};
  for (std::size_t i = 0; i < 7; ++i) {
    EXPECT_EQ(sink.log[i].at, TimePoint{microseconds(due_us[i])}) << i;
  }
}

// --- CAN ---------------------------------------------------------------------------------------

TEST(MockBusCan, FrameTimeIsTheWorstCaseStuffedLength) {
  for (std::size_t n = 0; n <= 8; ++n) {
    EXPECT_EQ(proto::can_frame_bits_worst_case(n, false), classic_worst_case_bits(n)) << n;
    EXPECT_DOUBLE_EQ(proto::can_frame_time_worst_case_s(n, false, 5e5, 5e6),
                     static_cast<double>(classic_worst_case_bits(n)) / 5e5)
        << n;
  }
  EXPECT_EQ(classic_worst_case_bits(8), 135U);
  // FD: the arbitration phase and the tail at the nominal rate, the rest at the data rate.
  const proto::CanFrameBits fd = proto::can_frame_bits_by_phase_worst_case(48, true);
  EXPECT_EQ(fd.nominal_bits, 17U + 4U + 12U);
  EXPECT_EQ(fd.nominal_bits + fd.data_bits, proto::can_frame_bits_worst_case(48, true));
  EXPECT_DOUBLE_EQ(proto::can_frame_time_worst_case_s(48, true, 1e6, 5e6),
                   33.0 / 1e6 + static_cast<double>(fd.data_bits) / 5e6);
}

// A heartbeat is one 8-byte frame: at 500 kbit/s it is delivered 135 bits x 2 us after it was
// sent, and two back to back take twice that.
TEST(MockBusCan, AFrameHoldsTheBusForItsStuffedBitTime) {
  MockBusOptions options = bus_options(MockBusKind::can);
  options.nominal_bitrate_bit_per_s = 5e5;
  Rig rig(options);
  auto& [bus, sink] = rig;
  const TimePoint t0{microseconds(1000)};
  bus.host_sent(packet(proto::Heartbeat{1}), t0, sink);
  bus.host_sent(packet(proto::Heartbeat{2}), t0, sink);
  bus.advance(t0, sink);
  EXPECT_TRUE(sink.log.empty());
  bus.advance(TimePoint{milliseconds(5)}, sink);
  ASSERT_EQ(sink.log.size(), 2U);
  const auto frame_ns = static_cast<std::int64_t>(classic_worst_case_bits(8) * 2000);  // 2 us a bit
  EXPECT_EQ(sink.log[0].at, t0 + std::chrono::nanoseconds(frame_ns));
  EXPECT_EQ(sink.log[1].at, t0 + std::chrono::nanoseconds(2 * frame_ns));
  const MockBusStats s = bus.stats();
  EXPECT_EQ(s.host_to_device.carried, 2U);
  EXPECT_EQ(s.host_to_device.bytes, 16U);
  EXPECT_NEAR(s.host_to_device.load, 2.0 * static_cast<double>(frame_ns) * 1e-9 / 5e-3, 1e-12);
  EXPECT_DOUBLE_EQ(s.host_to_device.max_wait_s, 2.0 * static_cast<double>(frame_ns) * 1e-9);
}

// While a frame is on the bus, frames of both nodes wait; when it ends, the lower identifier of
// the two queues' heads goes first (each node's queue is in order: the host's is Linux's qdisc).
// The unit's telemetry (TimeSync 0x021, then sensor blocks 0x201, 0x211, 0x221) and status
// (0x011) against the host's valve blocks (0x101, 0x111, 0x121), all sent while a state request
// (0x031) holds the bus.
TEST(MockBusCan, ArbitrationByIdentifier) {
  Rig rig(bus_options(MockBusKind::can));
  auto& [bus, sink] = rig;
  const TimePoint t0{0};
  bus.host_sent(packet(proto::StateRequest{1}), t0, sink);  // 0x031: on the bus from t0
  bus.advance(t0, sink);
  const TimePoint t1{microseconds(10)};
  bus.host_sent(packet(twelve_currents()), t1, sink);
  proto::Telemetry telemetry;
  telemetry.count = 12;
  bus.device_sent(packet(telemetry), t1, sink);
  const TimePoint t2{microseconds(20)};
  bus.device_sent(packet(proto::Status{}), t2, sink);
  bus.advance(TimePoint{milliseconds(5)}, sink);
  // 135 us a frame at 1 Mbit/s: StateRequest to 135; TimeSync beats 0x101 (to 270); the valve
  // blocks beat the sensor blocks behind it (to 675); the sensor blocks (to 1080); Status, behind
  // them in the unit's queue (to 1215).
  ASSERT_EQ(sink.log.size(), 4U);
  EXPECT_EQ(type_of(sink.log[0].datagram), proto::MessageType::state_request);
  EXPECT_EQ(sink.log[0].at, TimePoint{microseconds(135)});
  EXPECT_EQ(type_of(sink.log[1].datagram), proto::MessageType::valve_currents);
  EXPECT_EQ(sink.log[1].at, TimePoint{microseconds(675)});
  EXPECT_EQ(type_of(sink.log[2].datagram), proto::MessageType::telemetry);
  EXPECT_EQ(sink.log[2].at, TimePoint{microseconds(1080)});
  EXPECT_EQ(type_of(sink.log[3].datagram), proto::MessageType::status);
  EXPECT_EQ(sink.log[3].at, TimePoint{microseconds(1215)});
  const MockBusStats s = bus.stats();
  EXPECT_EQ(s.host_to_device.carried, 4U);
  EXPECT_EQ(s.device_to_host.carried, 5U);
}

// Heads of the two nodes' queues waiting at once: the lower identifier wins whichever was sent
// first.
TEST(MockBusCan, TheLowerIdentifierWinsWhicheverNodeSentFirst) {
  Rig rig(bus_options(MockBusKind::can));
  auto& [bus, sink] = rig;
  bus.host_sent(packet(proto::StateRequest{1}), TimePoint{0}, sink);  // holds the bus to 135 us
  bus.advance(TimePoint{0}, sink);
  bus.host_sent(packet(twelve_currents()), TimePoint{microseconds(1)}, sink);  // 0x101 first...
  bus.device_sent(packet(proto::Status{}), TimePoint{microseconds(2)}, sink);  // ...0x011 wins
  bus.advance(TimePoint{milliseconds(2)}, sink);
  ASSERT_EQ(sink.log.size(), 3U);
  EXPECT_EQ(type_of(sink.log[1].datagram), proto::MessageType::status);
  EXPECT_EQ(sink.log[1].at, TimePoint{microseconds(270)});
  EXPECT_EQ(type_of(sink.log[2].datagram), proto::MessageType::valve_currents);
  EXPECT_EQ(sink.log[2].at, TimePoint{microseconds(270 + 3 * 135)});
}

// The host writes more frames at once than the interface queues (txqueuelen 10): the write past
// it gets ENOBUFS, counted, and the frame goes out after the transport's backoff; nothing is lost.
TEST(MockBusCan, EnobufsPastTxqueuelenIsCountedAndRetried) {
  MockBusOptions options = bus_options(MockBusKind::can);
  options.can_txqueuelen_frames = 10;
  Rig rig(options);
  auto& [bus, sink] = rig;
  constexpr int kPackets = 6;  // 18 valve-block frames
  for (int i = 0; i < kPackets; ++i) {
    bus.host_sent(packet(twelve_currents(), static_cast<std::uint8_t>(i)), TimePoint{0}, sink);
  }
  bus.advance(TimePoint{0}, sink);
  // Ten frames queued, the eleventh write refused (the bus takes the first off the queue after).
  EXPECT_EQ(bus.stats().enobufs, 1U);
  bus.advance(TimePoint{milliseconds(20)}, sink);
  ASSERT_EQ(sink.log.size(), static_cast<std::size_t>(kPackets));
  for (int i = 0; i < kPackets; ++i) {
    EXPECT_EQ(sink.log[i].datagram.bytes[2], i) << "in order";
  }
  const MockBusStats s = bus.stats();
  EXPECT_EQ(s.host_to_device.dropped, 0U);
  EXPECT_EQ(s.host_to_device.carried, 3U * kPackets);
  EXPECT_GT(s.enobufs, 1U);  // the first retries, 100 and 200 us later, still find it full
  // The bus idles while the writer backs off, so the last packet ends no earlier than 18 frames.
  EXPECT_GE(sink.log.back().at, TimePoint{microseconds(18 * 135)});
}

// The unit's packets wait for its transmit queue; a newer telemetry sample takes the place of one
// none of whose frames went out yet, a full packet queue drops, and classic CAN has no heartbeat
// echo.
TEST(MockBusCan, TheUnitKeepsTheNewestSampleDropsPastItsQueueAndHasNoEcho) {
  MockBusOptions options = bus_options(MockBusKind::can);
  options.can_send_queue_packets = 2;
  Rig rig(options);
  auto& [bus, sink] = rig;
  proto::Telemetry telemetry;
  telemetry.count = 12;  // a TimeSync and 3 sensor blocks
  telemetry.device_time_us = 1;
  bus.device_sent(packet(telemetry), TimePoint{0}, sink);
  bus.advance(TimePoint{0}, sink);  // its frames are in the unit's queue, the first on the bus
  telemetry.device_time_us = 2;
  bus.device_sent(packet(telemetry), TimePoint{0}, sink);  // waits
  telemetry.device_time_us = 3;
  bus.device_sent(packet(telemetry), TimePoint{0}, sink);        // takes its place
  bus.device_sent(packet(proto::Status{}), TimePoint{0}, sink);  // two packets queued: dropped
  bus.device_sent(packet(proto::Heartbeat{7}), TimePoint{0}, sink);
  bus.advance(TimePoint{milliseconds(5)}, sink);
  ASSERT_EQ(sink.log.size(), 2U);
  const auto time_of = [](const Delivery& d) {
    const proto::PacketDecoded p =
        proto::decode_packet(std::span<const std::uint8_t>(d.datagram.bytes.data(), d.datagram.length));
    return std::get<proto::Telemetry>(p.message).device_time_us;
  };
  EXPECT_EQ(time_of(sink.log[0]), 1U);
  EXPECT_EQ(time_of(sink.log[1]), 3U);
  EXPECT_EQ(sink.log[1].at, TimePoint{microseconds(8 * 135)});
  const MockBusStats s = bus.stats();
  EXPECT_EQ(s.device_to_host.dropped, 2U);  // the superseded sample and the status
  EXPECT_EQ(s.device_to_host.unsent, 1U);
  EXPECT_EQ(s.device_to_host.packets, 2U);
  EXPECT_EQ(s.device_to_host.carried, 8U);
}

// On USB too the unit keeps one telemetry report waiting: a newer sample takes its slot.
TEST(MockBusUsb, ANewerSampleTakesTheWaitingOnesSlot) {
  Rig rig(bus_options(MockBusKind::hid_fs));
  auto& [bus, sink] = rig;
  bus.device_sent(packet(proto::Status{}), TimePoint{0}, sink);  // frame 0
  proto::Telemetry telemetry;
  telemetry.count = 12;
  for (std::uint32_t k = 1; k <= 3; ++k) {
    telemetry.device_time_us = k;
    bus.device_sent(packet(telemetry), TimePoint{microseconds(100 * k)}, sink);  // frame 1, waiting
  }
  bus.device_sent(packet(proto::Heartbeat{1}), TimePoint{microseconds(400)}, sink);  // frame 2
  bus.advance(TimePoint{milliseconds(3)}, sink);
  ASSERT_EQ(sink.log.size(), 3U);
  EXPECT_EQ(sink.log[1].at, TimePoint{milliseconds(1)});
  const proto::PacketDecoded p = proto::decode_packet(
      std::span<const std::uint8_t>(sink.log[1].datagram.bytes.data(), sink.log[1].datagram.length));
  EXPECT_EQ(std::get<proto::Telemetry>(p.message).device_time_us, 3U);
  EXPECT_EQ(sink.log[2].at, TimePoint{milliseconds(2)});
  EXPECT_EQ(bus.stats().device_to_host.dropped, 2U);
}

// --- protocol 1.2: packed reports ------------------------------------------------------------------

// Several packets in one datagram, sequences from 0 (append_packet).
Datagram packed(std::initializer_list<proto::Message> messages) {
  Datagram d;
  std::uint8_t sequence = 0;
  for (const proto::Message& m : messages) {
    const proto::EncodeResult r = proto::append_packet(m, sequence++, d.bytes, d.length);
    EXPECT_EQ(r.error, proto::Error::ok);
    d.length = static_cast<std::uint16_t>(d.length + r.bytes);
  }
  return d;
}

proto::Telemetry twelve_samples() {
  proto::Telemetry t;
  t.count = 12;
  return t;
}

TEST(MockBusUsb, APackedReportIsOneReportAndNoNewerSampleTakesItsPlace) {
  Rig rig(bus_options(MockBusKind::hid_fs));
  auto& [bus, sink] = rig;
  bus.device_sent(packet(proto::Status{}), TimePoint{0}, sink);  // frame 0
  const Datagram status_and_sample = packed({proto::Status{}, twelve_samples()});
  bus.device_sent(status_and_sample, TimePoint{microseconds(100)}, sink);         // frame 1, waiting
  bus.device_sent(packet(twelve_samples()), TimePoint{microseconds(200)}, sink);  // frame 2: no replacing
  bus.advance(TimePoint{milliseconds(3)}, sink);
  ASSERT_EQ(sink.log.size(), 3U);
  EXPECT_EQ(sink.log[1].at, TimePoint{milliseconds(1)});
  EXPECT_EQ(sink.log[1].datagram.length, status_and_sample.length);  // 11 + 37 bytes, one report
  EXPECT_EQ(sink.log[2].at, TimePoint{milliseconds(2)});
  const MockBusStats s = bus.stats();
  EXPECT_EQ(s.device_to_host.carried, 3U);
  EXPECT_EQ(s.device_to_host.packets, 4U);
  EXPECT_EQ(s.device_to_host.bytes, 11U + 48U + 37U);
  EXPECT_EQ(s.device_to_host.dropped, 0U);
}

TEST(MockBusCan, EachPacketOfAPackedReportArrivesWithItsOwnLastFrame) {
  Rig rig(bus_options(MockBusKind::can));
  auto& [bus, sink] = rig;
  const TimePoint t0{microseconds(1000)};
  bus.host_sent(packed({proto::Heartbeat{1}, twelve_currents()}), t0, sink);
  bus.advance(TimePoint{milliseconds(5)}, sink);
  ASSERT_EQ(sink.log.size(), 2U);
  const auto frame_ns = static_cast<std::int64_t>(classic_worst_case_bits(8) * 1000);  // 1 us a bit
  EXPECT_EQ(type_of(sink.log[0].datagram), proto::MessageType::heartbeat);
  EXPECT_EQ(sink.log[0].at, t0 + std::chrono::nanoseconds(frame_ns));  // the heartbeat frame
  EXPECT_EQ(type_of(sink.log[1].datagram), proto::MessageType::valve_currents);
  EXPECT_EQ(sink.log[1].at, t0 + std::chrono::nanoseconds(4 * frame_ns));  // then 3 valve blocks
  const MockBusStats s = bus.stats();
  EXPECT_EQ(s.host_to_device.carried, 4U);  // the frames of the two packets sent alone
  EXPECT_EQ(s.host_to_device.packets, 2U);
}

TEST(MockBusCan, APackedReportIsOneCanFdFrame) {
  Rig rig(bus_options(MockBusKind::canfd));
  auto& [bus, sink] = rig;
  const Datagram report = packed({proto::Status{}, proto::Heartbeat{1}, twelve_samples()});
  bus.device_sent(report, TimePoint{0}, sink);
  bus.advance(TimePoint{milliseconds(1)}, sink);
  ASSERT_EQ(sink.log.size(), 1U);
  EXPECT_EQ(sink.log[0].datagram.length, report.length);  // delivered whole
  const MockBusStats s = bus.stats();
  EXPECT_EQ(s.device_to_host.carried, 1U);
  EXPECT_EQ(s.device_to_host.packets, 3U);
  EXPECT_EQ(s.device_to_host.bytes, proto::canfd_padded_length(report.length));  // 56 -> 64
}

// --- through the unit ------------------------------------------------------------------------------

// A host that sends two heartbeats a 1 ms frame to a full-speed unit, which echoes each beside its
// telemetry (three reports a frame back): the echoes reach the host later and later, then some
// never do, and the unit's bus statistics count what was lost. Synchronous mock, simulated clock.
TEST(MockBusDevice, DelayAndLossReachTheHost) {
  MockOptions options;
  options.bus.kind = MockBusKind::hid_fs;
  options.bus.usb_queue_reports = 8;
  const std::shared_ptr<MockDevice> mock = MockDevice::make(options);
  constexpr std::int64_t kFrameNs = 1'000'000;
  SimulatedClock clock;
  const std::unique_ptr<Transport> link = mock->connect(true, &clock);
  std::vector<std::int64_t> sent_ns;
  std::vector<std::int64_t> echo_delay_ns;
  Datagram in;
  for (int k = 0; k < 60; ++k) {
    mock->step(clock.now());
    for (int r = 0; r < 2; ++r) {
      const Datagram d = packet(proto::Heartbeat{static_cast<std::uint16_t>(sent_ns.size())},
                                static_cast<std::uint8_t>(sent_ns.size()));
      ASSERT_EQ(link->send(std::span<const std::uint8_t>(d.bytes.data(), d.length)), ResultCode::ok);
      sent_ns.push_back(clock.now().count());
    }
    while (link->receive(in) == ResultCode::ok) {
      const proto::PacketDecoded p =
          proto::decode_packet(std::span<const std::uint8_t>(in.bytes.data(), in.length));
      if (const auto* h = std::get_if<proto::Heartbeat>(&p.message)) {
        ASSERT_LT(h->counter, sent_ns.size());
        echo_delay_ns.push_back(clock.now().count() - sent_ns[h->counter]);
      }
    }
    clock.advance(milliseconds(1));
  }
  ASSERT_FALSE(echo_delay_ns.empty());
  // The first frame's IN slot carries the telemetry: the first echo takes the next.
  EXPECT_EQ(echo_delay_ns.front(), kFrameNs);
  EXPECT_GE(*std::max_element(echo_delay_ns.begin(), echo_delay_ns.end()), 8 * kFrameNs);
  // At most 8 waiting each way, so at most 8 + 8 frames and the frame the host reads in.
  EXPECT_LE(*std::max_element(echo_delay_ns.begin(), echo_delay_ns.end()), 17 * kFrameNs);
  EXPECT_LT(echo_delay_ns.size(), sent_ns.size());
  const MockBusStats s = mock->bus_stats();
  EXPECT_EQ(s.kind, MockBusKind::hid_fs);
  EXPECT_GT(s.host_to_device.dropped, 0U);
  EXPECT_GT(s.device_to_host.dropped, 0U);
  // Every heartbeat was delivered, dropped, or still waits (at most 8).
  EXPECT_LE(s.host_to_device.packets + s.host_to_device.dropped, sent_ns.size());
  EXPECT_GE(s.host_to_device.packets + s.host_to_device.dropped + 8, sent_ns.size());
  EXPECT_DOUBLE_EQ(s.host_to_device.max_wait_s, 8e-3);
  EXPECT_DOUBLE_EQ(s.device_to_host.max_wait_s, 8e-3);
  EXPECT_LE(s.device_to_host.carried, 60U);  // one report a frame
}

// A unit whose plant lags real time (stepped 20 ms late, as a 64x64 plant on a loaded machine is)
// hears what the host queued meanwhile at its own time, outside the bus: on the bus the 20 reports
// would arrive in one frame and all but 9 be dropped (issue 20). A unit that keeps up is unchanged.
TEST(MockBusDevice, ALaggingUnitHearsTheHostOutsideTheBus) {
  for (const bool lagging : {false, true}) {
    MockOptions options;
    options.bus.kind = MockBusKind::hid_fs;
    options.bus.usb_queue_reports = 8;
    const std::shared_ptr<MockDevice> mock = MockDevice::make(options);
    const std::unique_ptr<Transport> link = mock->connect(false);
    TimePoint now{};
    mock->step(now);  // the bus starts
    for (int k = 0; k < 20; ++k) {
      const Datagram d =
          packet(proto::Heartbeat{static_cast<std::uint16_t>(k)}, static_cast<std::uint8_t>(k));
      ASSERT_EQ(link->send(std::span<const std::uint8_t>(d.bytes.data(), d.length)), ResultCode::ok);
      if (!lagging) {
        now += milliseconds(1);
        mock->step(now);
      }
    }
    mock->step(now + milliseconds(20));
    const MockBusStats s = mock->bus_stats();
    EXPECT_EQ(s.host_to_device.dropped, 0U) << "lagging " << lagging;
    EXPECT_EQ(s.host_while_lagging, lagging ? 20U : 0U);
    EXPECT_EQ(s.host_to_device.packets, lagging ? 0U : 20U);
  }
}

// A threaded unit that now and then wakes a millisecond late (its thread's scheduling) does not
// lag: the host's reports stay on the bus, each at the time the host sent it, so none waits behind
// another. With one late wake counted as lagging, the 5x5 daemon's currents went outside the bus
// (its host-to-device load read 0.2-5 % instead of 27 %); taken at the unit's wake, two reports
// arrived in one frame and one waited.
TEST(MockBusDevice, AUnitThatWakesLateKeepsTheHostOnTheBus) {
  MockOptions options;
  options.bus.kind = MockBusKind::hid_fs;
  const std::shared_ptr<MockDevice> mock = MockDevice::make(options);
  SimulatedClock clock;
  const std::unique_ptr<Transport> link = mock->connect(false, &clock);
  mock->step(clock.now());  // the bus starts
  for (int k = 1; k <= 30; ++k) {
    clock.advance(milliseconds(1));
    const Datagram d = packet(proto::Heartbeat{static_cast<std::uint16_t>(k)}, static_cast<std::uint8_t>(k));
    ASSERT_EQ(link->send(std::span<const std::uint8_t>(d.bytes.data(), d.length)), ResultCode::ok);
    if (k % 5 != 0) {
      mock->step(clock.now());  // the unit's thread misses every fifth wake
    }
  }
  clock.advance(milliseconds(1));
  mock->step(clock.now());
  const MockBusStats s = mock->bus_stats();
  EXPECT_EQ(s.host_while_lagging, 0U);
  EXPECT_EQ(s.host_to_device.packets, 30U);
  EXPECT_EQ(s.host_to_device.dropped, 0U);
  EXPECT_EQ(s.host_to_device.max_wait_s, 0.0);
}

// A synchronous host's packet enters the bus when the host sends it, not at the unit's next step
// (docs/protocol.md, "When a packet enters the bus"): currents a host's tick sends on classic CAN
// (a few frames, under 0.5 ms) drive the coils before the unit's next 1 ms step ends. Entering the
// bus at that step, they reached the coils a whole step later (the test fails so).
TEST(MockBusDevice, ASynchronousHostsPacketEntersTheBusWhenSent) {
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  const OpenedDevice dev = open_device("mock://?bus=can", clock, open);
  MockDevice& mock = *mock_of(dev);
  const auto tick = [&] {  // the rig's order: the unit steps to now, then the host's tick
    mock.step(clock.now());
    EXPECT_EQ(dev.session->poll(clock.now()), ResultCode::ok);
  };
  tick();
  ASSERT_EQ(dev.session->request_enable(), ResultCode::ok);
  for (int k = 0; k < 20 && mock.state() != static_cast<std::uint8_t>(proto::DeviceState::enabled); ++k) {
    clock.advance(milliseconds(1));
    tick();
  }
  ASSERT_EQ(mock.state(), static_cast<std::uint8_t>(proto::DeviceState::enabled));
  clock.advance(milliseconds(5));  // the re-seed's zero currents long delivered
  tick();
  const std::vector<double> request_A(mock.layout().valve_count(), 0.05);
  ASSERT_EQ(dev.session->send_valve_currents(request_A), ResultCode::ok);
  clock.advance(milliseconds(1));
  mock.step(clock.now());
  std::vector<double> applied_A(mock.layout().valve_count());
  mock.applied_currents(applied_A);
  EXPECT_GT(*std::min_element(applied_A.begin(), applied_A.end()), 0.0);
}

// bus=profile (the default): the unit is on the bus its profile names ([interface] bus): full-speed USB for
// the 5x5, high speed for the 16x16 (whose telemetry alone needs six full-speed reports a frame) and the
// 64x64 design (ModelProfile.TheInterfaceNamesTheBus).
TEST(MockBusDevice, BusProfileIsTheBusTheProfileNames) {
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  const auto kind_of = [&](const char* uri) {
    const OpenedDevice dev = open_device(uri, clock, open);
    return mock_of(dev)->bus_stats().kind;
  };
  EXPECT_EQ(kind_of("mock://"), MockBusKind::hid_fs);  // the default: the profile's bus
  EXPECT_EQ(kind_of("mock://?bus=none"), MockBusKind::none);
  EXPECT_EQ(kind_of("mock://?bus=none"), MockBusKind::none);
  EXPECT_EQ(kind_of("mock://?bus=profile"), MockBusKind::hid_fs);
  EXPECT_EQ(kind_of("mock://mr-skin-5x5?seed=2&bus=profile"), MockBusKind::hid_fs);
  EXPECT_EQ(kind_of("mock://fingertip-16x16?bus=profile"), MockBusKind::hid_hs);
  EXPECT_EQ(kind_of("mock://fingertip-16x16?bus=canfd"), MockBusKind::canfd);
  EXPECT_EQ(kind_of("mock://palm-64x64"), MockBusKind::hid_hs);
}

}  // namespace
}  // namespace mrskin::sim
