// Golden byte vectors of protocol v1 (tests/protocol/golden_vectors.txt): for every
// message on every framing, the encoder must produce exactly the stored bytes and the
// decoder must give back exactly the message. A second group rebuilds some vectors byte
// by byte from the layout in the headers, with its own CRC code, so the file is not just
// the encoder's output checked against itself. docs/protocol.md must quote every line.
#include <gtest/gtest.h>

#include <array>
#include <fstream>
#include <map>
#include <set>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

#include "mrskin/protocol/can.hpp"
#include "mrskin/protocol/packed_report.hpp"
#include "mrskin/protocol/packet.hpp"
#include "test_support.hpp"

namespace {

using namespace mrskin::protocol;
using namespace mrskin::protocol::test;

const std::vector<GoldenLine>& golden() {
  static const std::vector<GoldenLine> lines = read_golden(MRSKIN_GOLDEN_VECTORS);
  return lines;
}

const GoldenLine* find_line(const std::string& name, const std::string& framing) {
  for (const GoldenLine& g : golden()) {
    if (g.name == name && g.framing == framing) return &g;
  }
  return nullptr;
}

std::vector<CanFrame> frames_of(const GoldenLine& g) {
  std::vector<CanFrame> frames;
  for (const std::string& t : g.tokens) frames.push_back(frame_from_text(t));
  return frames;
}

class ProtocolGolden : public ::testing::TestWithParam<NamedMessage> {};

TEST_P(ProtocolGolden, PacketEncode) {
  const NamedMessage& nm = GetParam();
  const GoldenLine* g = find_line(nm.name, "packet");
  ASSERT_NE(g, nullptr) << "no packet vector for " << nm.name;
  ASSERT_EQ(g->tokens.size(), 1U);
  EXPECT_EQ(hex(packet_bytes(nm.message, kGoldenSequence)), g->tokens[0]);
}

TEST_P(ProtocolGolden, PacketDecode) {
  const NamedMessage& nm = GetParam();
  const GoldenLine* g = find_line(nm.name, "packet");
  ASSERT_NE(g, nullptr);
  const std::vector<std::uint8_t> bytes = unhex(g->tokens[0]);
  const PacketDecoded d = decode_packet(bytes);
  EXPECT_EQ(d.error, Error::ok);
  EXPECT_EQ(d.sequence, kGoldenSequence);
  EXPECT_EQ(d.peer_version, kVersionMajor);
  EXPECT_EQ(d.message, nm.message);
}

TEST_P(ProtocolGolden, HidReportIsPacketPaddedTo64) {
  const NamedMessage& nm = GetParam();
  const GoldenLine* g = find_line(nm.name, "packet");
  ASSERT_NE(g, nullptr);
  std::vector<std::uint8_t> expected = unhex(g->tokens[0]);
  expected.resize(kHidReportBytes, 0x00);
  std::array<std::uint8_t, kHidReportBytes> report;
  report.fill(0xCC);  // the encoder must clear the padding itself
  const EncodeResult r = encode_hid_report(nm.message, kGoldenSequence, report);
  ASSERT_EQ(r.error, Error::ok);
  EXPECT_EQ(r.bytes, unhex(g->tokens[0]).size());
  EXPECT_EQ(hex(report.data(), report.size()), hex(expected));
  // hid_read() hands the 64 bytes to decode_packet, padding included.
  const PacketDecoded d = decode_packet(report);
  EXPECT_EQ(d.error, Error::ok);
  EXPECT_EQ(d.message, nm.message);
}

// encode_packet writes straight into an `out` that holds the largest packet, and through a
// buffer of its own into a shorter one: the golden bytes either way, nothing past them written,
// and an `out` one byte short refused untouched.
TEST_P(ProtocolGolden, PacketEncodesTheSameIntoAnyBufferThatHoldsIt) {
  const NamedMessage& nm = GetParam();
  const GoldenLine* g = find_line(nm.name, "packet");
  ASSERT_NE(g, nullptr);
  const std::vector<std::uint8_t> golden = unhex(g->tokens[0]);
  for (const std::size_t size : {kPacketMaxBytes + 3, kPacketMaxBytes, golden.size(), golden.size() - 1}) {
    std::vector<std::uint8_t> out(size, 0xCC);
    const EncodeResult r = encode_packet(nm.message, kGoldenSequence, out);
    if (size < golden.size()) {
      EXPECT_EQ(r.error, Error::short_buffer);
      EXPECT_EQ(out, std::vector<std::uint8_t>(size, 0xCC)) << "a refused encode writes nothing";
      continue;
    }
    ASSERT_EQ(r.error, Error::ok) << size;
    ASSERT_EQ(r.bytes, golden.size());
    EXPECT_EQ(hex(out.data(), golden.size()), hex(golden)) << size;
    for (std::size_t i = golden.size(); i < size; ++i) {
      ASSERT_EQ(out[i], 0xCC) << "byte " << i << " of " << size;
    }
  }
}

TEST_P(ProtocolGolden, ClassicCanEncode) {
  const NamedMessage& nm = GetParam();
  const GoldenLine* g = find_line(nm.name, "can");
  ASSERT_NE(g, nullptr) << "no classic CAN vector for " << nm.name;
  const std::vector<CanFrame> frames = can_frames(nm.message, kGoldenNode, kGoldenCounter, kGoldenSequence);
  ASSERT_EQ(frames.size(), g->tokens.size());
  for (std::size_t i = 0; i < frames.size(); ++i) {
    EXPECT_EQ(frame_to_text(frames[i]), g->tokens[i]) << "frame " << i;
    EXPECT_EQ(frames[i].length, 8U);
    EXPECT_FALSE(frames[i].fd);
  }
}

TEST_P(ProtocolGolden, ClassicCanDecode) {
  const NamedMessage& nm = GetParam();
  const GoldenLine* g = find_line(nm.name, "can");
  ASSERT_NE(g, nullptr);
  CanDecoder decoder(kGoldenNode);
  BlockMerger merged;
  const std::vector<CanFrame> frames = frames_of(*g);
  for (std::size_t i = 0; i < frames.size(); ++i) {
    const CanDecoded d = decoder.decode(frames[i]);
    ASSERT_EQ(d.error, Error::ok) << "frame " << i;
    if (!d.complete) {
      EXPECT_LT(i + 1, frames.size()) << "segmented transfer never completed";
      continue;
    }
    if (is_segmented_type(nm.message)) {
      EXPECT_EQ(d.sequence, kGoldenSequence);
    } else {
      EXPECT_EQ(d.counter, kGoldenCounter);
    }
    ASSERT_TRUE(merged.add(d.message)) << "frame " << i;
  }
  ASSERT_FALSE(merged.empty());
  Message expected = nm.message;
  if (auto* t = std::get_if<Telemetry>(&expected)) {
    t->device_time_us = 0;  // travels in the TimeSync frame on classic CAN
  }
  EXPECT_EQ(merged.result(), expected);
}

TEST_P(ProtocolGolden, CanFdEncode) {
  const NamedMessage& nm = GetParam();
  const GoldenLine* g = find_line(nm.name, "canfd");
  ASSERT_NE(g, nullptr) << "no CAN FD vector for " << nm.name;
  ASSERT_EQ(g->tokens.size(), 1U);
  CanFrame f;
  ASSERT_EQ(encode_canfd(nm.message, kGoldenNode, direction_of(nm.message), kGoldenSequence, f).error,
            Error::ok);
  EXPECT_EQ(frame_to_text(f), g->tokens[0]);
  EXPECT_TRUE(f.fd);
}

TEST_P(ProtocolGolden, CanFdDecode) {
  const NamedMessage& nm = GetParam();
  const GoldenLine* g = find_line(nm.name, "canfd");
  ASSERT_NE(g, nullptr);
  const CanFrame f = frame_from_text(g->tokens[0]);
  ASSERT_TRUE(f.fd);
  CanDecoder decoder(kGoldenNode);
  const CanDecoded d = decoder.decode(f);
  EXPECT_EQ(d.error, Error::ok);
  EXPECT_TRUE(d.complete);
  EXPECT_EQ(d.sequence, kGoldenSequence);
  EXPECT_EQ(d.message, nm.message);
}

INSTANTIATE_TEST_SUITE_P(Vectors, ProtocolGolden, ::testing::ValuesIn(golden_messages()),
                         [](const ::testing::TestParamInfo<NamedMessage>& param_info) {
                           return param_info.param.name;
                         });

TEST(ProtocolGoldenFile, EveryTypeOnEveryFraming) {
  std::map<std::string, std::set<MessageType>> seen;
  std::map<std::string, MessageType> type_by_name;
  std::set<std::string> report_names;
  for (const NamedMessage& nm : golden_messages()) type_by_name[nm.name] = type_of(nm.message);
  for (const NamedReport& r : golden_reports()) report_names.insert(r.name);
  for (const GoldenLine& g : golden()) {
    if (report_names.count(g.name) != 0) {
      EXPECT_TRUE(g.framing == "report" || g.framing == "canfd") << g.text;
      continue;
    }
    ASSERT_TRUE(type_by_name.count(g.name)) << "vector for unknown message " << g.name;
    seen[g.framing].insert(type_by_name[g.name]);
  }
  EXPECT_EQ(seen.size(), 3U) << "framings: packet, can, canfd";
  for (const char* framing : {"packet", "can", "canfd"}) {
    EXPECT_EQ(seen[framing].size(), std::variant_size_v<Message>) << framing;
  }
}

TEST(ProtocolGoldenFile, FileIsWhatTheGeneratorWrites) {
  // No stale or hand-edited lines: the file holds exactly the generated lines, in order.
  std::vector<std::string> generated;
  for (const NamedMessage& nm : golden_messages()) {
    for (const std::string& line : golden_lines_for(nm)) generated.push_back(line);
  }
  for (const NamedReport& r : golden_reports()) {
    for (const std::string& line : golden_report_lines_for(r)) generated.push_back(line);
  }
  std::vector<std::string> stored;
  for (const GoldenLine& g : golden()) stored.push_back(g.text);
  EXPECT_EQ(stored, generated);
}

TEST(ProtocolGoldenFile, DocQuotesEveryVector) {
  std::ifstream in(MRSKIN_PROTOCOL_DOC);
  ASSERT_TRUE(in) << MRSKIN_PROTOCOL_DOC;
  std::stringstream ss;
  ss << in.rdbuf();
  const std::string doc = ss.str();
  for (const GoldenLine& g : golden()) {
    EXPECT_NE(doc.find(g.text), std::string::npos) << "docs/protocol.md does not quote: " << g.text;
  }
}

// ---- protocol 1.2: packed reports --------------------------------------------------------

class ProtocolGoldenPacked : public ::testing::TestWithParam<NamedReport> {};

TEST_P(ProtocolGoldenPacked, ReportEncode) {
  const NamedReport& r = GetParam();
  const GoldenLine* g = find_line(r.name, "report");
  ASSERT_NE(g, nullptr) << "no report vector for " << r.name;
  ASSERT_EQ(g->tokens.size(), 1U);
  EXPECT_EQ(hex(report_bytes(r, kGoldenSequence)), g->tokens[0]);
}

TEST_P(ProtocolGoldenPacked, HidReportWalksToEveryPacket) {
  const NamedReport& r = GetParam();
  const GoldenLine* g = find_line(r.name, "report");
  ASSERT_NE(g, nullptr);
  std::vector<std::uint8_t> report = unhex(g->tokens[0]);
  const std::size_t used = report.size();
  report.resize(kHidReportBytes, 0x00);  // as hid_read() returns it
  PacketWalker walker(report);
  PacketDecoded d;
  std::size_t i = 0;
  while (walker.next(d)) {
    ASSERT_LT(i, r.messages.size());
    EXPECT_EQ(d.error, Error::ok) << "packet " << i;
    EXPECT_EQ(d.sequence, static_cast<std::uint8_t>(kGoldenSequence + i));
    EXPECT_EQ(d.message, r.messages[i]) << "packet " << i;
    ++i;
  }
  EXPECT_EQ(i, r.messages.size());
  EXPECT_FALSE(walker.broken());
  EXPECT_EQ(walker.offset(), used);
  // A 1.1 receiver reads the first packet and takes the rest for padding.
  const PacketDecoded first = decode_packet(report);
  EXPECT_EQ(first.error, Error::ok);
  EXPECT_EQ(first.message, r.messages.front());
}

TEST_P(ProtocolGoldenPacked, CanFdEncodeAndDecode) {
  const NamedReport& r = GetParam();
  const GoldenLine* g = find_line(r.name, "canfd");
  ASSERT_NE(g, nullptr) << "no CAN FD vector for " << r.name;
  CanFrame f;
  const std::vector<std::uint8_t> bytes = report_bytes(r, kGoldenSequence);
  ASSERT_EQ(encode_canfd_report(bytes, kGoldenNode, r.direction, f).error, Error::ok);
  EXPECT_EQ(frame_to_text(f), g->tokens[0]);
  const CanFrame parsed = frame_from_text(g->tokens[0]);
  CanDecoder decoder(kGoldenNode);
  const CanDecoded d = decoder.decode(parsed);  // the first packet, as a 1.1 decoder sees it
  EXPECT_EQ(d.error, Error::ok);
  EXPECT_EQ(d.message, r.messages.front());
  PacketWalker walker(std::span<const std::uint8_t>(parsed.data.data(), parsed.length));
  PacketDecoded p;
  std::size_t i = 0;
  while (walker.next(p)) {
    ASSERT_LT(i, r.messages.size());
    EXPECT_EQ(p.message, r.messages[i++]);
  }
  EXPECT_EQ(i, r.messages.size());
}

INSTANTIATE_TEST_SUITE_P(Reports, ProtocolGoldenPacked, ::testing::ValuesIn(golden_reports()),
                         [](const ::testing::TestParamInfo<NamedReport>& param_info) {
                           return param_info.param.name;
                         });

// ---- vectors rebuilt by hand from the documented layout -------------------------------

// Written independently of protocol/src/crc.cpp (byte-at-a-time table).
std::uint16_t ref_crc16(const std::vector<std::uint8_t>& d) {
  static const auto table = [] {
    std::array<std::uint16_t, 256> t{};
    for (unsigned i = 0; i < 256; ++i) {
      unsigned c = i << 8U;
      for (int k = 0; k < 8; ++k) c = (c & 0x8000U) ? ((c << 1U) ^ 0x1021U) : (c << 1U);
      t[i] = static_cast<std::uint16_t>(c & 0xFFFFU);
    }
    return t;
  }();
  unsigned crc = 0xFFFF;
  for (const std::uint8_t b : d) crc = ((crc << 8U) ^ table[((crc >> 8U) ^ b) & 0xFFU]) & 0xFFFFU;
  return static_cast<std::uint16_t>(crc);
}
std::uint8_t ref_crc8(const std::vector<std::uint8_t>& d) {
  unsigned crc = 0xFF;
  for (const std::uint8_t b : d) {
    crc ^= b;
    for (int k = 0; k < 8; ++k) crc = (crc & 0x80U) ? (((crc << 1U) ^ 0x1DU) & 0xFFU) : ((crc << 1U) & 0xFFU);
  }
  return static_cast<std::uint8_t>(crc ^ 0xFFU);
}
std::vector<std::uint8_t> with_crc16(std::vector<std::uint8_t> p) {
  const std::uint16_t c = ref_crc16(p);
  p.push_back(static_cast<std::uint8_t>(c & 0xFFU));  // little-endian
  p.push_back(static_cast<std::uint8_t>(c >> 8U));
  return p;
}
std::string classic(unsigned fn, unsigned block, unsigned node, std::vector<std::uint8_t> data7) {
  const unsigned id = (fn << 8U) | (block << 4U) | node;
  std::vector<std::uint8_t> crc_in{static_cast<std::uint8_t>(id >> 8U),
                                   static_cast<std::uint8_t>(id & 0xFFU)};
  crc_in.insert(crc_in.end(), data7.begin(), data7.end());
  data7.push_back(ref_crc8(crc_in));
  std::ostringstream os;
  os << std::hex << std::uppercase << ((id >> 8U) & 0xFU) << ((id >> 4U) & 0xFU) << (id & 0xFU) << '#'
     << hex(data7);
  return os.str();
}
// Four 12-bit values little-endian into 6 bytes: v0 bits 0-11, v1 bits 12-23, ...
std::vector<std::uint8_t> pack12(std::array<unsigned, 4> v) {
  return {static_cast<std::uint8_t>(v[0] & 0xFF),
          static_cast<std::uint8_t>((v[0] >> 8) | ((v[1] & 0xF) << 4)),
          static_cast<std::uint8_t>(v[1] >> 4),
          static_cast<std::uint8_t>(v[2] & 0xFF),
          static_cast<std::uint8_t>((v[2] >> 8) | ((v[3] & 0xF) << 4)),
          static_cast<std::uint8_t>(v[3] >> 4)};
}

TEST(ProtocolGoldenByHand, HeartbeatPacket) {
  // version 1, type 0x31, sequence 0x2A, length 2, counter 0xBEEF little-endian, CRC LE.
  const auto p = with_crc16({0x01, 0x31, 0x2A, 0x02, 0xEF, 0xBE});
  EXPECT_EQ(find_line("heartbeat", "packet")->tokens[0], hex(p));
}

TEST(ProtocolGoldenByHand, TelemetryPacket) {
  // u32 time, u16 first, u8 count, then 12 x i16 (two's complement, LE).
  std::vector<std::uint8_t> p{0x01, 0x20, 0x2A, 7 + 24, 0x78, 0x56, 0x34, 0x12, 0x00, 0x00, 12};
  for (const int v : {0, 1, -1, 2047, -2048, 400, -400, 0x123, -0x123, 1000, 2000, -7}) {
    const auto u = static_cast<std::uint16_t>(v);
    p.push_back(static_cast<std::uint8_t>(u & 0xFF));
    p.push_back(static_cast<std::uint8_t>(u >> 8));
  }
  EXPECT_EQ(find_line("telemetry", "packet")->tokens[0], hex(with_crc16(p)));
}

TEST(ProtocolGoldenByHand, ValveBlocksOnClassicCan) {
  // function 1, block b, node 5; 12-bit packing; byte 6 = counter 9 << 4 | value count.
  const GoldenLine* g = find_line("valve_currents", "can");
  ASSERT_EQ(g->tokens.size(), 3U);
  auto data = [](std::array<unsigned, 4> v, unsigned n) {
    auto d = pack12(v);
    d.push_back(static_cast<std::uint8_t>((9U << 4U) | n));
    return d;
  };
  EXPECT_EQ(g->tokens[0], classic(1, 0, 5, data({0, 1, 2047, 4095}, 4)));
  EXPECT_EQ(g->tokens[1], classic(1, 1, 5, data({0x123, 0xABC, 800, 1600}, 4)));
  EXPECT_EQ(g->tokens[2], classic(1, 2, 5, data({2400, 3200, 4000, 17}, 4)));
  // Partial block: valves 4..8 are block 1 (4 values) and block 2 (1 value, rest zero).
  const GoldenLine* pg = find_line("valve_currents_partial", "can");
  ASSERT_EQ(pg->tokens.size(), 2U);
  EXPECT_EQ(pg->tokens[0], classic(1, 1, 5, data({0x321, 0x654, 0x987, 0xCBA}, 4)));
  EXPECT_EQ(pg->tokens[1], classic(1, 2, 5, data({0xFED, 0, 0, 0}, 1)));
  // Spot check of the raw text: 0x321, 0x654 -> 21 43 65.
  EXPECT_EQ(pg->tokens[0].substr(0, 10), "115#214365");
}

// Protocol 1.2's delta blocks on classic CAN, worked by hand over three blocks (valves 0..11).
TEST(ProtocolGoldenByHand, DeltaBlocksGoWhenChangedAndEveryTenUpdates) {
  CanDeltaBlocks delta(/*repeat_refreshes=*/true);  // the host's valve blocks
  std::array<std::uint16_t, CanDeltaBlocks::kValues> v{};
  std::fill(v.begin(), v.begin() + 12, 100);
  EXPECT_EQ(delta.select(v, 0, 3), 0b111U);  // never sent: all
  // Only block 1 (valves 4..7) changes from here on: block 0 and 2 go again at update 11, after
  // 9 updates unsent, so a frame lost at update 1 heals 10 updates later.
  for (int update = 2; update <= 10; ++update) {
    v[5] = static_cast<std::uint16_t>(100 + update);
    EXPECT_EQ(delta.select(v, 0, 3), 0b010U) << update;
  }
  v[5] = 111;
  EXPECT_EQ(delta.select(v, 0, 3), 0b111U);
  v[5] = 112;
  v[11] = 7;  // block 2's last value
  EXPECT_EQ(delta.select(v, 0, 3), 0b110U);
  EXPECT_EQ(delta.select(v, 0, 3), 0b111U);  // the same values again: a refresh, whole
  v[0] = 1;
  EXPECT_EQ(delta.select(v, 0, 1), 0b001U);  // an update of block 0 alone (a packet's range)
  delta.reset();
  v[0] = 2;
  EXPECT_EQ(delta.select(v, 0, 3), 0b111U);  // a new link: all
  EXPECT_EQ(delta.select(v, 3, 3), 0U);      // empty or impossible ranges: nothing
  EXPECT_EQ(delta.select(v, 15, 17), 0U);
  // The unit's sensor blocks: a quiet sample sends only what is due.
  CanDeltaBlocks sensors(/*repeat_refreshes=*/false);
  EXPECT_EQ(sensors.select(v, 0, 3), 0b111U);
  for (int update = 2; update <= 10; ++update) {
    EXPECT_EQ(sensors.select(v, 0, 3), 0U) << update;
  }
  EXPECT_EQ(sensors.select(v, 0, 3), 0b111U);  // each block 10 updates after it last went
  EXPECT_TRUE(reads_delta_blocks(1, 2));
  EXPECT_FALSE(reads_delta_blocks(1, 1));
  EXPECT_FALSE(reads_delta_blocks(2, 2));
}

TEST(ProtocolGoldenByHand, SensorBlocksOnClassicCan) {
  const GoldenLine* g = find_line("telemetry", "can");
  ASSERT_EQ(g->tokens.size(), 3U);
  auto data = [](std::array<int, 4> v) {
    std::array<unsigned, 4> u{};
    for (std::size_t i = 0; i < 4; ++i)
      u[i] = static_cast<unsigned>(v[i]) & 0xFFFU;  // 12-bit two's complement
    auto d = pack12(u);
    d.push_back(0x94);
    return d;
  };
  EXPECT_EQ(g->tokens[0], classic(2, 0, 5, data({0, 1, -1, 2047})));
  EXPECT_EQ(g->tokens[1], classic(2, 1, 5, data({-2048, 400, -400, 0x123})));
  EXPECT_EQ(g->tokens[2], classic(2, 2, 5, data({-0x123, 1000, 2000, -7})));
}

TEST(ProtocolGoldenByHand, CellTargetsOnClassicCan) {
  // function 3, block = cell & 0xF, bits: stiffness 0-13, offset 14-25, ceiling 26-37,
  // validity 38-43, cell >> 4 in 44-47.
  auto pack = [](std::uint64_t k, std::uint64_t x, std::uint64_t f, std::uint64_t v, std::uint64_t hi) {
    const std::uint64_t bits = k | (x << 14U) | (f << 26U) | (v << 38U) | (hi << 44U);
    std::vector<std::uint8_t> d;
    for (unsigned i = 0; i < 6; ++i) d.push_back(static_cast<std::uint8_t>((bits >> (8U * i)) & 0xFFU));
    d.push_back(0x90);  // counter 9, low nibble 0
    return d;
  };
  const GoldenLine* g = find_line("cell_targets", "can");
  ASSERT_EQ(g->tokens.size(), 2U);
  EXPECT_EQ(g->tokens[0], classic(3, 18 & 0xF, 5, pack(150, 1000, 1500, 10, 18 >> 4)));
  EXPECT_EQ(g->tokens[1], classic(3, 19 & 0xF, 5, pack(16383, 4095, 4095, 63, 19 >> 4)));
}

TEST(ProtocolGoldenByHand, ManagementFramesOnClassicCan) {
  EXPECT_EQ(find_line("heartbeat", "can")->tokens[0], classic(0, 0, 5, {0xEF, 0xBE, 0, 0, 0, 0, 0x90}));
  EXPECT_EQ(find_line("status", "can")->tokens[0], classic(0, 1, 5, {3, 2, 0x34, 0x12, 0x05, 0, 0x90}));
  EXPECT_EQ(find_line("time_sync", "can")->tokens[0], classic(0, 2, 5, {0x78, 0x56, 0x34, 0x12, 0, 0, 0x90}));
  EXPECT_EQ(find_line("state_request", "can")->tokens[0], classic(0, 3, 5, {1, 0, 0, 0, 0, 0, 0x90}));
  // Spot check of the raw text.
  EXPECT_EQ(find_line("heartbeat", "can")->tokens[0].substr(0, 18), "005#EFBE0000000090");
}

TEST(ProtocolGoldenByHand, SegmentedConfigWrite) {
  // ConfigWrite packet: 7 + 5 payload bytes -> 18-byte packet. ISO-TP style on id 0x045
  // (management, block 4 = segmented host->device, node 5): first frame 10 12 + 6 bytes,
  // consecutive frames 21, 22 with 7 bytes each, zero padded.
  const auto p =
      with_crc16({0x01, 0x42, 0x2A, 12, 0x01, 0x00, 0x00, 0x00, 0x05, 0x00, 5, 'm', 'r', 's', 'k', 'n'});
  ASSERT_EQ(p.size(), 18U);
  EXPECT_EQ(find_line("config_write", "packet")->tokens[0], hex(p));
  const GoldenLine* g = find_line("config_write", "can");
  ASSERT_EQ(g->tokens.size(), 3U);
  std::vector<std::uint8_t> f0{0x10, 18}, f1{0x21}, f2{0x22};
  f0.insert(f0.end(), p.begin(), p.begin() + 6);
  f1.insert(f1.end(), p.begin() + 6, p.begin() + 13);
  f2.insert(f2.end(), p.begin() + 13, p.end());
  f2.resize(8, 0);
  EXPECT_EQ(g->tokens[0], "045#" + hex(f0));
  EXPECT_EQ(g->tokens[1], "045#" + hex(f1));
  EXPECT_EQ(g->tokens[2], "045#" + hex(f2));
  // Identity goes device->host: block 5.
  EXPECT_EQ(find_line("identity", "can")->tokens[0].substr(0, 4), "055#");
}

TEST(ProtocolGoldenByHand, SensorDeadbandPacketInOneSegmentedFrame) {
  // 1.2: type 0x04, one payload byte, the deadband in counts (2). Device->host, segmented on
  // classic CAN (block 5): a 7-byte packet fits one single frame (ISO-TP style: 0L + L bytes).
  const auto p = with_crc16({0x01, 0x04, 0x2A, 0x01, 0x02});
  ASSERT_EQ(p.size(), 7U);
  EXPECT_EQ(find_line("sensor_deadband", "packet")->tokens[0], hex(p));
  const GoldenLine* g = find_line("sensor_deadband", "can");
  ASSERT_EQ(g->tokens.size(), 1U);
  std::vector<std::uint8_t> f0{0x07};
  f0.insert(f0.end(), p.begin(), p.end());
  EXPECT_EQ(g->tokens[0], "055#" + hex(f0));
}

TEST(ProtocolGoldenByHand, CanFdCarriesThePacket) {
  // Valve currents host->device: function 4, block 0, node 5 = 0x405; 33-byte packet
  // padded to the FD length 48. Telemetry device->host: 0x505, 37 bytes -> 48.
  const std::string packet = find_line("valve_currents", "packet")->tokens[0];
  ASSERT_EQ(packet.size(), 2U * 33U);
  EXPECT_EQ(find_line("valve_currents", "canfd")->tokens[0], "405##0" + packet + std::string(2 * 15, '0'));
  const std::string tele = find_line("telemetry", "packet")->tokens[0];
  ASSERT_EQ(tele.size(), 2U * 37U);
  EXPECT_EQ(find_line("telemetry", "canfd")->tokens[0], "505##0" + tele + std::string(2 * 11, '0'));
  // Heartbeat: 8-byte packet, FD length 8, no padding.
  EXPECT_EQ(find_line("heartbeat", "canfd")->tokens[0],
            "405##0" + find_line("heartbeat", "packet")->tokens[0]);
}

TEST(ProtocolGoldenByHand, PackedReportsAreTheirPacketsBackToBack) {
  // Each packet whole, with its own header and CRC; sequences 0x2A, 0x2B, 0x2C.
  const std::string status = find_line("status", "packet")->tokens[0];  // sequence 0x2A
  const auto echo = with_crc16({0x01, 0x31, 0x2B, 0x02, 0xEF, 0xBE});
  std::vector<std::uint8_t> tele = unhex(find_line("telemetry", "packet")->tokens[0]);
  tele[2] = 0x2C;
  tele.resize(tele.size() - 2);
  EXPECT_EQ(find_line("packed_device_report", "report")->tokens[0],
            status + hex(echo) + hex(with_crc16(tele)));
  // 11 + 8 + 37 = 56 bytes: CAN FD length 64, 8 zero bytes after the last packet.
  EXPECT_EQ(find_line("packed_device_report", "canfd")->tokens[0],
            "505##0" + status + hex(echo) + hex(with_crc16(tele)) + std::string(2 * 8, '0'));
  const std::string heartbeat = find_line("heartbeat", "packet")->tokens[0];  // sequence 0x2A
  std::vector<std::uint8_t> currents = unhex(find_line("valve_currents", "packet")->tokens[0]);
  currents[2] = 0x2B;
  currents.resize(currents.size() - 2);
  EXPECT_EQ(find_line("packed_host_report", "report")->tokens[0], heartbeat + hex(with_crc16(currents)));
  // 8 + 33 = 41 bytes: CAN FD length 48.
  EXPECT_EQ(find_line("packed_host_report", "canfd")->tokens[0],
            "405##0" + heartbeat + hex(with_crc16(currents)) + std::string(2 * 7, '0'));
}

TEST(ProtocolGoldenByHand, ReferenceCrcsMatchCheckValues) {
  const std::vector<std::uint8_t> check{'1', '2', '3', '4', '5', '6', '7', '8', '9'};
  EXPECT_EQ(ref_crc16(check), 0x29B1);
  EXPECT_EQ(ref_crc8(check), 0x4B);
}

}  // namespace
