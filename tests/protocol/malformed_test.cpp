// Malformed input: each kind gives its own error code, never an exception or a crash.
#include <gtest/gtest.h>

#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "mrskin/protocol/can.hpp"
#include "mrskin/protocol/crc.hpp"
#include "mrskin/protocol/packed_report.hpp"
#include "mrskin/protocol/packet.hpp"
#include "mrskin/protocol/units.hpp"
#include "test_support.hpp"

namespace {

using namespace mrskin::protocol;
using namespace mrskin::protocol::test;

constexpr std::uint8_t kNode = 5;
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();

// Recomputes the CRC of a packet after a deliberate change to its header or payload.
void fix_crc(std::vector<std::uint8_t>& p) {
  const std::size_t body = kPacketHeaderBytes + p[3];
  p.resize(body + kPacketCrcBytes);
  const std::uint16_t c = crc16_ccitt({p.data(), body});
  p[body] = static_cast<std::uint8_t>(c & 0xFFU);
  p[body + 1] = static_cast<std::uint8_t>(c >> 8U);
}
void fix_crc8(CanFrame& f) {
  const std::array<std::uint8_t, 9> in{static_cast<std::uint8_t>((f.id >> 8U) & 0x7U),
                                       static_cast<std::uint8_t>(f.id & 0xFFU),
                                       f.data[0],
                                       f.data[1],
                                       f.data[2],
                                       f.data[3],
                                       f.data[4],
                                       f.data[5],
                                       f.data[6]};
  f.data[7] = crc8_j1850(in);
}
std::vector<std::uint8_t> heartbeat_packet() { return packet_bytes(Heartbeat{0x1234}, 7); }
Error encode_error(const Message& m) {
  std::array<std::uint8_t, kPacketMaxBytes> out{};
  return encode_packet(m, 0, out).error;
}
CanFrame classic_frame(const Message& m) { return can_frames(m, kNode, 3, 0).at(0); }

// ---- short ---------------------------------------------------------------------------

TEST(ProtocolMalformed, ShortPacket) {
  const auto p = heartbeat_packet();
  for (std::size_t n = 0; n < p.size(); ++n) {
    EXPECT_EQ(decode_packet({p.data(), n}).error, Error::short_buffer) << n << " bytes";
  }
}

TEST(ProtocolMalformed, ShortOutputBuffers) {
  std::array<std::uint8_t, 7> small{};
  EXPECT_EQ(encode_packet(Heartbeat{}, 0, small).error, Error::short_buffer);  // needs 8
  std::array<CanFrame, 2> two{};
  ValveCurrents v;
  v.count = 12;
  EXPECT_EQ(encode_can(v, kNode, 0, 0, two).error, Error::short_buffer);  // needs 3
  EXPECT_EQ(encode_can(Identity{1, 0, 0, 0, 0, 5, 5, 13, 12, 12, 1, 1000, 4095, 0, 1000, 100, 1000}, kNode, 0,
                       0, two)
                .error,
            Error::short_buffer);  // needs 6
  EXPECT_EQ(encode_can(Heartbeat{}, kNode, 0, 0, std::span<CanFrame>{}).error, Error::short_buffer);
}

TEST(ProtocolMalformed, ShortClassicFrame) {
  CanFrame f = classic_frame(Heartbeat{1});
  f.length = 7;
  CanDecoder dec(kNode);
  EXPECT_EQ(dec.decode(f).error, Error::short_buffer);
}

TEST(ProtocolMalformed, ShortCanFdFrame) {
  CanFrame f;
  ASSERT_EQ(encode_canfd(Heartbeat{1}, kNode, Direction::host_to_device, 0, f).error, Error::ok);
  f.length = 7;  // the packet is 8 bytes
  CanDecoder dec(kNode);
  EXPECT_EQ(dec.decode(f).error, Error::short_buffer);
}

// ---- too long ------------------------------------------------------------------------

TEST(ProtocolMalformed, TooLongPacket) {
  std::vector<std::uint8_t> p = heartbeat_packet();
  p.resize(kPacketMaxBytes, 0);
  EXPECT_EQ(decode_packet(p).error, Error::ok);  // 64 bytes with padding is fine
  p.push_back(0);
  EXPECT_EQ(decode_packet(p).error, Error::too_long);  // 65: e.g. a hid_write buffer by mistake
}

TEST(ProtocolMalformed, TooLongFrames) {
  CanDecoder dec(kNode);
  CanFrame f = classic_frame(Heartbeat{1});
  f.length = 9;
  EXPECT_EQ(dec.decode(f).error, Error::too_long);
  CanFrame fd;
  ASSERT_EQ(encode_canfd(Heartbeat{1}, kNode, Direction::host_to_device, 0, fd).error, Error::ok);
  fd.length = 65;
  EXPECT_EQ(dec.decode(fd).error, Error::too_long);
}

TEST(ProtocolMalformed, TooLongSegmentedTransfer) {
  CanDecoder dec(kNode);
  CanFrame f;
  f.id = can_id(CanFunction::management, 4, kNode);
  f.length = 8;
  f.data[0] = 0x10;
  f.data[1] = 65;  // first frame announcing 65 bytes: more than a packet
  EXPECT_EQ(dec.decode(f).error, Error::too_long);
}

// ---- bad CRC -------------------------------------------------------------------------

TEST(ProtocolMalformed, BadPacketCrc) {
  const auto good = heartbeat_packet();
  for (std::size_t i = 1; i < good.size(); ++i) {  // byte 0 is the version, checked first
    auto p = good;
    p[i] = static_cast<std::uint8_t>(p[i] ^ 0x01U);
    const Error e = decode_packet(p).error;
    // Flipping the length byte makes the packet look shorter or longer than it is.
    if (i == 3) {
      EXPECT_TRUE(e == Error::short_buffer || e == Error::bad_crc) << e;
    } else {
      EXPECT_EQ(e, Error::bad_crc) << "byte " << i;
    }
  }
}

TEST(ProtocolMalformed, BadFrameCrc) {
  CanDecoder dec(kNode);
  for (const Message& m :
       {Message{Heartbeat{1}}, Message{Status{1, 0, 0, 0}}, Message{TimeSync{5}}, Message{StateRequest{1}}}) {
    CanFrame f = classic_frame(m);
    f.data[7] ^= 0x80;
    EXPECT_EQ(dec.decode(f).error, Error::bad_crc) << m;
  }
  ValveCurrents v;
  v.count = 4;
  CanFrame f = classic_frame(v);
  f.data[2] ^= 0x10;
  EXPECT_EQ(dec.decode(f).error, Error::bad_crc);
  // The CRC covers the identifier: the same data on another block is refused.
  f = classic_frame(v);
  f.id = can_id(CanFunction::valve_block, 1, kNode);
  EXPECT_EQ(dec.decode(f).error, Error::bad_crc);
}

TEST(ProtocolMalformed, BadCrcInsideSegmentedTransfer) {
  Identity id{1, 0, 0, 0, 0, 5, 5, 13, 12, 12, 1, 1000, 4095, 0, 1000, 100, 1000};
  auto frames = can_frames(id, kNode, 0, 1);
  frames[2].data[3] ^= 0xFF;  // corrupt the reassembled packet
  CanDecoder dec(kNode);
  CanDecoded d;
  for (const CanFrame& f : frames) d = dec.decode(f);
  EXPECT_EQ(d.error, Error::bad_crc);
  EXPECT_FALSE(d.complete);
}

// ---- unknown type --------------------------------------------------------------------

TEST(ProtocolMalformed, UnknownPacketType) {
  for (const int type : {0x00, 0x05, 0x12, 0x22, 0x33, 0x44, 0xFF}) {
    auto p = heartbeat_packet();
    p[1] = static_cast<std::uint8_t>(type);
    fix_crc(p);
    EXPECT_EQ(decode_packet(p).error, Error::unknown_type) << type;
  }
}

TEST(ProtocolMalformed, UnknownCanIdentifiers) {
  CanDecoder dec(kNode);
  CanFrame f = classic_frame(Heartbeat{1});
  for (const unsigned block : {6U, 7U, 15U}) {  // management blocks not defined in v1
    f.id = can_id(CanFunction::management, static_cast<std::uint8_t>(block), kNode);
    fix_crc8(f);
    EXPECT_EQ(dec.decode(f).error, Error::unknown_type) << block;
  }
  for (const unsigned fn : {6U, 7U}) {  // functions not defined in v1
    f.id = (fn << 8U) | kNode;
    fix_crc8(f);
    EXPECT_EQ(dec.decode(f).error, Error::unknown_type) << fn;
  }
  f.id = 0x800U | kNode;  // not an 11-bit identifier
  EXPECT_EQ(dec.decode(f).error, Error::unknown_type);
  // CAN FD functions need FD frames, and FD frames need FD functions.
  f.id = can_id(CanFunction::fd_host_to_device, 0, kNode);
  EXPECT_EQ(dec.decode(f).error, Error::unknown_type);
  CanFrame fd;
  ASSERT_EQ(encode_canfd(Heartbeat{1}, kNode, Direction::host_to_device, 0, fd).error, Error::ok);
  fd.id = can_id(CanFunction::valve_block, 0, kNode);
  EXPECT_EQ(dec.decode(fd).error, Error::unknown_type);
  fd.id = can_id(CanFunction::fd_host_to_device, 1, kNode);  // FD uses block 0 only
  EXPECT_EQ(dec.decode(fd).error, Error::unknown_type);
}

// ---- wrong version -------------------------------------------------------------------

TEST(ProtocolMalformed, WrongVersionNamesThePeerVersion) {
  for (const int version : {0, 2, 0xFF}) {
    auto p = heartbeat_packet();
    p[0] = static_cast<std::uint8_t>(version);
    fix_crc(p);
    const PacketDecoded d = decode_packet(p);
    EXPECT_EQ(d.error, Error::wrong_version);
    EXPECT_EQ(d.peer_version, version);
    EXPECT_NE(d.peer_version, kVersionMajor);
  }
  // A v2 packet may have another layout: the version is refused before length and CRC.
  std::vector<std::uint8_t> v2{2, 0x31, 0, 200, 0, 0, 0, 0};
  const PacketDecoded d = decode_packet(v2);
  EXPECT_EQ(d.error, Error::wrong_version);
  EXPECT_EQ(d.peer_version, 2);
}

TEST(ProtocolMalformed, WrongVersionOverCan) {
  // CAN FD frame.
  CanFrame fd;
  ASSERT_EQ(encode_canfd(Heartbeat{1}, kNode, Direction::host_to_device, 0, fd).error, Error::ok);
  fd.data[0] = 2;
  CanDecoder dec(kNode);
  CanDecoded d = dec.decode(fd);
  EXPECT_EQ(d.error, Error::wrong_version);
  EXPECT_EQ(d.peer_version, 2);
  // Segmented identity from a v3 device.
  std::vector<std::uint8_t> p =
      packet_bytes(Identity{3, 1, 0, 0, 0, 5, 5, 13, 12, 12, 1, 1000, 4095, 0, 1000, 100, 1000}, 0);
  p[0] = 3;
  fix_crc(p);
  CanFrame first;
  first.id = can_id(CanFunction::management, 5, kNode);
  first.length = 8;
  first.data[0] = 0x10;
  first.data[1] = static_cast<std::uint8_t>(p.size());
  std::copy_n(p.begin(), 6, first.data.begin() + 2);
  d = dec.decode(first);
  ASSERT_EQ(d.error, Error::ok);
  for (std::size_t pos = 6, index = 1; pos < p.size(); pos += 7, ++index) {
    CanFrame cf;
    cf.id = first.id;
    cf.length = 8;
    cf.data[0] = static_cast<std::uint8_t>(0x20U | index);
    std::copy_n(p.begin() + static_cast<std::ptrdiff_t>(pos), std::min<std::size_t>(7, p.size() - pos),
                cf.data.begin() + 1);
    d = dec.decode(cf);
  }
  EXPECT_EQ(d.error, Error::wrong_version);
  EXPECT_EQ(d.peer_version, 3);
}

// ---- out-of-range fields -------------------------------------------------------------

TEST(ProtocolMalformed, OutOfRangeOnEncode) {
  ValveCurrents v;
  v.count = 0;
  EXPECT_EQ(encode_error(v), Error::out_of_range);
  v.count = kMaxValveCurrents + 1;
  EXPECT_EQ(encode_error(v), Error::out_of_range);
  v.count = 1;
  v.counts[0] = kCurrentCountMax + 1;
  EXPECT_EQ(encode_error(v), Error::out_of_range);

  Telemetry t;
  t.count = 2;
  t.counts[1] = kSensorCountMax + 1;
  EXPECT_EQ(encode_error(t), Error::out_of_range);
  t.counts[1] = kSensorCountMin - 1;
  EXPECT_EQ(encode_error(t), Error::out_of_range);
  t.counts[1] = 0;
  t.count = kMaxTelemetryValues + 1;
  EXPECT_EQ(encode_error(t), Error::out_of_range);

  for (const CellTarget bad :
       {CellTarget{kStiffnessCountMax + 1, 0, 0, 0}, CellTarget{0, kOffsetCountMax + 1, 0, 0},
        CellTarget{0, 0, kCeilingCountMax + 1, 0}, CellTarget{0, 0, 0, kValidityCountMax + 1}}) {
    CellTargets c;
    c.count = 1;
    c.targets[0] = bad;
    EXPECT_EQ(encode_error(c), Error::out_of_range) << c;
  }
  CellTargets c8;
  c8.count = kMaxCellTargets + 1;
  EXPECT_EQ(encode_error(c8), Error::out_of_range);

  EXPECT_EQ(encode_error(Status{4, 0, 0, 0}), Error::out_of_range);
  EXPECT_EQ(encode_error(Status{0, 8, 0, 0}), Error::out_of_range);
  EXPECT_EQ(encode_error(StateRequest{5}), Error::out_of_range);
  EXPECT_EQ(encode_error(ConfigRead{1, 0, 0}), Error::out_of_range);
  EXPECT_EQ(encode_error(ConfigRead{1, 0, kMaxConfigBytes + 1}), Error::out_of_range);
  ConfigWrite w;
  w.total = 10;
  w.offset = 8;
  w.length = 3;  // past the end of the blob
  EXPECT_EQ(encode_error(w), Error::out_of_range);
  w.offset = 0;
  w.total = 100;
  w.length = kMaxConfigBytes + 1;
  EXPECT_EQ(encode_error(w), Error::out_of_range);
  EXPECT_EQ(encode_error(ConfigAck{1, 0, 5}), Error::out_of_range);
  // UsbSlots: 64..1024 bytes, 1..3 reports, an interval of 125, 250, 500 or 1000 us.
  EXPECT_EQ(encode_error(UsbSlots{64, 1, 1000}), Error::ok);
  EXPECT_EQ(encode_error(UsbSlots{1024, 3, 125}), Error::ok);
  EXPECT_EQ(encode_error(UsbSlots{63, 1, 1000}), Error::out_of_range);
  EXPECT_EQ(encode_error(UsbSlots{1025, 1, 1000}), Error::out_of_range);
  EXPECT_EQ(encode_error(UsbSlots{64, 0, 1000}), Error::out_of_range);
  EXPECT_EQ(encode_error(UsbSlots{64, 4, 125}), Error::out_of_range);
  EXPECT_EQ(encode_error(UsbSlots{64, 1, 2000}), Error::out_of_range);
  EXPECT_EQ(encode_error(UsbSlots{64, 1, 0}), Error::out_of_range);
  // SensorDeadband: 0 (none) to kSensorDeadbandMaxCounts.
  EXPECT_EQ(encode_error(SensorDeadband{0}), Error::ok);
  EXPECT_EQ(encode_error(SensorDeadband{kSensorDeadbandMaxCounts}), Error::ok);
  EXPECT_EQ(encode_error(SensorDeadband{kSensorDeadbandMaxCounts + 1}), Error::out_of_range);

  Identity id{1, 0, 0, 0, 0, 5, 5, 13, 12, 12, 1, 1000, 4095, 0, 1000, 100, 1000};
  EXPECT_EQ(encode_error(id), Error::ok);
  Identity bad = id;
  bad.current_max_counts = kCurrentCountMax + 1;
  EXPECT_EQ(encode_error(bad), Error::out_of_range);
  bad = id;
  bad.sensor_quantity = 3;
  EXPECT_EQ(encode_error(bad), Error::out_of_range);
  bad = id;
  bad.current_lsb_nA = 0;
  EXPECT_EQ(encode_error(bad), Error::out_of_range);
  bad = id;
  bad.sensor_lsb_nano = 0;
  EXPECT_EQ(encode_error(bad), Error::out_of_range);
}

TEST(ProtocolMalformed, OutOfRangeOnCanEncode) {
  std::array<CanFrame, 16> out{};
  EXPECT_EQ(encode_can(Heartbeat{}, 0, 0, 0, out).error, Error::out_of_range);  // node 0
  EXPECT_EQ(encode_can(Heartbeat{}, 16, 0, 0, out).error, Error::out_of_range);
  CanFrame fd;
  EXPECT_EQ(encode_canfd(Heartbeat{}, 0, Direction::host_to_device, 0, fd).error, Error::out_of_range);
  ValveCurrents v;
  v.first = 2;  // blocks start at multiples of 4
  v.count = 4;
  EXPECT_EQ(encode_can(v, kNode, 0, 0, out).error, Error::out_of_range);
  v.first = 60;
  v.count = 8;  // valves 60..67: past block 15
  EXPECT_EQ(encode_can(v, kNode, 0, 0, out).error, Error::out_of_range);
  Telemetry t;
  t.first = 1;
  t.count = 1;
  EXPECT_EQ(encode_can(t, kNode, 0, 0, out).error, Error::out_of_range);
  CellTargets c;
  c.first = 255;
  c.count = 2;  // cell 256 has no CAN address
  EXPECT_EQ(encode_can(c, kNode, 0, 0, out).error, Error::out_of_range);
  // The fields themselves are checked on every framing.
  v.first = 0;
  v.count = 1;
  v.counts[0] = 5000;
  EXPECT_EQ(encode_can(v, kNode, 0, 0, out).error, Error::out_of_range);
  EXPECT_EQ(encode_canfd(v, kNode, Direction::host_to_device, 0, fd).error, Error::out_of_range);
}

TEST(ProtocolMalformed, OutOfRangeOnDecode) {
  // A well-formed packet (right length and CRC) whose fields break the v1 domains.
  auto p = packet_bytes(ValveCurrents{0, 1, {100}}, 0);
  p[7] = 0x00;
  p[8] = 0x10;  // 4096
  fix_crc(p);
  EXPECT_EQ(decode_packet(p).error, Error::out_of_range);

  Telemetry t;
  t.count = 1;
  p = packet_bytes(t, 0);
  p[11] = 0x00;
  p[12] = 0x08;  // +2048
  fix_crc(p);
  EXPECT_EQ(decode_packet(p).error, Error::out_of_range);

  p = packet_bytes(Status{0, 0, 0, 0}, 0);
  p[4] = 9;  // state 9
  fix_crc(p);
  EXPECT_EQ(decode_packet(p).error, Error::out_of_range);

  p = packet_bytes(ValveCurrents{0, 1, {100}}, 0);
  p[6] = 0;  // count 0 with a 3-byte payload
  p[3] = 3;
  fix_crc(p);
  EXPECT_EQ(decode_packet(p).error, Error::out_of_range);

  // Classic CAN: a valve block announcing 0 or 5 values.
  CanDecoder dec(kNode);
  ValveCurrents v;
  v.count = 4;
  CanFrame f = classic_frame(v);
  for (const unsigned n : {0U, 5U, 15U}) {
    f.data[6] = static_cast<std::uint8_t>((f.data[6] & 0xF0U) | n);
    fix_crc8(f);
    EXPECT_EQ(dec.decode(f).error, Error::out_of_range) << n;
  }
  // Status state 7 on classic CAN.
  f = classic_frame(Status{0, 0, 0, 0});
  f.data[0] = 7;
  fix_crc8(f);
  EXPECT_EQ(dec.decode(f).error, Error::out_of_range);
}

// ---- bad length ----------------------------------------------------------------------

TEST(ProtocolMalformed, BadLength) {
  auto p = heartbeat_packet();
  p.insert(p.begin() + 6, 0x00);  // heartbeat with a 3-byte payload
  p[3] = 3;
  fix_crc(p);
  EXPECT_EQ(decode_packet(p).error, Error::bad_length);
  p = heartbeat_packet();
  p[3] = 1;  // 1-byte payload
  p.erase(p.begin() + 5);
  fix_crc(p);
  EXPECT_EQ(decode_packet(p).error, Error::bad_length);
  // A count that disagrees with the payload length.
  p = packet_bytes(ValveCurrents{0, 2, {1, 2}}, 0);
  p[6] = 3;
  fix_crc(p);
  EXPECT_EQ(decode_packet(p).error, Error::bad_length);
  // A length byte beyond the 58-byte maximum.
  std::vector<std::uint8_t> big(kPacketMaxBytes, 0);
  big[0] = kVersionMajor;
  big[1] = static_cast<std::uint8_t>(MessageType::heartbeat);
  big[3] = kPacketMaxPayload + 1;
  EXPECT_EQ(decode_packet(big).error, Error::bad_length);
}

// ---- counter gaps --------------------------------------------------------------------

TEST(ProtocolMalformed, CounterGapModulus16) {
  CounterTracker c(16);
  EXPECT_EQ(c.accept(14), Error::ok);  // first value is always accepted
  EXPECT_EQ(c.accept(15), Error::ok);
  EXPECT_EQ(c.accept(0), Error::ok);  // wraparound
  EXPECT_EQ(c.missed(), 0U);
  EXPECT_EQ(c.accept(3), Error::counter_gap);
  EXPECT_EQ(c.missed(), 2U);  // 1 and 2
  EXPECT_EQ(c.accept(4), Error::ok);
  EXPECT_EQ(c.missed(), 0U);
  EXPECT_EQ(c.accept(15), Error::counter_gap);
  EXPECT_EQ(c.missed(), 10U);                  // 5..14
  EXPECT_EQ(c.accept(1), Error::counter_gap);  // gap across the wrap: 0 missed
  EXPECT_EQ(c.missed(), 1U);
  EXPECT_EQ(c.accept(1), Error::counter_gap);  // a repeat reads as 15 missed
  EXPECT_EQ(c.missed(), 15U);
  c.reset();
  EXPECT_EQ(c.accept(9), Error::ok);
}

TEST(ProtocolMalformed, CounterGapModulus256) {
  CounterTracker c;  // 0 = 256: packet sequence numbers
  EXPECT_EQ(c.accept(254), Error::ok);
  EXPECT_EQ(c.accept(255), Error::ok);
  EXPECT_EQ(c.accept(0), Error::ok);
  EXPECT_EQ(c.accept(1), Error::ok);
  EXPECT_EQ(c.accept(5), Error::counter_gap);
  EXPECT_EQ(c.missed(), 3U);
  EXPECT_EQ(c.accept(6), Error::ok);
  EXPECT_EQ(c.accept(5), Error::counter_gap);  // going back
  EXPECT_EQ(c.missed(), 254U);
  for (unsigned i = 0; i < 600; ++i) {
    EXPECT_EQ(c.accept(static_cast<std::uint8_t>((6 + i) & 0xFFU)), Error::ok) << i;
  }
}

// ---- CAN node and segments -----------------------------------------------------------

TEST(ProtocolMalformed, WrongNode) {
  CanDecoder dec(kNode);
  const auto on_other = can_frames(Heartbeat{1}, 6, 0, 0).at(0);
  EXPECT_EQ(dec.decode(on_other).error, Error::wrong_node);
  CanFrame fd;
  ASSERT_EQ(encode_canfd(Heartbeat{1}, 4, Direction::host_to_device, 0, fd).error, Error::ok);
  EXPECT_EQ(dec.decode(fd).error, Error::wrong_node);
  const auto seg = can_frames(ConfigRead{1, 0, 4}, 1, 0, 0);
  EXPECT_EQ(dec.decode(seg.at(0)).error, Error::wrong_node);
}

TEST(ProtocolMalformed, BadSegmentOrder) {
  const auto frames = can_frames(ConfigData{{2, 0, 100, 40, {}}}, kNode, 0, 1);  // 53 bytes, 8 frames
  ASSERT_EQ(frames.size(), 8U);
  {
    CanDecoder dec(kNode);  // consecutive frame with no first frame
    EXPECT_EQ(dec.decode(frames[1]).error, Error::bad_segment);
  }
  {
    CanDecoder dec(kNode);  // a frame skipped
    EXPECT_EQ(dec.decode(frames[0]).error, Error::ok);
    EXPECT_EQ(dec.decode(frames[1]).error, Error::ok);
    EXPECT_EQ(dec.decode(frames[3]).error, Error::bad_segment);
    // The transfer is abandoned: later frames of it are refused too.
    EXPECT_EQ(dec.decode(frames[4]).error, Error::bad_segment);
    // A new first frame starts over and completes.
    CanDecoded d;
    for (const CanFrame& f : frames) d = dec.decode(f);
    EXPECT_EQ(d.error, Error::ok);
    EXPECT_TRUE(d.complete);
  }
  {
    CanDecoder dec(kNode);  // a frame repeated
    EXPECT_EQ(dec.decode(frames[0]).error, Error::ok);
    EXPECT_EQ(dec.decode(frames[1]).error, Error::ok);
    EXPECT_EQ(dec.decode(frames[1]).error, Error::bad_segment);
  }
  CanDecoder dec(kNode);
  CanFrame f = frames[0];
  f.data[0] = 0x30;  // flow control: not used in v1
  EXPECT_EQ(dec.decode(f).error, Error::bad_segment);
  f.data[0] = 0x00;  // single frame of 0 bytes
  EXPECT_EQ(dec.decode(f).error, Error::bad_segment);
  f.data[0] = 0x08;  // single frame of 8 bytes: cannot fit
  EXPECT_EQ(dec.decode(f).error, Error::bad_segment);
  f.data[0] = 0x10;
  f.data[1] = 7;  // first frame for 7 bytes: should have been a single frame
  EXPECT_EQ(dec.decode(f).error, Error::bad_segment);
}

TEST(ProtocolMalformed, SegmentedDirectionsAreIndependent) {
  // A device->host identity and a host->device config write interleaved frame by frame.
  const auto a =
      can_frames(Identity{1, 0, 0, 0, 0, 5, 5, 13, 12, 12, 1, 1000, 4095, 0, 1000, 100, 1000}, kNode, 0, 1);
  ConfigWrite w;
  w.total = 4;
  w.length = 4;
  const auto b = can_frames(w, kNode, 0, 2);
  CanDecoder dec(kNode);
  int complete = 0;
  for (std::size_t i = 0; i < std::max(a.size(), b.size()); ++i) {
    for (const auto* frames : {&a, &b}) {
      if (i >= frames->size()) continue;
      const CanDecoded d = dec.decode((*frames)[i]);
      ASSERT_EQ(d.error, Error::ok);
      complete += d.complete ? 1 : 0;
    }
  }
  EXPECT_EQ(complete, 2);
}

// ---- quantisation: NaN, Inf and out-of-range SI values ---------------------------------

Identity unit_identity() {
  Identity id;
  id.current_lsb_nA = 125000;    // 125 uA
  id.current_max_counts = 4000;  // 0.5 A
  id.sensor_lsb_nano = 2500;     // 2.5 um
  return id;
}

TEST(ProtocolMalformed, NotFiniteIsRefused) {
  const Identity id = unit_identity();
  for (const double bad : {kNaN, kInf, -kInf}) {
    EXPECT_EQ(quantize_unsigned(bad, 1.0, 100).error, Error::not_finite);
    EXPECT_EQ(quantize_signed(bad, 1.0, -100, 100).error, Error::not_finite);
    EXPECT_EQ(quantize_current(bad, id).error, Error::not_finite);
    EXPECT_EQ(quantize_sensor(bad, id).error, Error::not_finite);
    EXPECT_EQ(quantize_unsigned(1.0, bad, 100).error, Error::not_finite);  // a bad LSB too
    for (int field = 0; field < 4; ++field) {
      CellTargetSi si{300.0, 1e-3, 1.0, 0.1};
      (field == 0   ? si.stiffness_N_per_m
       : field == 1 ? si.offset_m
       : field == 2 ? si.ceiling_N
                    : si.validity_s) = bad;
      EXPECT_EQ(quantize_cell_target(si).error, Error::not_finite) << field;
    }
  }
  EXPECT_EQ(quantize_cell_target({300.0, 1e-3, 1.0, 0.1}).error, Error::ok);
}

TEST(ProtocolMalformed, OutOfRangeSiValues) {
  const Identity id = unit_identity();
  EXPECT_EQ(quantize_current(0.5, id).error, Error::ok);
  EXPECT_EQ(quantize_current(0.5, id).counts, 4000);
  EXPECT_EQ(quantize_current(0.5 + 62e-6, id).counts, 4000);                // rounds down, within half an LSB
  EXPECT_EQ(quantize_current(0.5 + 63e-6, id).error, Error::out_of_range);  // the device's maximum
  EXPECT_EQ(quantize_current(-1e-3, id).error, Error::out_of_range);        // coils are unipolar
  EXPECT_EQ(quantize_current(-62e-6, id).counts, 0);
  EXPECT_EQ(quantize_current(1e300, id).error, Error::out_of_range);

  EXPECT_EQ(quantize_sensor(2047 * 2.5e-6, id).counts, 2047);
  EXPECT_EQ(quantize_sensor(2048 * 2.5e-6, id).error, Error::out_of_range);
  EXPECT_EQ(quantize_sensor(-2048 * 2.5e-6, id).counts, -2048);
  EXPECT_EQ(quantize_sensor(-2049 * 2.5e-6, id).error, Error::out_of_range);

  EXPECT_EQ(quantize_cell_target({-10.0, 0, 0, 0}).error, Error::out_of_range);       // negative stiffness
  EXPECT_EQ(quantize_cell_target({32768.0, 0, 0, 0}).error, Error::out_of_range);     // > 16383 x 2 N/m
  EXPECT_EQ(quantize_cell_target({0, 8.2e-3, 0, 0}).error, Error::out_of_range);      // > 4095 x 2 um
  EXPECT_EQ(quantize_cell_target({0, 0, 4.1, 0}).error, Error::out_of_range);         // > 4.095 N
  EXPECT_EQ(quantize_cell_target({0, 0, 0, 0.64}).error, Error::out_of_range);        // > 630 ms
  EXPECT_EQ(quantize_cell_target({32766.0, 8.19e-3, 4.095, 0.63}).error, Error::ok);  // the maxima

  // A count that would read back as Inf is refused (found by the quantize fuzzer in CI).
  EXPECT_EQ(quantize_unsigned(1.7e308, 1e308, 100).error, Error::out_of_range);
  EXPECT_EQ(quantize_signed(-1.7e308, 1e308, -100, 100).error, Error::out_of_range);
  EXPECT_EQ(quantize_unsigned(1.4e308, 1e308, 100).counts, 1);

  // An LSB of zero or below cannot quantise anything.
  EXPECT_EQ(quantize_unsigned(1.0, 0.0, 100).error, Error::not_finite);
  EXPECT_EQ(quantize_unsigned(1.0, -1.0, 100).error, Error::not_finite);
}

// ---- protocol 1.2: packed reports --------------------------------------------------------

// Heartbeat (8 bytes), second packet (given), Status (11 bytes): one report.
std::vector<std::uint8_t> report_with_middle(const std::vector<std::uint8_t>& middle) {
  std::vector<std::uint8_t> r = packet_bytes(Heartbeat{7}, 1);
  r.insert(r.end(), middle.begin(), middle.end());
  const std::vector<std::uint8_t> status = packet_bytes(Status{1, 0, 0, 0}, 3);
  r.insert(r.end(), status.begin(), status.end());
  r.resize(kHidReportBytes, 0);
  return r;
}

struct Walked {
  std::vector<Error> errors;
  std::vector<Message> messages;
  bool broken = false;
};
Walked walk(std::span<const std::uint8_t> report) {
  Walked w;
  PacketWalker walker(report);
  PacketDecoded d;
  while (walker.next(d)) {
    w.errors.push_back(d.error);
    w.messages.push_back(d.message);
  }
  w.broken = walker.broken();
  return w;
}

// The second packet of report_with_middle(middle): its error, and whether the walk read on.
// Broken framing ends the walk after it (the Status is not read); intact framing goes on.
void expect_middle(const std::vector<std::uint8_t>& middle, Error error, bool broken) {
  const Walked w = walk(report_with_middle(middle));
  ASSERT_EQ(w.errors.size(), broken ? 2U : 3U) << to_string(error);
  EXPECT_EQ(w.errors[0], Error::ok);
  EXPECT_EQ(w.messages[0], Message(Heartbeat{7}));  // the packet before it stands
  EXPECT_EQ(w.errors[1], error);
  EXPECT_EQ(w.broken, broken);
  if (!broken) {
    EXPECT_EQ(w.errors[2], Error::ok);
    EXPECT_EQ(w.messages[2], Message(Status{1, 0, 0, 0}));
  }
}

// A heartbeat packet (sequence 2) with one byte set, and its CRC recomputed when fix.
std::vector<std::uint8_t> changed_heartbeat(std::size_t at, std::uint8_t value, bool fix) {
  std::vector<std::uint8_t> p = packet_bytes(Heartbeat{8}, 2);
  p[at] = value;
  if (fix) fix_crc(p);
  return p;
}

TEST(ProtocolMalformedPacked, BrokenFramingEndsTheWalkAfterTheFirstPacket) {
  std::vector<std::uint8_t> bad_crc = packet_bytes(Heartbeat{8}, 2);
  bad_crc.back() ^= 0x01U;
  expect_middle(bad_crc, Error::bad_crc, true);
  expect_middle(changed_heartbeat(0, 2, false), Error::wrong_version, true);
  expect_middle(changed_heartbeat(3, 59, false), Error::bad_length, true);  // length byte over 58
  // Claims 58 payload bytes: 64 in all, past the report's 64 - 8.
  std::vector<std::uint8_t> r = packet_bytes(Heartbeat{7}, 1);
  const std::vector<std::uint8_t> big = changed_heartbeat(3, 58, false);
  r.insert(r.end(), big.begin(), big.end());
  r.resize(kHidReportBytes, 0xEE);
  const Walked w = walk(r);
  ASSERT_EQ(w.errors.size(), 2U);
  EXPECT_EQ(w.errors[1], Error::short_buffer);
  EXPECT_TRUE(w.broken);
}

TEST(ProtocolMalformedPacked, RefusedContentWithIntactFramingIsSkipped) {
  // A later minor version's message: its CRC holds, so the walk goes on to the Status.
  expect_middle(changed_heartbeat(1, 0x7E, true), Error::unknown_type, false);
  // So is a payload that disagrees with its type, and a field out of its domain.
  std::vector<std::uint8_t> short_payload = changed_heartbeat(3, 1, true);
  expect_middle(short_payload, Error::bad_length, false);
  std::vector<std::uint8_t> bad_state = packet_bytes(StateRequest{1}, 2);
  bad_state[4] = 9;
  fix_crc(bad_state);
  expect_middle(bad_state, Error::out_of_range, false);
}

TEST(ProtocolMalformedPacked, EmptyOverlongAndTruncatedReports) {
  EXPECT_TRUE(walk({}).errors.empty());
  const std::array<std::uint8_t, kHidReportBytes> zeros{};
  EXPECT_TRUE(walk(zeros).errors.empty());  // all padding: no packet, no error
  // Longer than the largest report a unit may declare (UsbSlots, 1024 bytes).
  const std::vector<std::uint8_t> overlong(kUsbSlotsMaxReportBytes + 1, 0x01);
  const Walked o = walk(overlong);
  ASSERT_EQ(o.errors.size(), 1U);
  EXPECT_EQ(o.errors[0], Error::too_long);
  std::vector<std::uint8_t> r = packet_bytes(Heartbeat{7}, 1);
  r.push_back(0x01);  // a version byte and nothing after it
  const Walked t = walk(r);
  ASSERT_EQ(t.errors.size(), 2U);
  EXPECT_EQ(t.errors[1], Error::short_buffer);
}

// A high-speed unit's report (UsbSlots: up to 1024 bytes) holds as many whole packets as fit,
// and the walk hands every one out, in order.
TEST(ProtocolMalformedPacked, AReportOfTheLargestDeclaredSizeWalksToEveryPacket) {
  std::vector<std::uint8_t> report(kUsbSlotsMaxReportBytes, 0xCC);
  std::size_t used = 0;
  std::uint8_t sequence = 0;
  Telemetry t;
  t.count = kMaxTelemetryValues;  // 63-byte packets (57 payload bytes): 16 fit in 1024 bytes
  for (;;) {
    t.first = static_cast<std::uint16_t>(sequence * kMaxTelemetryValues);
    const EncodeResult e = append_packet(t, sequence, report, used);
    if (e.error != Error::ok) {
      EXPECT_EQ(e.error, Error::short_buffer);
      break;
    }
    used += e.bytes;
    ++sequence;
  }
  EXPECT_EQ(sequence, kUsbSlotsMaxReportBytes / 63);
  EXPECT_EQ(report[used], 0x00);  // the padding that ends the report
  PacketWalker walker(report);
  PacketDecoded d;
  std::uint8_t walked = 0;
  while (walker.next(d)) {
    ASSERT_EQ(d.error, Error::ok);
    EXPECT_EQ(d.sequence, walked);
    EXPECT_EQ(std::get<Telemetry>(d.message).first, walked * kMaxTelemetryValues);
    ++walked;
  }
  EXPECT_EQ(walked, sequence);
  EXPECT_FALSE(walker.broken());
}

// A CAN FD frame holds 64 bytes: a longer report (a USB unit's may hold 1024) is refused, never
// copied into the frame.
TEST(ProtocolMalformedPacked, CanFdRefusesAReportLongerThanAFrame) {
  std::vector<std::uint8_t> report(kUsbSlotsMaxReportBytes, 0);
  std::size_t used = 0;
  for (std::uint8_t s = 0; s < 3; ++s) {
    Heartbeat h{s};
    used += append_packet(h, s, report, used).bytes;
  }
  ValveCurrents v;
  v.count = kMaxValveCurrents;  // 63 bytes: the report passes 64
  used += append_packet(v, 3, report, used).bytes;
  ASSERT_GT(used, kPacketMaxBytes);
  CanFrame f;
  EXPECT_EQ(
      encode_canfd_report(std::span<const std::uint8_t>(report).first(used), 5, Direction::host_to_device, f)
          .error,
      Error::too_long);
  EXPECT_EQ(encode_canfd_report(report, 5, Direction::host_to_device, f).error, Error::too_long);
}

TEST(ProtocolMalformedPacked, AppendRefusesWhatDoesNotFitAndLeavesTheReport) {
  std::array<std::uint8_t, kHidReportBytes> report{};
  report.fill(0xCC);
  std::size_t used = 0;
  Telemetry t;
  t.count = 22;  // 7 + 44 payload bytes: a 57-byte packet
  EncodeResult e = append_packet(t, 1, report, used);
  ASSERT_EQ(e.error, Error::ok);
  EXPECT_EQ(e.bytes, 57U);
  EXPECT_EQ(report[57], 0x00);  // terminated
  used += e.bytes;
  const auto before = report;
  e = append_packet(Heartbeat{1}, 2, report, used);  // 8 bytes: 65 > 64
  EXPECT_EQ(e.error, Error::short_buffer);
  EXPECT_EQ(report, before);
  e = append_packet(StateRequest{1}, 2, report, used);  // 7 bytes: exactly 64, no terminator
  ASSERT_EQ(e.error, Error::ok);
  EXPECT_EQ(append_packet(Heartbeat{1}, 3, report, kHidReportBytes + 1).error, Error::short_buffer);
  EXPECT_EQ(append_packet(StateRequest{99}, 3, report, 0).error, Error::out_of_range);
  const Walked w = walk(report);
  ASSERT_EQ(w.errors.size(), 2U);
  EXPECT_EQ(w.messages[1], Message(StateRequest{1}));
}

CanFrame packed_frame(const std::vector<std::uint8_t>& report, Direction d) {
  CanFrame f;
  EXPECT_EQ(encode_canfd_report(report, kNode, d, f).error, Error::ok);
  return f;
}

TEST(ProtocolMalformedPacked, CanFdReportRefusesBadPacketsAndNodes) {
  std::vector<std::uint8_t> middle = packet_bytes(Heartbeat{8}, 2);
  middle.back() ^= 0x01U;
  CanFrame f;
  EXPECT_EQ(encode_canfd_report(report_with_middle(middle), kNode, Direction::host_to_device, f).error,
            Error::bad_crc);
  const std::vector<std::uint8_t> good = report_with_middle(packet_bytes(Heartbeat{8}, 2));
  EXPECT_EQ(encode_canfd_report(good, 0, Direction::host_to_device, f).error, Error::out_of_range);
  EXPECT_EQ(encode_canfd_report({}, kNode, Direction::host_to_device, f).error, Error::short_buffer);
  const CanFrame ok = packed_frame(good, Direction::host_to_device);
  EXPECT_EQ(ok.length, 32U);  // 8 + 8 + 11 = 27 bytes -> FD length 32
}

}  // namespace
