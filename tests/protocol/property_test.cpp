// Round-trip and robustness properties of protocol v1 (rapidcheck).
//
// The seed is fixed so that runs repeat; RC_PARAMS in the environment overrides it, e.g.
//   RC_PARAMS="seed=42 max_success=5000" build/release/tests/protocol/mrskin_protocol_property_test
#include <gtest/gtest.h>
#include <rapidcheck/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <limits>
#include <vector>

#include "fuzz_entry.hpp"
#include "mrskin/protocol/can.hpp"
#include "mrskin/protocol/packed_report.hpp"
#include "mrskin/protocol/packet.hpp"
#include "mrskin/protocol/units.hpp"
#include "test_support.hpp"

namespace {

using namespace mrskin::protocol;
using namespace mrskin::protocol::test;

// Runs before main(), so before rapidcheck reads its configuration; keeps a user's RC_PARAMS.
const bool kSeedSet = [] {
  setenv("RC_PARAMS", "seed=20240601 max_success=500", 0);
  return true;
}();

// ---- generators --------------------------------------------------------------------

// Fails the property with the broken invariant and the input that broke it.
void expect_ok(const char* failure, const std::vector<std::uint8_t>& input) {
  if (failure != nullptr) {
    RC_FAIL(std::string(failure) + " on input " + hex(input));
  }
}

template <class T>
T in(long lo, long hi) {  // inclusive
  return static_cast<T>(*rc::gen::inRange<long>(lo, hi + 1));
}
template <class T>
T any() {
  return *rc::gen::arbitrary<T>();
}

// Where a message must fit: any packet, or the classic CAN frame layout (blocks of 4 from
// a multiple of 4 within 16 blocks, 256 cell addresses, telemetry time in TimeSync).
enum class Fit { packet, classic_can };

Identity gen_identity() {
  Identity m;
  m.proto_major = any<std::uint8_t>();
  m.proto_minor = any<std::uint8_t>();
  m.fw_major = any<std::uint8_t>();
  m.fw_minor = any<std::uint8_t>();
  m.fw_patch = any<std::uint8_t>();
  m.rows = any<std::uint8_t>();
  m.cols = any<std::uint8_t>();
  m.fluid_cells = any<std::uint16_t>();
  m.valves = any<std::uint16_t>();
  m.sensors = any<std::uint16_t>();
  m.serial = any<std::uint32_t>();
  m.current_lsb_nA = in<std::uint32_t>(1, 0xFFFFFFFFL);
  m.current_max_counts = in<std::uint16_t>(0, kCurrentCountMax);
  m.sensor_quantity = in<std::uint8_t>(0, 2);
  m.sensor_lsb_nano = in<std::uint32_t>(1, 0xFFFFFFFFL);
  m.heartbeat_timeout_ms = any<std::uint16_t>();
  m.telemetry_rate_hz = any<std::uint16_t>();
  return m;
}

// first and count of a run of values: anywhere for packets, whole blocks for classic CAN.
std::pair<std::uint16_t, std::uint8_t> gen_run(std::size_t max_count, Fit fit) {
  if (fit == Fit::classic_can) {
    const auto block = in<std::size_t>(0, kCanMaxBlocks - 1);
    const std::size_t room = (kCanMaxBlocks - block) * kCanValuesPerBlock;
    const auto count = in<std::uint8_t>(1, static_cast<long>(std::min(max_count, room)));
    return {static_cast<std::uint16_t>(block * kCanValuesPerBlock), count};
  }
  const auto count = in<std::uint8_t>(1, static_cast<long>(max_count));
  return {in<std::uint16_t>(0, 0xFFFF - count), count};
}

ValveCurrents gen_valves(Fit fit) {
  ValveCurrents m;
  std::tie(m.first, m.count) = gen_run(kMaxValveCurrents, fit);
  for (std::size_t i = 0; i < m.count; ++i) m.counts[i] = in<std::uint16_t>(0, kCurrentCountMax);
  return m;
}

Telemetry gen_telemetry(Fit fit) {
  Telemetry m;
  m.device_time_us = fit == Fit::classic_can ? 0 : any<std::uint32_t>();
  std::tie(m.first, m.count) = gen_run(kMaxTelemetryValues, fit);
  for (std::size_t i = 0; i < m.count; ++i) m.counts[i] = in<std::int16_t>(kSensorCountMin, kSensorCountMax);
  return m;
}

CellTargets gen_cells(Fit fit) {
  CellTargets m;
  m.count = in<std::uint8_t>(1, kMaxCellTargets);
  const long last_first = (fit == Fit::classic_can ? kCellIndexMaxCan + 1 : 0xFFFF) - m.count;
  m.first = in<std::uint16_t>(0, last_first);
  for (std::size_t i = 0; i < m.count; ++i) {
    m.targets[i] = CellTarget{in<std::uint16_t>(0, kStiffnessCountMax), in<std::uint16_t>(0, kOffsetCountMax),
                              in<std::uint16_t>(0, kCeilingCountMax), in<std::uint8_t>(0, kValidityCountMax)};
  }
  return m;
}

template <class Chunk>
Chunk gen_chunk() {
  Chunk m;
  m.key = any<std::uint16_t>();
  m.total = any<std::uint16_t>();
  m.length = in<std::uint8_t>(0, std::min<long>(static_cast<long>(kMaxConfigBytes), m.total));
  m.offset = in<std::uint16_t>(0, m.total - m.length);
  for (std::size_t i = 0; i < m.length; ++i) m.bytes[i] = any<std::uint8_t>();
  return m;
}

Message gen_message(Fit fit) {
  switch (in<int>(0, 14)) {
    case 0:
      return IdentifyRequest{any<std::uint8_t>(), any<std::uint8_t>()};
    case 1:
      return gen_identity();
    case 2:
      return gen_valves(fit);
    case 3:
      return gen_cells(fit);
    case 4:
      return gen_telemetry(fit);
    case 5:
      return TimeSync{any<std::uint32_t>()};
    case 6:
      return Status{in<std::uint8_t>(0, 3), in<std::uint8_t>(0, 7), any<std::uint16_t>(),
                    any<std::uint8_t>()};
    case 7:
      return Heartbeat{any<std::uint16_t>()};
    case 8:
      return StateRequest{in<std::uint8_t>(0, 3)};
    case 9:
      return ConfigRead{any<std::uint16_t>(), any<std::uint16_t>(), in<std::uint8_t>(1, kMaxConfigBytes)};
    case 10:
      return gen_chunk<ConfigData>();
    case 11:
      return gen_chunk<ConfigWrite>();
    case 12:
      return ConfigAck{any<std::uint16_t>(), any<std::uint16_t>(), in<std::uint8_t>(0, 4)};
    case 13:
      return SensorDeadband{in<std::uint8_t>(0, kSensorDeadbandMaxCounts)};
    default: {
      static constexpr std::uint16_t kIntervals_us[] = {125, 250, 500, 1000};
      return UsbSlots{in<std::uint16_t>(kUsbSlotsMinReportBytes, kUsbSlotsMaxReportBytes),
                      in<std::uint8_t>(1, kUsbSlotsMaxReportsPerInterval),
                      kIntervals_us[in<std::size_t>(0, 3)]};
    }
  }
}

std::vector<std::uint8_t> gen_bytes(std::size_t max_size) {
  const auto n = in<std::size_t>(0, static_cast<long>(max_size));
  std::vector<std::uint8_t> v(n);
  for (auto& b : v) b = any<std::uint8_t>();
  return v;
}

// Flips a few random bits of a valid encoding.
void mutate(std::vector<std::uint8_t>& bytes) {
  if (bytes.empty()) return;
  const int flips = in<int>(1, 3);
  for (int i = 0; i < flips; ++i) {
    const auto pos = in<std::size_t>(0, static_cast<long>(bytes.size() - 1));
    bytes[pos] = static_cast<std::uint8_t>(bytes[pos] ^ (1U << in<unsigned>(0, 7)));
  }
}

// Decodes frames with one decoder; returns the messages completed, merged per message.
std::vector<Message> decode_all(CanDecoder& decoder, const std::vector<std::vector<CanFrame>>& per_message,
                                std::uint8_t counter, std::uint8_t sequence) {
  std::vector<Message> out;
  for (const auto& frames : per_message) {
    BlockMerger merged;
    for (const CanFrame& f : frames) {
      const CanDecoded d = decoder.decode(f);
      RC_ASSERT(d.error == Error::ok);
      if (!d.complete) continue;
      if (std::holds_alternative<ValveCurrents>(d.message) || std::holds_alternative<Telemetry>(d.message) ||
          std::holds_alternative<CellTargets>(d.message) || std::holds_alternative<Heartbeat>(d.message) ||
          std::holds_alternative<Status>(d.message) || std::holds_alternative<TimeSync>(d.message) ||
          std::holds_alternative<StateRequest>(d.message)) {
        RC_ASSERT(d.counter == (counter & 0xFU));
      }
      if (is_segmented_type(d.message)) {
        RC_ASSERT(d.sequence == sequence);
      }
      RC_ASSERT(merged.add(d.message));
    }
    RC_ASSERT(!merged.empty());
    out.push_back(merged.result());
  }
  return out;
}

// ---- round trips ---------------------------------------------------------------------

TEST(ProtocolProperty, SeedIsFixed) {
  ASSERT_TRUE(kSeedSet);
  ASSERT_NE(std::getenv("RC_PARAMS"), nullptr);
}

RC_GTEST_PROP(ProtocolProperty, PacketAndHidRoundTrip, ()) {
  const Message m = gen_message(Fit::packet);
  const auto sequence = any<std::uint8_t>();
  std::array<std::uint8_t, kPacketMaxBytes> buf{};
  const EncodeResult e = encode_packet(m, sequence, buf);
  RC_ASSERT(e.error == Error::ok);
  RC_ASSERT(e.bytes == kPacketHeaderBytes + packet_payload_length(m) + kPacketCrcBytes);
  const PacketDecoded d = decode_packet({buf.data(), e.bytes});
  RC_ASSERT(d.error == Error::ok);
  RC_ASSERT(d.sequence == sequence);
  RC_ASSERT(d.message == m);

  std::array<std::uint8_t, kHidReportBytes> report{};
  report.fill(0xA5);
  RC_ASSERT(encode_hid_report(m, sequence, report).error == Error::ok);
  RC_ASSERT(std::equal(buf.begin(), buf.begin() + static_cast<std::ptrdiff_t>(e.bytes), report.begin()));
  RC_ASSERT(std::all_of(report.begin() + static_cast<std::ptrdiff_t>(e.bytes), report.end(),
                        [](std::uint8_t b) { return b == 0; }));
  const PacketDecoded dr = decode_packet(report);
  RC_ASSERT(dr.error == Error::ok);
  RC_ASSERT(dr.message == m);
}

RC_GTEST_PROP(ProtocolProperty, ClassicCanRoundTrip, ()) {
  const Message m = gen_message(Fit::classic_can);
  const auto node = in<std::uint8_t>(kCanNodeMin, kCanNodeMax);
  const auto counter = in<std::uint8_t>(0, 15);
  const auto sequence = any<std::uint8_t>();
  const std::vector<CanFrame> frames = can_frames(m, node, counter, sequence);
  for (const CanFrame& f : frames) {
    RC_ASSERT(f.length == 8U);
    RC_ASSERT(!f.fd);
    RC_ASSERT((f.id & 0xFU) == node);
    RC_ASSERT(f.id <= 0x7FFU);
  }
  RC_ASSERT(frames.size() <= kCanMaxFramesPerMessage);
  CanDecoder decoder(node);
  const auto decoded = decode_all(decoder, {frames}, counter, sequence);
  RC_ASSERT(decoded.size() == 1U);
  RC_ASSERT(decoded[0] == m);
}

RC_GTEST_PROP(ProtocolProperty, ClassicCanStreamWithOtherNodes, ()) {
  // Several messages in a row, each followed by frames for another node; segmented
  // transfers of both directions overlap.
  const auto node = in<std::uint8_t>(kCanNodeMin, kCanNodeMax);
  const auto other = static_cast<std::uint8_t>(node % kCanNodeMax + 1);
  const auto counter = in<std::uint8_t>(0, 15);
  const auto sequence = any<std::uint8_t>();
  const int n = in<int>(1, 6);
  std::vector<Message> sent;
  std::vector<std::vector<CanFrame>> per_message;
  for (int i = 0; i < n; ++i) {
    sent.push_back(gen_message(Fit::classic_can));
    per_message.push_back(can_frames(sent.back(), node, counter, sequence));
  }
  CanDecoder decoder(node);
  std::vector<Message> received;
  // Interleave: frame k of every message in turn (a segmented host->device transfer and a
  // device->host one may run at once; two of one direction may not, so those go whole).
  std::vector<CanFrame> wire;
  std::vector<std::size_t> owner;
  bool seg_busy[2] = {false, false};
  std::vector<std::size_t> done(per_message.size(), 0);
  for (bool progress = true; progress;) {
    progress = false;
    for (std::size_t i = 0; i < per_message.size(); ++i) {
      if (done[i] == per_message[i].size()) continue;
      const bool seg = is_segmented_type(sent[i]);
      const int dir = direction_of(sent[i]) == Direction::host_to_device ? 0 : 1;
      if (seg && done[i] == 0) {
        if (seg_busy[dir]) continue;
        seg_busy[dir] = true;
      }
      wire.push_back(per_message[i][done[i]++]);
      owner.push_back(i);
      if (seg && done[i] == per_message[i].size()) seg_busy[dir] = false;
      const auto noise = can_frames(Heartbeat{any<std::uint16_t>()}, other, counter, 0);
      wire.push_back(noise[0]);
      owner.push_back(per_message.size());
      progress = true;
    }
  }
  std::vector<BlockMerger> merged(per_message.size());
  for (std::size_t k = 0; k < wire.size(); ++k) {
    const CanDecoded d = decoder.decode(wire[k]);
    if (owner[k] == per_message.size()) {
      RC_ASSERT(d.error == Error::wrong_node);
      continue;
    }
    RC_ASSERT(d.error == Error::ok);
    if (d.complete) RC_ASSERT(merged[owner[k]].add(d.message));
  }
  for (std::size_t i = 0; i < sent.size(); ++i) {
    RC_ASSERT(!merged[i].empty());
    RC_ASSERT(merged[i].result() == sent[i]);
  }
}

RC_GTEST_PROP(ProtocolProperty, CanFdRoundTrip, ()) {
  const Message m = gen_message(Fit::packet);
  const auto node = in<std::uint8_t>(kCanNodeMin, kCanNodeMax);
  const auto sequence = any<std::uint8_t>();
  const Direction dir = direction_of(m);
  CanFrame f;
  RC_ASSERT(encode_canfd(m, node, dir, sequence, f).error == Error::ok);
  RC_ASSERT(f.fd);
  RC_ASSERT(f.length == canfd_padded_length(kPacketHeaderBytes + packet_payload_length(m) + kPacketCrcBytes));
  RC_ASSERT(f.id == can_id(dir == Direction::host_to_device ? CanFunction::fd_host_to_device
                                                            : CanFunction::fd_device_to_host,
                           0, node));
  CanDecoder decoder(node);
  const CanDecoded d = decoder.decode(f);
  RC_ASSERT(d.error == Error::ok);
  RC_ASSERT(d.complete);
  RC_ASSERT(d.sequence == sequence);
  RC_ASSERT(d.message == m);
}

// ---- protocol 1.2: packed reports ----------------------------------------------------

// Packs the messages into as few 64-byte reports as append_packet allows, in order; sequences
// from sequence. Returns the reports' used bytes.
std::vector<std::vector<std::uint8_t>> pack_reports(const std::vector<Message>& messages,
                                                    std::uint8_t sequence) {
  std::vector<std::vector<std::uint8_t>> reports;
  std::array<std::uint8_t, kHidReportBytes> report{};
  std::size_t used = 0;
  for (std::size_t i = 0; i < messages.size(); ++i) {
    const auto seq = static_cast<std::uint8_t>(sequence + i);
    EncodeResult e = append_packet(messages[i], seq, report, used);
    if (e.error == Error::short_buffer) {
      RC_ASSERT(used > 0);  // only a report with packets already in it is full
      reports.emplace_back(report.begin(), report.begin() + static_cast<std::ptrdiff_t>(used));
      used = 0;
      e = append_packet(messages[i], seq, report, used);
    }
    RC_ASSERT(e.error == Error::ok);
    used += e.bytes;
  }
  if (used > 0) reports.emplace_back(report.begin(), report.begin() + static_cast<std::ptrdiff_t>(used));
  return reports;
}

RC_GTEST_PROP(ProtocolProperty, PackedReportsRoundTrip, ()) {
  // Any run of valid packets packed then walked gives back the same packets, in order, with
  // their sequences; with the HID report's zero padding or without it.
  const int n = in<int>(1, 12);
  std::vector<Message> sent;
  for (int i = 0; i < n; ++i) sent.push_back(gen_message(Fit::packet));
  const auto sequence = any<std::uint8_t>();
  const bool padded = *rc::gen::arbitrary<bool>();
  std::size_t k = 0;
  for (std::vector<std::uint8_t> report : pack_reports(sent, sequence)) {
    RC_ASSERT(report.size() <= kHidReportBytes);
    if (padded) report.resize(kHidReportBytes, 0x00);
    PacketWalker walker(report);
    PacketDecoded d;
    std::size_t in_report = 0;
    while (walker.next(d)) {
      RC_ASSERT(d.error == Error::ok);
      RC_ASSERT(k < sent.size());
      RC_ASSERT(d.sequence == static_cast<std::uint8_t>(sequence + k));
      RC_ASSERT(d.message == sent[k]);
      ++k;
      ++in_report;
    }
    RC_ASSERT(in_report > 0U);
    RC_ASSERT(!walker.broken());
  }
  RC_ASSERT(k == sent.size());
}

RC_GTEST_PROP(ProtocolProperty, PackedReportOnCanFdRoundTrip, ()) {
  const int n = in<int>(1, 8);
  std::vector<Message> sent;
  for (int i = 0; i < n; ++i) sent.push_back(gen_message(Fit::packet));
  const std::vector<std::uint8_t> report = pack_reports(sent, 0).front();
  const auto node = in<std::uint8_t>(kCanNodeMin, kCanNodeMax);
  CanFrame f;
  RC_ASSERT(encode_canfd_report(report, node, Direction::device_to_host, f).error == Error::ok);
  RC_ASSERT(f.length == canfd_padded_length(report.size()));
  RC_ASSERT(std::equal(report.begin(), report.end(), f.data.begin()));
  PacketWalker walker(std::span<const std::uint8_t>(f.data.data(), f.length));
  PacketDecoded d;
  std::size_t k = 0;
  while (walker.next(d)) {
    RC_ASSERT(d.error == Error::ok);
    RC_ASSERT(d.message == sent[k++]);
  }
  RC_ASSERT(k >= 1U);
  RC_ASSERT(walker.offset() == report.size());
}

RC_GTEST_PROP(ProtocolProperty, TruncatedPackedReportGivesItsWholePacketsThenAnError, ()) {
  const int n = in<int>(2, 8);
  std::vector<Message> sent;
  for (int i = 0; i < n; ++i) sent.push_back(gen_message(Fit::packet));
  const std::vector<std::uint8_t> report = pack_reports(sent, 0).front();
  const auto cut = in<std::size_t>(0, static_cast<long>(report.size()));
  const std::vector<std::uint8_t> truncated(report.begin(),
                                            report.begin() + static_cast<std::ptrdiff_t>(cut));
  // Where each packet of the full report ends.
  std::vector<std::size_t> ends;
  PacketWalker full(report);
  PacketDecoded d;
  while (full.next(d)) ends.push_back(full.offset());
  PacketWalker walker(truncated);
  std::size_t k = 0;
  bool error = false;
  while (walker.next(d)) {
    if (d.error != Error::ok) {
      RC_ASSERT(d.error == Error::short_buffer);
      RC_ASSERT(!error);
      error = true;
      continue;
    }
    RC_ASSERT(!error);
    RC_ASSERT(ends[k] <= cut);
    RC_ASSERT(d.message == sent[k]);
    ++k;
  }
  // Every packet that ends inside the cut is delivered; a cut inside a packet is one error.
  const auto whole = static_cast<std::size_t>(
      std::count_if(ends.begin(), ends.end(), [cut](std::size_t e) { return e <= cut; }));
  RC_ASSERT(k == whole);
  RC_ASSERT(error == (std::find(ends.begin(), ends.end(), cut) == ends.end() && cut > 0));
}

RC_GTEST_PROP(ProtocolProperty, CorruptedPackedReportsIntoTheWalker, ()) {
  const int n = in<int>(1, 8);
  std::vector<Message> sent;
  for (int i = 0; i < n; ++i) sent.push_back(gen_message(Fit::packet));
  std::vector<std::uint8_t> original = pack_reports(sent, any<std::uint8_t>()).front();
  original.resize(in<std::size_t>(original.size(), kHidReportBytes), 0);
  std::vector<std::uint8_t> report = original;
  mutate(report);
  expect_ok(mrskin::fuzz::check_packed_report(report), report);
  // The packets that end before the first changed byte still come out whole, in order.
  const auto first_change = static_cast<std::size_t>(
      std::mismatch(original.begin(), original.end(), report.begin()).first - original.begin());
  std::vector<std::size_t> ends;
  PacketWalker full(original);
  PacketDecoded d;
  while (full.next(d)) ends.push_back(full.offset());
  PacketWalker walker(report);
  for (std::size_t k = 0; k < ends.size() && ends[k] <= first_change; ++k) {
    RC_ASSERT(walker.next(d));
    RC_ASSERT(d.error == Error::ok);
    RC_ASSERT(d.message == sent[k]);
  }
}

// ---- random and mutated input --------------------------------------------------------

RC_GTEST_PROP(ProtocolProperty, RandomBytesIntoDecodePacket, ()) {
  const auto bytes = gen_bytes(72);
  expect_ok(mrskin::fuzz::packet_entry(bytes.data(), bytes.size()), bytes);
}

RC_GTEST_PROP(ProtocolProperty, MutatedPacketsIntoDecodePacket, ()) {
  auto bytes = packet_bytes(gen_message(Fit::packet), any<std::uint8_t>());
  bytes.resize(in<std::size_t>(bytes.size(), kHidReportBytes), 0);
  mutate(bytes);
  expect_ok(mrskin::fuzz::packet_entry(bytes.data(), bytes.size()), bytes);
}

RC_GTEST_PROP(ProtocolProperty, RandomFramesIntoCanDecoder, ()) {
  const auto classic = gen_bytes(1 + 12 * 12);
  expect_ok(mrskin::fuzz::can_classic_entry(classic.data(), classic.size()), classic);
  const auto fd = gen_bytes(1 + 3 * 68);
  expect_ok(mrskin::fuzz::can_fd_entry(fd.data(), fd.size()), fd);
}

RC_GTEST_PROP(ProtocolProperty, MutatedFramesIntoCanDecoder, ()) {
  // Valid frames of one message, turned into the classic fuzzer's input and mutated.
  const auto node = in<std::uint8_t>(kCanNodeMin, kCanNodeMax);
  const Message m = gen_message(Fit::classic_can);
  // Byte 0 selects the decoder node as 1 + byte % 15.
  std::vector<std::uint8_t> input{static_cast<std::uint8_t>(node - 1)};
  for (const CanFrame& f : can_frames(m, node, in<std::uint8_t>(0, 15), any<std::uint8_t>())) {
    // flags: keep the CRC as sent, or have the harness fix it after the mutation.
    input.push_back(static_cast<std::uint8_t>(in<int>(0, 1)));
    input.push_back(static_cast<std::uint8_t>(f.id & 0xFFU));
    input.push_back(static_cast<std::uint8_t>(f.id >> 8U));
    input.push_back(f.length);
    input.insert(input.end(), f.data.begin(), f.data.begin() + 8);
  }
  mutate(input);
  expect_ok(mrskin::fuzz::can_classic_entry(input.data(), input.size()), input);

  CanFrame fd;
  const Message pm = gen_message(Fit::packet);
  RC_ASSERT(encode_canfd(pm, node, direction_of(pm), any<std::uint8_t>(), fd).error == Error::ok);
  std::vector<std::uint8_t> fd_input{
      static_cast<std::uint8_t>(node - 1), static_cast<std::uint8_t>(1U | (in<unsigned>(0, 1) << 2U)),
      static_cast<std::uint8_t>(fd.id & 0xFFU), static_cast<std::uint8_t>(fd.id >> 8U), fd.length};
  fd_input.insert(fd_input.end(), fd.data.begin(), fd.data.begin() + fd.length);
  mutate(fd_input);
  expect_ok(mrskin::fuzz::can_fd_entry(fd_input.data(), fd_input.size()), fd_input);
}

// ---- quantisation --------------------------------------------------------------------

// A value within half an LSB of count c (strictly inside, so rounding is unambiguous).
double near_count(double c, double lsb) {
  const double frac = static_cast<double>(*rc::gen::inRange(-499999, 500000)) * 1e-6;
  return (c + frac) * lsb;
}

RC_GTEST_PROP(ProtocolProperty, QuantizeWithinHalfLsb, ()) {
  Identity id;
  id.current_lsb_nA = in<std::uint32_t>(1, 10'000'000);  // 1 nA .. 10 mA per count
  id.current_max_counts = in<std::uint16_t>(0, kCurrentCountMax);
  id.sensor_lsb_nano = in<std::uint32_t>(1, 100'000'000);
  const double lsb_A = id.current_lsb_nA * 1e-9;
  const double lsb_s = id.sensor_lsb_nano * 1e-9;

  const auto ci = in<std::uint16_t>(0, id.current_max_counts);
  const double current = near_count(ci, lsb_A);
  const auto qc = quantize_current(current, id);
  RC_ASSERT(qc.error == Error::ok);
  RC_ASSERT(qc.counts == ci);
  RC_ASSERT(mrskin::fuzz::within_half_lsb(current_from_counts(qc.counts, id), current, lsb_A));

  const auto si = in<std::int16_t>(kSensorCountMin, kSensorCountMax);
  const double reading = near_count(si, lsb_s);
  const auto qs = quantize_sensor(reading, id);
  RC_ASSERT(qs.error == Error::ok);
  RC_ASSERT(qs.counts == si);
  RC_ASSERT(mrskin::fuzz::within_half_lsb(sensor_from_counts(qs.counts, id), reading, lsb_s));

  const CellTarget t{in<std::uint16_t>(0, kStiffnessCountMax), in<std::uint16_t>(0, kOffsetCountMax),
                     in<std::uint16_t>(0, kCeilingCountMax), in<std::uint8_t>(0, kValidityCountMax)};
  const CellTargetSi target{near_count(t.stiffness, kStiffnessLsb_N_per_m),
                            near_count(t.offset, kOffsetLsb_m), near_count(t.ceiling, kCeilingLsb_N),
                            near_count(t.validity, kValidityLsb_s)};
  const auto qt = quantize_cell_target(target);
  RC_ASSERT(qt.error == Error::ok);
  RC_ASSERT(qt.counts == t);
  const CellTargetSi back = cell_target_to_si(qt.counts);
  RC_ASSERT(
      mrskin::fuzz::within_half_lsb(back.stiffness_N_per_m, target.stiffness_N_per_m, kStiffnessLsb_N_per_m));
  RC_ASSERT(mrskin::fuzz::within_half_lsb(back.offset_m, target.offset_m, kOffsetLsb_m));
  RC_ASSERT(mrskin::fuzz::within_half_lsb(back.ceiling_N, target.ceiling_N, kCeilingLsb_N));
  RC_ASSERT(mrskin::fuzz::within_half_lsb(back.validity_s, target.validity_s, kValidityLsb_s));
}

// Delta blocks (1.2, classic CAN) against a receiver that keeps each block's last values, on a
// link that loses frames: a changed block always goes, every host update sends a block, every
// block goes at least once in any kCanDeltaRefreshUpdates updates, and once frames stop being lost
// the receiver holds the sender's values within kCanDeltaRefreshUpdates updates.
RC_GTEST_PROP(ProtocolProperty, DeltaBlocksHealWithinTheRefresh, ()) {
  const auto blocks = *rc::gen::inRange<std::size_t>(1, kCanMaxBlocks + 1);
  const auto updates = *rc::gen::inRange(1, 60);
  const auto change_percent = *rc::gen::inRange(0, 101);
  const auto loss_percent = *rc::gen::inRange(0, 60);
  const bool host = *rc::gen::arbitrary<bool>();
  CanDeltaBlocks delta(host);
  std::array<std::uint16_t, CanDeltaBlocks::kValues> sender{};
  std::array<std::uint16_t, CanDeltaBlocks::kValues> receiver{};
  std::array<int, kCanMaxBlocks> unsent_run{};
  const int total = updates + static_cast<int>(kCanDeltaRefreshUpdates);
  for (int u = 0; u < total; ++u) {
    const bool lossy = u < updates;
    std::uint16_t changed = 0;
    for (std::size_t b = 0; b < blocks; ++b) {
      if (*rc::gen::inRange(0, 100) < change_percent) {
        const auto i = b * kCanValuesPerBlock + *rc::gen::inRange<std::size_t>(0, kCanValuesPerBlock);
        const auto value = *rc::gen::inRange<std::uint16_t>(0, 4096);
        changed = static_cast<std::uint16_t>(changed | (value != sender[i] ? 1U << b : 0U));
        sender[i] = value;
      }
    }
    const std::uint16_t sent = delta.select(sender, 0, blocks);
    RC_ASSERT(!host || sent != 0);
    RC_ASSERT((sent & changed) == changed);
    for (std::size_t b = 0; b < blocks; ++b) {
      if ((sent & (1U << b)) == 0) {
        RC_ASSERT(++unsent_run[b] < static_cast<int>(kCanDeltaRefreshUpdates));
        continue;
      }
      unsent_run[b] = 0;
      if (!(lossy && *rc::gen::inRange(0, 100) < loss_percent)) {
        const auto at = static_cast<std::ptrdiff_t>(b * kCanValuesPerBlock);
        std::copy_n(sender.begin() + at, kCanValuesPerBlock, receiver.begin() + at);
      }
    }
  }
  RC_ASSERT(std::equal(sender.begin(), sender.end(), receiver.begin()));
}

RC_GTEST_PROP(ProtocolProperty, QuantizeAnyDoubles, ()) {
  // Arbitrary doubles (NaN, Inf, huge, denormal) through the quantize fuzzer's entry.
  std::vector<std::uint8_t> bytes;
  auto put = [&bytes](const auto& v) {
    const auto* p = reinterpret_cast<const std::uint8_t*>(&v);
    bytes.insert(bytes.end(), p, p + sizeof v);
  };
  const auto special =
      rc::gen::element(std::numeric_limits<double>::quiet_NaN(), std::numeric_limits<double>::infinity(),
                       -std::numeric_limits<double>::infinity(), std::numeric_limits<double>::denorm_min(),
                       0.0, -0.0, 1e-3, 0.5);
  auto pick = [&special] {
    return *rc::gen::weightedOneOf<double>({{3, rc::gen::arbitrary<double>()}, {1, special}});
  };
  put(pick());
  put(pick());
  put(any<std::uint16_t>());
  put(any<std::int16_t>());
  put(any<std::int16_t>());
  put(any<std::uint32_t>());
  put(any<std::uint16_t>());
  put(any<std::uint32_t>());
  put(pick());
  put(pick());
  expect_ok(mrskin::fuzz::quantize_entry(bytes.data(), bytes.size()), bytes);
}

}  // namespace
