// Robot stream sources over loopback (127.0.0.1 and ::1): UDP, replay and recording, OpenIGTLink
// as client and as server; every malformed kind dropped and counted; a flood absorbed; latest()
// allocation-free. Loops are bounded and stop by themselves; nothing asserts on timing.
#include "mrskin/bridge/sources.hpp"

#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <igtlClientSocket.h>
#include <igtlNDArrayMessage.h>
#include <igtlPositionMessage.h>
#include <igtlQuaternionTrackingDataMessage.h>
#include <igtlSensorMessage.h>
#include <igtlTrackingDataMessage.h>
#include <igtlTransformMessage.h>
#include <igtlUnit.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <functional>
#include <limits>
#include <string>
#include <thread>
#include <vector>

#include "counting_new.hpp"
#include "mrskin/driver/errors.hpp"

// libopenigtlink 1.11's NDArrayMessage::Pack() never frees the info igtl_ndarray_alloc_info()
// gives it (48 + 4 bytes a message); the test sender packs three. Read only under ASan.
// The sanitizer runtime's hook has a reserved name by design.
#if defined(__clang__)
#pragma clang diagnostic push
#pragma clang diagnostic ignored "-Wreserved-identifier"
#endif
extern "C" const char* __lsan_default_suppressions() { return "leak:igtl_ndarray_alloc_info\n"; }
#if defined(__clang__)
#pragma clang diagnostic pop
#endif

namespace mrskin::bridge {
namespace {

using std::chrono::milliseconds;

// Polls pred every 2 ms, at most 10 s.
bool eventually(const std::function<bool()>& pred) {
  for (int k = 0; k < 5000; ++k) {
    if (pred()) {
      return true;
    }
    std::this_thread::sleep_for(milliseconds(2));
  }
  return pred();
}

// Takes the newest sample until one with this force arrives.
bool wait_for_force(SlaveSource& src, double force_N, SlaveSample& out) {
  return eventually([&] { return src.latest(TimePoint{}, out) && out.force_N == force_N; });
}

class UdpSender {
 public:
  UdpSender(bool v6, std::uint16_t port) : fd_(::socket(v6 ? AF_INET6 : AF_INET, SOCK_DGRAM, 0)) {
    if (v6) {
      sockaddr_in6 a{};
      a.sin6_family = AF_INET6;
      a.sin6_port = htons(port);
      a.sin6_addr = in6addr_loopback;
      (void)::connect(fd_, reinterpret_cast<const sockaddr*>(&a), sizeof a);
    } else {
      sockaddr_in a{};
      a.sin_family = AF_INET;
      a.sin_port = htons(port);
      a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
      (void)::connect(fd_, reinterpret_cast<const sockaddr*>(&a), sizeof a);
    }
  }
  UdpSender(const UdpSender&) = delete;
  UdpSender& operator=(const UdpSender&) = delete;
  ~UdpSender() { ::close(fd_); }
  void send(std::span<const std::uint8_t> bytes) const { (void)::send(fd_, bytes.data(), bytes.size(), 0); }
  void send(const UdpSample& s) const { send(encode_udp_sample(s)); }

 private:
  int fd_;
};

UdpSample udp_sample(std::uint32_t seq, double force_N) {
  UdpSample s;
  s.sequence = seq;
  s.stamp_ns = 1'000'000'000LL + static_cast<std::int64_t>(seq) * 1'000'000;
  s.force_N = force_N;
  s.indentation_m = 1e-3 + 1e-6 * seq;
  s.contact_x_m = 0.01;
  s.contact_y_m = -0.02;
  s.tip_radius_m = 3e-3;
  return s;
}

StreamSource& as_stream(const std::unique_ptr<SlaveSource>& s) { return dynamic_cast<StreamSource&>(*s); }

// ---- formats and the factory ------------------------------------------------------------------

TEST(Sources, Crc32cCheckValue) {
  const std::string text = "123456789";
  EXPECT_EQ(crc32c(std::span(reinterpret_cast<const std::uint8_t*>(text.data()), text.size())), 0xE3069283U);
}

TEST(Sources, BadUrisNameThePartAndListTheSchemes) {
  const auto message = [](std::string_view uri) {
    try {
      (void)make_source(uri);
    } catch (const InvalidArgument& e) {
      return std::string(e.what());
    }
    return std::string("no throw");
  };
  EXPECT_NE(message("ftp://x:1").find("igtl-listen://"), std::string::npos);
  EXPECT_NE(message("ftp://x:1").find("'ftp://'"), std::string::npos);
  EXPECT_NE(message("udp").find("scene://"), std::string::npos);
  EXPECT_NE(message("udp://127.0.0.1").find("missing port"), std::string::npos);
  EXPECT_NE(message("udp://127.0.0.1:70000").find("bad port '70000'"), std::string::npos);
  EXPECT_NE(message("igtl://:18944").find("missing host"), std::string::npos);
  EXPECT_NE(message("igtl://localhost:0").find("bad port"), std::string::npos);
  EXPECT_NE(message("udp://:0?speed=max").find("unknown option 'speed'"), std::string::npos);
  EXPECT_NE(message("replay://x?speed=2").find("bad speed '2'"), std::string::npos);
  EXPECT_NE(message("replay://").find("missing file"), std::string::npos);
  EXPECT_NE(message("scene://nope").find("demo"), std::string::npos);
  EXPECT_THROW((void)make_source("replay:///nonexistent/file.txt"), Error);
}

TEST(Sources, SceneThroughTheFactory) {
  auto s = make_source("scene://demo");
  SlaveSample out;
  EXPECT_TRUE(s->latest(TimePoint{0}, out));
  EXPECT_TRUE(out.valid);
}

// ---- UDP ------------------------------------------------------------------------------------------

class UdpFamilies : public ::testing::TestWithParam<bool> {};

TEST_P(UdpFamilies, GoodSamplesArriveMappedOntoTheHostClock) {
  const bool v6 = GetParam();
  SimulatedClock clock(TimePoint{std::chrono::seconds(50)});
  auto src = make_source(v6 ? "udp://[::1]:0" : "udp://:0", {}, &clock);
  auto& stream = as_stream(src);
  ASSERT_NE(stream.local_port(), 0);
  UdpSender tx(v6, stream.local_port());
  SlaveSample out;
  EXPECT_FALSE(src->latest(clock.now(), out));
  for (std::uint32_t k = 1; k <= 50; ++k) {
    tx.send(udp_sample(k, 0.01 * k));
  }
  ASSERT_TRUE(wait_for_force(*src, 0.5, out));
  EXPECT_TRUE(out.valid);
  EXPECT_DOUBLE_EQ(out.indentation_m, 1e-3 + 50e-6);
  EXPECT_DOUBLE_EQ(out.contact_x_m, 0.01);
  EXPECT_DOUBLE_EQ(out.contact_y_m, -0.02);
  EXPECT_DOUBLE_EQ(out.tip_radius_m, 3e-3);
  EXPECT_EQ(out.received, clock.now());
  // The clock stood still, so every later sample looked faster than the first: the offset fell
  // with each, and the stamps map to their arrival (never later).
  EXPECT_EQ(out.stamp, out.received);
  EXPECT_EQ(stream.stats().accepted, 50U);
  EXPECT_EQ(stream.stats().dropped(), 0U);
}
INSTANTIATE_TEST_SUITE_P(Loopback, UdpFamilies, ::testing::Values(false, true),
                         [](const ::testing::TestParamInfo<bool>& p) { return p.param ? "ipv6" : "ipv4"; });

TEST(UdpSource, TheStampMapsNoLaterThanArrivalAndFollowsTheMinimumDelay) {
  SimulatedClock clock(TimePoint{std::chrono::seconds(10)});
  auto src = make_source("udp://127.0.0.1:0", {}, &clock);
  UdpSender tx(false, as_stream(src).local_port());
  SlaveSample out;
  tx.send(udp_sample(1, 0.1));  // arrives "late": 5 ms
  ASSERT_TRUE(wait_for_force(*src, 0.1, out));
  const TimePoint first_arrival = out.received;
  clock.advance(milliseconds(1));
  tx.send(udp_sample(2, 0.2));  // robot + 1 ms, host + 1 ms: same delay
  ASSERT_TRUE(wait_for_force(*src, 0.2, out));
  EXPECT_EQ(out.stamp, first_arrival + milliseconds(1));
  tx.send(udp_sample(4, 0.3));  // robot + 2 ms, host + 0: faster than ever, the offset drops
  ASSERT_TRUE(wait_for_force(*src, 0.3, out));
  EXPECT_EQ(out.stamp, out.received);
}

TEST(UdpSource, EveryMalformedKindIsDroppedAndCounted) {
  auto src = make_source("udp://127.0.0.1:0");
  auto& stream = as_stream(src);
  UdpSender tx(false, stream.local_port());
  std::uint32_t seq = 1;
  tx.send(udp_sample(seq++, 0.1));  // good
  auto bad_version = encode_udp_sample(udp_sample(seq++, 0.2));
  bad_version[4] = 2;
  tx.send(bad_version);
  auto bad_crc = encode_udp_sample(udp_sample(seq++, 0.2));
  bad_crc[30] ^= 0x01U;
  tx.send(bad_crc);
  const auto good = encode_udp_sample(udp_sample(seq++, 0.2));
  tx.send(std::span(good.data(), 40));  // short
  std::vector<std::uint8_t> longer(good.begin(), good.end());
  longer.resize(100, 0);
  tx.send(longer);                           // oversized
  tx.send(std::span<const std::uint8_t>{});  // empty
  auto s = udp_sample(seq++, std::numeric_limits<double>::quiet_NaN());
  tx.send(s);
  s = udp_sample(seq++, 0.2);
  s.indentation_m = std::numeric_limits<double>::infinity();
  tx.send(s);
  tx.send(udp_sample(seq++, 25.0));  // force out of range
  s = udp_sample(seq++, 0.2);
  s.indentation_m = 0.06;
  tx.send(s);  // indentation out of range
  s = udp_sample(seq++, 0.2);
  s.force_N = -0.1;
  tx.send(s);  // negative force
  s = udp_sample(seq++, 0.2);
  s.stamp_ns = -1;
  tx.send(s);                         // stamp out of range
  tx.send(udp_sample(seq++, 0.4));    // good
  tx.send(udp_sample(seq - 2, 0.5));  // out of order
  tx.send(udp_sample(seq - 1, 0.6));  // duplicate stamp
  tx.send(udp_sample(seq++, 0.7));    // good, the sentinel
  SlaveSample out;
  ASSERT_TRUE(wait_for_force(*src, 0.7, out));
  const SourceStats st = stream.stats();
  EXPECT_EQ(st.accepted, 3U);
  EXPECT_EQ(st.of(DropReason::format), 1U);  // version
  EXPECT_EQ(st.of(DropReason::crc), 1U);
  EXPECT_EQ(st.of(DropReason::length), 2U);  // short, empty
  EXPECT_EQ(st.of(DropReason::oversized), 1U);
  EXPECT_EQ(st.of(DropReason::non_finite), 2U);
  EXPECT_EQ(st.of(DropReason::out_of_range), 3U);
  EXPECT_EQ(st.of(DropReason::stamp), 1U);
  EXPECT_EQ(st.of(DropReason::out_of_order), 1U);
  EXPECT_EQ(st.of(DropReason::duplicate), 1U);
  EXPECT_EQ(st.dropped(), 13U);
  // Each reason is explained once, with what to do.
  const std::vector<SourceEvent> events = stream.events_after(0);
  EXPECT_EQ(events.size(), 9U);
  EXPECT_TRUE(std::all_of(events.begin(), events.end(), [](const SourceEvent& e) { return e.warning; }));
  EXPECT_EQ(stream.event_count(), events.size());
  EXPECT_NE(stream.last_warning().find("repeats the last one"), std::string::npos) << stream.last_warning();
}

TEST(UdpSource, AStreamThatRestartsIsFollowedAfterARunOfOlderStamps) {
  SourceOptions o;
  o.restart_after_out_of_order = 5;
  auto src = make_source("udp://127.0.0.1:0", o);
  auto& stream = as_stream(src);
  UdpSender tx(false, stream.local_port());
  tx.send(udp_sample(1000, 0.1));
  for (std::uint32_t k = 1; k <= 6; ++k) {  // the robot rebooted: its stamps start again
    tx.send(udp_sample(k, 0.2 + 0.01 * k));
  }
  SlaveSample out;
  ASSERT_TRUE(wait_for_force(*src, 0.26, out));
  EXPECT_EQ(stream.stats().of(DropReason::out_of_order), 4U);
  EXPECT_EQ(stream.stats().restarts, 1U);
}

TEST(UdpSource, AFloodOfTenTimesTheRateIsAbsorbedAndTheNewestWins) {
  auto src = make_source("udp://127.0.0.1:0?queue=64");
  auto& stream = as_stream(src);
  UdpSender tx(false, stream.local_port());
  // 10,000 datagrams in one burst (10 s of a 1 kHz stream at once) while the "tick" keeps
  // reading: what it sees only moves forward.
  std::atomic<bool> done{false};
  std::uint64_t reads = 0;
  TimePoint newest{};
  bool monotonic = true;
  std::thread tick([&] {
    SlaveSample out;
    while (!done.load()) {
      if (src->latest(TimePoint{}, out)) {
        monotonic = monotonic && out.stamp >= newest;
        newest = out.stamp;
      }
      ++reads;
      std::this_thread::sleep_for(std::chrono::microseconds(200));
    }
  });
  for (std::uint32_t k = 1; k <= 10'000; ++k) {
    tx.send(udp_sample(k, 1.0));
  }
  // The kernel may drop part of a burst its socket buffer cannot hold; once the source has
  // settled, the sample after the flood arrives.
  std::uint64_t seen = 0;
  ASSERT_TRUE(eventually([&] {
    const SourceStats st = stream.stats();
    const std::uint64_t now_seen = st.accepted + st.dropped();
    const bool settled = now_seen == seen;
    seen = now_seen;
    return settled;
  }));
  done.store(true);
  tick.join();
  // Sent again until seen: a sanitised build may still be draining a full socket buffer, and the
  // kernel drops what does not fit.
  SlaveSample out;
  std::uint32_t marker = 20'000;
  ASSERT_TRUE(eventually([&] {
    tx.send(udp_sample(marker++, 1.5));
    std::this_thread::sleep_for(milliseconds(5));
    return src->latest(TimePoint{}, out) && out.force_N == 1.5;
  }));
  EXPECT_TRUE(monotonic);
  EXPECT_GT(reads, 0U);
  const SourceStats st = stream.stats();
  EXPECT_GT(st.accepted, 64U);
  EXPECT_LE(st.accepted, 10'000U + (marker - 20'000U));
  EXPECT_EQ(st.dropped() - st.of(DropReason::superseded), 0U);
}

TEST(UdpSource, WithoutATickTheQueueOverflowsIntoQueueFullAndTheNewestStillGetsThrough) {
  auto src = make_source("udp://127.0.0.1:0?queue=8");
  auto& stream = as_stream(src);
  UdpSender tx(false, stream.local_port());
  for (std::uint32_t k = 1; k <= 40; ++k) {
    tx.send(udp_sample(k, 0.01 * k));
    std::this_thread::sleep_for(std::chrono::microseconds(100));  // within the socket's buffer
  }
  ASSERT_TRUE(eventually([&] { return stream.stats().accepted == 40U; }));
  EXPECT_GT(stream.stats().of(DropReason::superseded), 0U);
  SlaveSample out;
  ASSERT_TRUE(src->latest(TimePoint{}, out));  // the queue's 8 oldest; the newest is held back
  ASSERT_TRUE(wait_for_force(*src, 0.4, out));
}

TEST(UdpSource, LatestAllocatesNothingAndAStoppedStreamKeepsItsLastStamp) {
  SimulatedClock clock(TimePoint{std::chrono::seconds(1)});
  auto src = make_source("udp://127.0.0.1:0", {}, &clock);
  auto& stream = as_stream(src);
  UdpSender tx(false, stream.local_port());
  for (std::uint32_t k = 1; k <= 100; ++k) {
    tx.send(udp_sample(k, 0.005 * k));
  }
  ASSERT_TRUE(eventually([&] { return stream.stats().accepted == 100U; }));
  SlaveSample out;
  const std::uint64_t before = mrskin::test::allocation_count();
  bool ok = true;
  for (int k = 0; k < 1000; ++k) {  // drains the queue, then holds the last sample
    ok = src->latest(clock.now(), out) && ok;
    clock.advance(milliseconds(1));
  }
  EXPECT_EQ(mrskin::test::allocation_count() - before, 0U);
  EXPECT_TRUE(ok);
  EXPECT_DOUBLE_EQ(out.force_N, 0.5);
  EXPECT_LT(out.stamp, clock.now() - milliseconds(900));  // old: the bridge's stale policy acts on it
}

TEST(UdpSource, TheArrivalHookFiresFromTheIoThread) {
  auto src = make_source("udp://127.0.0.1:0");
  auto& stream = as_stream(src);
  std::atomic<int> calls{0};
  stream.set_arrival_hook([](void* c) noexcept { static_cast<std::atomic<int>*>(c)->fetch_add(1); }, &calls);
  UdpSender tx(false, stream.local_port());
  tx.send(udp_sample(1, 0.1));
  EXPECT_TRUE(eventually([&] { return calls.load() == 1; }));
}

// ---- replay and recording ------------------------------------------------------------------------

std::filesystem::path temp_file(const std::string& name) {
  return std::filesystem::temp_directory_path() /
         ("mrskin-sources-" + std::to_string(::getpid()) + "-" + name);
}

std::vector<SlaveSample> recorded_samples() {
  std::vector<SlaveSample> v;
  for (int k = 0; k < 200; ++k) {
    SlaveSample s;
    s.stamp = TimePoint{std::chrono::seconds(7)} + milliseconds(k);
    s.received = s.stamp + std::chrono::microseconds(200 + 10 * (k % 5));
    s.force_N = 0.1 + std::sin(0.05 * k) * 0.05 + 1e-9 / 3.0;
    s.indentation_m = 1e-3 * std::cos(0.03 * k);
    s.contact_x_m = 1e-3 / 7.0 * k;
    s.contact_y_m = -2e-3 / 3.0;
    s.tip_radius_m = 3e-3;
    s.valid = true;
    v.push_back(s);
  }
  return v;
}

std::filesystem::path record(const std::vector<SlaveSample>& samples, const std::string& name) {
  const auto path = temp_file(name);
  SampleRecorder rec(path.string());
  for (const SlaveSample& s : samples) {
    EXPECT_TRUE(rec.record(s));
    EXPECT_FALSE(rec.record(s));  // the same stamp again: the tick saw no new sample
  }
  rec.close();
  EXPECT_EQ(rec.written(), samples.size());
  EXPECT_EQ(rec.dropped(), 0U);
  return path;
}

TEST(Replay, RecordThenReplayOnTheRecordedTimingGivesTheSameSamples) {
  const auto samples = recorded_samples();
  const auto path = record(samples, "timed.txt");
  SimulatedClock clock(TimePoint{std::chrono::seconds(100)});
  auto src = make_source("replay://" + path.string(), {}, &clock);
  const TimePoint start = clock.now();
  std::vector<SlaveSample> got;
  SlaveSample out;
  for (int k = 0; k < 20'000 && got.size() < samples.size(); ++k) {  // 10 us steps
    if (src->latest(clock.now(), out) && (got.empty() || out.stamp != got.back().stamp)) {
      EXPECT_EQ(out.received, clock.now());  // delivered the step it became due
      got.push_back(out);
    }
    clock.advance(std::chrono::microseconds(10));
  }
  ASSERT_EQ(got.size(), samples.size());
  for (std::size_t i = 0; i < samples.size(); ++i) {
    EXPECT_EQ(got[i].force_N, samples[i].force_N);
    EXPECT_EQ(got[i].indentation_m, samples[i].indentation_m);
    EXPECT_EQ(got[i].contact_x_m, samples[i].contact_x_m);
    EXPECT_EQ(got[i].contact_y_m, samples[i].contact_y_m);
    EXPECT_EQ(got[i].tip_radius_m, samples[i].tip_radius_m);
    EXPECT_EQ(got[i].stamp - got[0].stamp, samples[i].stamp - samples[0].stamp);
    EXPECT_EQ(got[i].received - start, samples[i].received - samples[0].received);
    EXPECT_LE(got[i].stamp, got[i].received);
  }
  // The end: the last sample holds with its old stamp.
  clock.advance(std::chrono::seconds(1));
  ASSERT_TRUE(src->latest(clock.now(), out));
  EXPECT_EQ(out.stamp, got.back().stamp);
  EXPECT_EQ(dynamic_cast<StreamSource&>(*src).stats().accepted, samples.size());
  std::filesystem::remove(path);
}

TEST(Replay, SpeedMaxGivesOneSamplePerCallAndLoops) {
  const auto samples = recorded_samples();
  const auto path = record(samples, "max.txt");
  SimulatedClock clock;
  auto src = make_source("replay://" + path.string() + "?speed=max&loop=1", {}, &clock);
  SlaveSample out;
  const std::uint64_t before = mrskin::test::allocation_count();
  for (std::size_t i = 0; i < 2 * samples.size(); ++i) {
    ASSERT_TRUE(src->latest(clock.now(), out));
    EXPECT_EQ(out.force_N, samples[i % samples.size()].force_N);
    EXPECT_EQ(out.stamp, clock.now());
    clock.advance(std::chrono::microseconds(1));
  }
  EXPECT_EQ(mrskin::test::allocation_count() - before, 0U);
  std::filesystem::remove(path);
}

TEST(Replay, TimedLoopStartsOverAfterTheEnd) {
  const auto samples = recorded_samples();
  const auto path = record(samples, "loop.txt");
  SimulatedClock clock;
  auto src = make_source("replay://" + path.string() + "?loop=1", {}, &clock);
  SlaveSample out;
  const std::uint64_t before = mrskin::test::allocation_count();
  ASSERT_TRUE(src->latest(clock.now(), out));
  EXPECT_EQ(out.force_N, samples[0].force_N);
  // One cycle is the recording's span (199.04 ms) plus one mean period (1.0002 ms).
  const Duration cycle = Duration{199'040'000} + Duration{199'040'000} / 199;
  clock.advance(cycle);
  ASSERT_TRUE(src->latest(clock.now(), out));
  EXPECT_EQ(out.force_N, samples[0].force_N);
  EXPECT_EQ(out.received, clock.now());
  clock.advance(milliseconds(199) + std::chrono::microseconds(40));
  ASSERT_TRUE(src->latest(clock.now(), out));
  EXPECT_EQ(out.force_N, samples[199].force_N);
  EXPECT_EQ(mrskin::test::allocation_count() - before, 0U);
  std::filesystem::remove(path);
}

TEST(Replay, BadLinesAreDroppedAndCountedAndABadHeaderRefused) {
  const auto path = temp_file("bad.txt");
  {
    std::FILE* f = std::fopen(path.c_str(), "w");
    ASSERT_NE(f, nullptr);
    std::fputs("# mrskin-stream 1\n", f);
    std::fputs("# a comment\n", f);
    std::fputs("0 100 0.5 0.001 0 0 0.003\n", f);           // good
    std::fputs("1000 1100 0.5 0.001 0 0\n", f);             // malformed: six fields
    std::fputs("1000 1100 0.5 0.001 0 0 0.003 9\n", f);     // malformed: eight
    std::fputs("1000 1100 zero 0.001 0 0 0.003\n", f);      // malformed
    std::fputs("1000 1100 nan 0.001 0 0 0.003\n", f);       // non-finite
    std::fputs("1000 1100 0.5 inf 0 0 0.003\n", f);         // non-finite
    std::fputs("1000 1100 21 0.001 0 0 0.003\n", f);        // out of range
    std::fputs("-5 1100 0.5 0.001 0 0 0.003\n", f);         // stamp out of range
    std::fputs("0 1100 0.5 0.001 0 0 0.003\n", f);          // duplicate stamp
    std::fputs("2000 2100 0.6 0.001 0 0 0.003\n", f);       // good
    std::fputs("1000 2200 0.6 0.001 0 0 0.003\n", f);       // out of order
    std::fputs((std::string(600, '1') + "\n").c_str(), f);  // oversized line
    std::fputs("3000 3100 0.7 0.001 0 0 0.003\n", f);       // good
    (void)std::fclose(f);
  }
  auto src = open_stream("replay://" + path.string());
  const SourceStats st = src->stats();
  EXPECT_EQ(st.accepted, 3U);
  EXPECT_EQ(st.of(DropReason::format), 3U);
  EXPECT_EQ(st.of(DropReason::non_finite), 2U);
  EXPECT_EQ(st.of(DropReason::out_of_range), 1U);
  EXPECT_EQ(st.of(DropReason::stamp), 1U);
  EXPECT_EQ(st.of(DropReason::duplicate), 1U);
  EXPECT_EQ(st.of(DropReason::out_of_order), 1U);
  EXPECT_EQ(st.of(DropReason::oversized), 1U);
  const std::vector<SourceEvent> events = src->events_after(0);
  ASSERT_FALSE(events.empty());
  EXPECT_NE(events.front().text.find("replay line 4 skipped: not 7 numbers"), std::string::npos)
      << events.front().text;
  {
    std::FILE* f = std::fopen(path.c_str(), "w");
    std::fputs("# mrskin-stream 2\n0 0 0 0 0 0 0\n", f);
    (void)std::fclose(f);
  }
  EXPECT_THROW((void)open_stream("replay://" + path.string()), Error);
  {
    std::FILE* f = std::fopen(path.c_str(), "w");  // a first line too long to be the header
    std::fputs(("# mrskin-stream 1" + std::string(600, ' ') + "\n0 0 0 0 0 0 0\n").c_str(), f);
    (void)std::fclose(f);
  }
  EXPECT_THROW((void)open_stream("replay://" + path.string()), Error);
  std::filesystem::remove(path);
}

// ---- OpenIGTLink ---------------------------------------------------------------------------------

igtl::TimeStamp::Pointer stamp_at(std::uint32_t ms) {
  auto ts = igtl::TimeStamp::New();
  ts->SetTime(1000U + ms / 1000U, (ms % 1000U) * 1'000'000U);
  return ts;
}

// A SENSOR message: the contact force in newtons.
igtl::MessageBase::Pointer force_message(double force_N, std::uint32_t ms, bool newton = true,
                                         const char* device = "ContactForce") {
  auto m = igtl::SensorMessage::New();
  m->SetDeviceName(device);
  m->SetLength(1);
  auto unit = igtl::Unit::New();
  unit->Init();
  unit->SetPrefix(igtl::Unit::SI_PREFIX_NONE);
  unit->Append(newton ? igtl::Unit::SI_DERIVED_NEWTON : igtl::Unit::SI_DERIVED_PASCAL, 1);
  m->SetUnit(unit);
  m->SetValue(0U, force_N);
  auto ts = stamp_at(ms);
  m->SetTimeStamp(ts);
  m->Pack();
  return igtl::MessageBase::Pointer(m.GetPointer());
}

// A TRANSFORM at (x, y, z) mm in the tissue frame.
igtl::MessageBase::Pointer transform_message(float x_mm, float y_mm, float z_mm, std::uint32_t ms) {
  auto m = igtl::TransformMessage::New();
  m->SetDeviceName("InstrumentTip");
  igtl::Matrix4x4 mat;
  igtl::IdentityMatrix(mat);
  mat[0][3] = x_mm;
  mat[1][3] = y_mm;
  mat[2][3] = z_mm;
  m->SetMatrix(mat);
  auto ts = stamp_at(ms);
  m->SetTimeStamp(ts);
  m->Pack();
  return igtl::MessageBase::Pointer(m.GetPointer());
}

igtl::MessageBase::Pointer position_message(float x_mm, float y_mm, float z_mm, std::uint32_t ms) {
  auto m = igtl::PositionMessage::New();
  m->SetDeviceName("InstrumentTip");
  m->SetPackType(igtl::PositionMessage::ALL);
  m->SetPosition(x_mm, y_mm, z_mm);
  m->SetQuaternion(0.0F, 0.0F, 0.0F, 1.0F);
  auto ts = stamp_at(ms);
  m->SetTimeStamp(ts);
  m->Pack();
  return igtl::MessageBase::Pointer(m.GetPointer());
}

// A 3 x 4 pressure map (Pa), float32, with pressure on two cells.
igtl::MessageBase::Pointer map_message(std::uint32_t ms) {
  igtl::Array<igtlFloat32> array;
  igtl::ArrayBase::IndexType size(2);
  size[0] = 3;
  size[1] = 4;
  array.SetSize(size);
  // Filled whole: 1.11's Array<T>::SetValue indexes T* by bytes and writes past the array.
  std::array<igtlFloat32, 12> cells{};
  cells[1 * 4 + 2] = 30000.0F;  // row 1 (centre row), column 2: +0.5 pitch from the centre
  cells[2 * 4 + 2] = 10000.0F;  // row 2: +1 pitch
  array.SetArray(cells.data());
  auto m = igtl::NDArrayMessage::New();
  m->SetDeviceName("TactileArray");
  m->SetArray(igtl::NDArrayMessage::TYPE_FLOAT32, &array);
  auto ts = stamp_at(ms);
  m->SetTimeStamp(ts);
  m->Pack();
  return igtl::MessageBase::Pointer(m.GetPointer());
}

void send_all(int fd, const igtl::MessageBase::Pointer& m) {
  const auto* p = static_cast<const std::uint8_t*>(m->GetPackPointer());
  std::size_t left = static_cast<std::size_t>(m->GetPackSize());
  while (left > 0) {
    const ssize_t n = ::send(fd, p, left, MSG_NOSIGNAL);
    if (n <= 0) {
      return;
    }
    p += n;
    left -= static_cast<std::size_t>(n);
  }
}

// What both directions check: pose then force, a pressure map, POSITION, bad messages.
void exercise(StreamSource& src, const std::function<void(const igtl::MessageBase::Pointer&)>& send,
              const std::function<void(std::span<const std::uint8_t>)>& send_raw) {
  SlaveSample out;
  send(force_message(0.2, 1));  // force before any pose: contact at the origin, no indentation
  ASSERT_TRUE(wait_for_force(src, 0.2, out));
  EXPECT_EQ(out.contact_x_m, 0.0);
  EXPECT_EQ(out.tip_radius_m, 3e-3);
  send(transform_message(10.0F, -5.0F, -2.0F, 2));  // 2 mm into the tissue
  send(force_message(0.75, 2));
  ASSERT_TRUE(wait_for_force(src, 0.75, out));
  EXPECT_NEAR(out.contact_x_m, 0.010, 1e-7);
  EXPECT_NEAR(out.contact_y_m, -0.005, 1e-7);
  EXPECT_NEAR(out.indentation_m, 0.002, 1e-7);
  EXPECT_LE(out.stamp, out.received);
  const TimePoint first_stamp = out.stamp;
  send(position_message(4.0F, 3.0F, -1.0F, 3));
  send(force_message(0.8, 3));
  ASSERT_TRUE(wait_for_force(src, 0.8, out));
  EXPECT_NEAR(out.contact_x_m, 0.004, 1e-7);
  EXPECT_NEAR(out.indentation_m, 0.001, 1e-7);
  // Robot stamps 1 ms apart, mapped by the minimum-delay offset: later, never past the arrival.
  EXPECT_GT(out.stamp, first_stamp);
  EXPECT_LE(out.stamp, out.received);
  // The map: 40 kPa over 2 mm cells = 0.16 N; centroid x = 0.5 pitch, y = 0.25 pitch from the centre.
  send(map_message(4));
  ASSERT_TRUE(eventually([&] { return src.latest(TimePoint{}, out) && std::abs(out.force_N - 0.16) < 1e-9; }))
      << "dropped " << src.stats().dropped() << " (" << src.last_warning() << ") force " << out.force_N;
  EXPECT_NEAR(out.contact_x_m, 0.004 + 0.5 * 2e-3, 1e-9);
  EXPECT_NEAR(out.contact_y_m, 0.003 + 0.25 * 2e-3, 1e-9);
  // Dropped and counted: wrong unit, unknown device, a duplicate, an older stamp, a bad CRC,
  // an out-of-range force.
  const SourceStats before = src.stats();
  send(force_message(0.3, 5, false));
  send(force_message(0.3, 5, true, "SomethingElse"));
  send(force_message(0.3, 3));
  send(force_message(0.3, 2));
  send(force_message(25.0, 6));
  auto corrupt = force_message(0.3, 7);
  std::vector<std::uint8_t> bytes(
      static_cast<const std::uint8_t*>(corrupt->GetPackPointer()),
      static_cast<const std::uint8_t*>(corrupt->GetPackPointer()) + corrupt->GetPackSize());
  bytes.back() ^= 0x40U;
  send_raw(bytes);
  send(force_message(0.9, 8));
  ASSERT_TRUE(wait_for_force(src, 0.9, out));
  const SourceStats st = src.stats();
  const auto delta = [&](DropReason r) { return st.of(r) - before.of(r); };
  EXPECT_EQ(delta(DropReason::unit), 1U);
  EXPECT_EQ(delta(DropReason::device), 1U);
  EXPECT_EQ(delta(DropReason::duplicate), 1U);
  EXPECT_EQ(delta(DropReason::out_of_order), 1U);
  EXPECT_EQ(delta(DropReason::out_of_range), 1U);
  EXPECT_EQ(delta(DropReason::crc), 1U);
  EXPECT_EQ(st.accepted, 5U);
  EXPECT_EQ(st.poses, 2U);
  // The unknown device is named with the key that takes it.
  bool named = false;
  for (const SourceEvent& e : src.events_after(0)) {
    named = named || (e.text.find("SENSOR from device 'SomethingElse' ignored") != std::string::npos &&
                      e.text.find("set force_device=SomethingElse") != std::string::npos);
  }
  EXPECT_TRUE(named);
}

// A loopback TCP server for the igtl:// client (the library's ServerSocket binds every address).
class LoopbackServer {
 public:
  explicit LoopbackServer(bool v6) : fd_(::socket(v6 ? AF_INET6 : AF_INET, SOCK_STREAM, 0)) {
    const int one = 1;
    (void)::setsockopt(fd_, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
    if (v6) {
      sockaddr_in6 a{};
      a.sin6_family = AF_INET6;
      a.sin6_addr = in6addr_loopback;
      (void)::bind(fd_, reinterpret_cast<const sockaddr*>(&a), sizeof a);
    } else {
      sockaddr_in a{};
      a.sin_family = AF_INET;
      a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
      (void)::bind(fd_, reinterpret_cast<const sockaddr*>(&a), sizeof a);
    }
    (void)::listen(fd_, 2);
    sockaddr_storage addr{};
    socklen_t len = sizeof addr;
    (void)::getsockname(fd_, reinterpret_cast<sockaddr*>(&addr), &len);
    port_ = ntohs(v6 ? reinterpret_cast<sockaddr_in6*>(&addr)->sin6_port
                     : reinterpret_cast<sockaddr_in*>(&addr)->sin_port);
  }
  LoopbackServer(const LoopbackServer&) = delete;
  LoopbackServer& operator=(const LoopbackServer&) = delete;
  ~LoopbackServer() { ::close(fd_); }
  [[nodiscard]] std::uint16_t port() const { return port_; }
  // Accepts one connection, waiting at most 10 s; -1 if none came.
  [[nodiscard]] int accept_one() const {
    pollfd p{fd_, POLLIN, 0};
    if (::poll(&p, 1, 10'000) <= 0) {
      return -1;
    }
    return ::accept(fd_, nullptr, nullptr);
  }

 private:
  int fd_;
  std::uint16_t port_ = 0;
};

class IgtlFamilies : public ::testing::TestWithParam<bool> {};

TEST_P(IgtlFamilies, ClientReadsSensorTransformPositionAndNdarrayAndReconnects) {
  const bool v6 = GetParam();
  LoopbackServer server(v6);
  SourceOptions o;
  o.reconnect_min_s = 0.01;
  o.reconnect_max_s = 0.05;
  auto stream =
      open_stream(std::string("igtl://") + (v6 ? "[::1]:" : "127.0.0.1:") + std::to_string(server.port()), o);
  int conn = server.accept_one();
  ASSERT_GE(conn, 0);
  exercise(
      *stream, [&](const igtl::MessageBase::Pointer& m) { send_all(conn, m); },
      [&](std::span<const std::uint8_t> b) { (void)::send(conn, b.data(), b.size(), MSG_NOSIGNAL); });
  // The robot goes away: the last sample stays, with its old stamp; then it comes back.
  SlaveSample held;
  ASSERT_TRUE(stream->latest(TimePoint{}, held));
  ::close(conn);
  ASSERT_TRUE(eventually([&] { return stream->stats().disconnects == 1U; }));
  SlaveSample out;
  ASSERT_TRUE(stream->latest(TimePoint{}, out));
  EXPECT_EQ(out.stamp, held.stamp);
  conn = server.accept_one();
  ASSERT_GE(conn, 0);
  send_all(conn, force_message(1.25, 1));  // a new session: its stamps start over
  ASSERT_TRUE(wait_for_force(*stream, 1.25, out));
  EXPECT_EQ(stream->stats().connections, 2U);
  // A body larger than the limit: counted, and the connection is dropped.
  std::array<std::uint8_t, 58> header{};
  header[1] = 1;
  std::memcpy(header.data() + 2, "SENSOR", 6);
  header[42] = 0x7F;  // 2^63-ish bytes
  (void)::send(conn, header.data(), header.size(), MSG_NOSIGNAL);
  ASSERT_TRUE(eventually(
      [&] { return stream->stats().of(DropReason::oversized) == 1U && stream->stats().disconnects == 2U; }));
  ::close(conn);
}
INSTANTIATE_TEST_SUITE_P(Loopback, IgtlFamilies, ::testing::Values(false, true),
                         [](const ::testing::TestParamInfo<bool>& p) { return p.param ? "ipv6" : "ipv4"; });

TEST(IgtlListen, ServerTakesARobotConnectingWithTheLibrarysClientSocket) {
  auto stream = open_stream("igtl-listen://127.0.0.1:0");
  ASSERT_NE(stream->local_port(), 0);
  auto client = igtl::ClientSocket::New();
  ASSERT_EQ(client->ConnectToServer("127.0.0.1", stream->local_port()), 0);
  exercise(
      *stream,
      [&](const igtl::MessageBase::Pointer& m) { client->Send(m->GetPackPointer(), m->GetPackSize()); },
      [&](std::span<const std::uint8_t> b) { client->Send(b.data(), static_cast<int>(b.size())); });
  // A second robot connection replaces the first.
  auto second = igtl::ClientSocket::New();
  ASSERT_EQ(second->ConnectToServer("127.0.0.1", stream->local_port()), 0);
  ASSERT_TRUE(eventually([&] { return stream->stats().connections == 2U; }));
  auto m = force_message(1.5, 1);
  second->Send(m->GetPackPointer(), m->GetPackSize());
  SlaveSample out;
  ASSERT_TRUE(wait_for_force(*stream, 1.5, out));
  client->CloseSocket();
  second->CloseSocket();
}

// ---- OpenIGTLink as senders in the field send it -----------------------------------------------

// A SENSOR of n values in the unit prefix given (igtl::Unit::SI_PREFIX_*), from device.
igtl::MessageBase::Pointer sensor_message(const char* device, std::vector<double> values, std::uint32_t ms,
                                          int prefix = igtl::Unit::SI_PREFIX_NONE, bool newton = true) {
  auto m = igtl::SensorMessage::New();
  m->SetDeviceName(device);
  m->SetLength(static_cast<unsigned int>(values.size()));
  auto unit = igtl::Unit::New();
  unit->Init();
  if (newton) {
    unit->SetPrefix(prefix);
    unit->Append(igtl::Unit::SI_DERIVED_NEWTON, 1);
  }
  m->SetUnit(unit);
  for (std::size_t i = 0; i < values.size(); ++i) {
    m->SetValue(static_cast<unsigned int>(i), values[i]);
  }
  auto ts = stamp_at(ms);
  m->SetTimeStamp(ts);
  m->Pack();
  return igtl::MessageBase::Pointer(m.GetPointer());
}

// A robot on the library's ClientSocket, connected to an igtl-listen:// source.
class Robot {
 public:
  explicit Robot(const StreamSource& src) : socket_(igtl::ClientSocket::New()) {
    connected_ = socket_->ConnectToServer("127.0.0.1", src.local_port()) == 0;
  }
  Robot(const Robot&) = delete;
  Robot& operator=(const Robot&) = delete;
  ~Robot() { socket_->CloseSocket(); }
  [[nodiscard]] bool connected() const { return connected_; }
  void send(const igtl::MessageBase::Pointer& m) {
    (void)socket_->Send(m->GetPackPointer(), m->GetPackSize());
  }

 private:
  igtl::ClientSocket::Pointer socket_;
  bool connected_ = false;
};

// Within rounding of force_N (a unit or a frame converted it).
bool wait_for_force_near(SlaveSource& src, double force_N, SlaveSample& out) {
  return eventually([&] { return src.latest(TimePoint{}, out) && std::abs(out.force_N - force_N) < 1e-12; });
}

// The source counts a drop before its event is published (another thread): callers wait for it.
bool has_event(const StreamSource& src, std::string_view a, std::string_view b = {}) {
  const std::vector<SourceEvent> events = src.events_after(0);
  return std::any_of(events.begin(), events.end(), [&](const SourceEvent& e) {
    return e.text.find(a) != std::string::npos && e.text.find(b) != std::string::npos;
  });
}

TEST(IgtlField, DeviceNamesComeFromTheUriAndStarTakesAny) {
  auto src = open_stream("igtl-listen://127.0.0.1:0?force_device=FTSensor&pose_device=Tracker");
  Robot robot(*src);
  ASSERT_TRUE(robot.connected());
  SlaveSample out;
  robot.send(sensor_message("ContactForce", {0.4}, 1));  // today's default name: not configured here
  robot.send(sensor_message("FTSensor", {0.5}, 2));
  ASSERT_TRUE(wait_for_force(*src, 0.5, out));
  EXPECT_EQ(src->stats().of(DropReason::device), 1U);
  EXPECT_TRUE(eventually([&] {
    return has_event(*src, "SENSOR from device 'ContactForce' ignored", "set force_device=ContactForce");
  }));
  EXPECT_NE(src->last_warning().find("force_device=ContactForce"), std::string::npos) << src->last_warning();

  auto any = open_stream("igtl-listen://127.0.0.1:0?force_device=*");
  Robot second(*any);
  ASSERT_TRUE(second.connected());
  second.send(sensor_message("WhateverItIsCalled", {0.6}, 1));
  ASSERT_TRUE(wait_for_force(*any, 0.6, out));
  EXPECT_EQ(any->stats().dropped(), 0U);

  EXPECT_THROW((void)open_stream("igtl-listen://127.0.0.1:0?force_device="), InvalidArgument);
  EXPECT_THROW((void)open_stream("igtl-listen://127.0.0.1:0?force_device=ThisNameIsLongerThan20"),
               InvalidArgument);
  EXPECT_THROW((void)open_stream("udp://127.0.0.1:0?force_device=X"), InvalidArgument);
  EXPECT_THROW((void)open_stream("igtl-listen://127.0.0.1:0?rpy_deg=1,2"), InvalidArgument);
  // A queue is bounded: no unbounded allocation, and no endless rounding to a power of two.
  EXPECT_THROW((void)open_stream("udp://127.0.0.1:0?queue=65537"), InvalidArgument);
  EXPECT_THROW((void)open_stream("udp://127.0.0.1:0?queue=9223372036854775809"), InvalidArgument);
  EXPECT_THROW((void)open_stream("igtl-listen://127.0.0.1:0?queue=1000000000000"), InvalidArgument);
  EXPECT_THROW((void)open_stream("igtl-listen://127.0.0.1:0?rpy_deg=1,2,nan"), InvalidArgument);
}

TEST(IgtlField, ForceVectorsAndWrenchesGiveTheNormalComponentInTheTissueFrame) {
  // The robot's frame is the tissue frame rolled by 90 degrees about x: the robot's +y is the
  // tissue's outward normal (+z), its +z the tissue's -y.
  auto src = open_stream("igtl-listen://127.0.0.1:0?force_device=FT&rpy_deg=90,0,0");
  Robot robot(*src);
  ASSERT_TRUE(robot.connected());
  SlaveSample out;
  robot.send(sensor_message("FT", {0.2, 0.75, 0.3}, 1));  // force: 0.75 N along the normal
  ASSERT_TRUE(wait_for_force_near(*src, 0.75, out)) << out.force_N << " " << src->last_warning();
  robot.send(
      sensor_message("FT", {0.0, 0.5, 0.0, 0.01, 0.02, 0.03}, 2));  // a wrench: the torque is not force
  ASSERT_TRUE(wait_for_force_near(*src, 0.5, out));
  robot.send(sensor_message("FT", {0.0, -0.4, 0.0}, 3));  // pulling: no contact, not a drop
  ASSERT_TRUE(eventually([&] { return src->latest(TimePoint{}, out) && out.force_N == 0.0; }));
  EXPECT_EQ(src->stats().accepted, 3U);
  EXPECT_EQ(src->stats().dropped(), 0U);
  // Two values are neither a force nor a vector nor a wrench.
  robot.send(sensor_message("FT", {0.1, 0.2}, 4));
  ASSERT_TRUE(eventually([&] { return src->stats().of(DropReason::length) == 1U; }));
  EXPECT_TRUE(eventually([&] {
    return has_event(*src, "SENSOR from 'FT' with 2 values dropped", "send 1 (the normal force), 3");
  }));
}

TEST(IgtlField, UnitPrefixesAreConvertedAndOtherUnitsRefusedWithTheFix) {
  auto src = open_stream("igtl-listen://127.0.0.1:0");
  Robot robot(*src);
  ASSERT_TRUE(robot.connected());
  SlaveSample out;
  robot.send(sensor_message("ContactForce", {750.0}, 1, igtl::Unit::SI_PREFIX_MILLI));
  ASSERT_TRUE(wait_for_force_near(*src, 0.75, out));
  robot.send(sensor_message("ContactForce", {0.0005}, 2, igtl::Unit::SI_PREFIX_KILO));
  ASSERT_TRUE(wait_for_force_near(*src, 0.5, out));
  robot.send(sensor_message("ContactForce", {0.3}, 3, igtl::Unit::SI_PREFIX_NONE, false));  // no unit
  ASSERT_TRUE(eventually([&] { return src->stats().of(DropReason::unit) == 1U; }));
  EXPECT_TRUE(eventually([&] { return has_event(*src, "its unit is not a force", "send newtons"); }));
}

// TDATA and QTDATA: the tool taken by name, every element's name listed when it is missing.
TEST(IgtlField, TrackingDataGivesThePoseOfTheNamedTool) {
  auto src = open_stream("igtl-listen://127.0.0.1:0?pose_device=Tracker&pose_tool=Probe");
  Robot robot(*src);
  ASSERT_TRUE(robot.connected());
  const auto tdata = [](const char* second, float z_mm, std::uint32_t ms) {
    auto m = igtl::TrackingDataMessage::New();
    m->SetDeviceName("Tracker");
    auto reference = igtl::TrackingDataElement::New();
    reference->SetName("Reference");
    reference->SetPosition(100.0F, 100.0F, 100.0F);
    m->AddTrackingDataElement(reference);
    auto probe = igtl::TrackingDataElement::New();
    probe->SetName(second);
    probe->SetPosition(4.0F, -3.0F, z_mm);
    m->AddTrackingDataElement(probe);
    auto ts = stamp_at(ms);
    m->SetTimeStamp(ts);
    m->Pack();
    return igtl::MessageBase::Pointer(m.GetPointer());
  };
  SlaveSample out;
  robot.send(tdata("Probe", -2.0F, 1));
  robot.send(sensor_message("ContactForce", {0.6}, 1));
  ASSERT_TRUE(wait_for_force(*src, 0.6, out));
  EXPECT_NEAR(out.contact_x_m, 0.004, 1e-7);
  EXPECT_NEAR(out.contact_y_m, -0.003, 1e-7);
  EXPECT_NEAR(out.indentation_m, 0.002, 1e-7);
  // QTDATA from the same tracker.
  auto q = igtl::QuaternionTrackingDataMessage::New();
  q->SetDeviceName("Tracker");
  auto probe = igtl::QuaternionTrackingDataElement::New();
  probe->SetName("Probe");
  probe->SetPosition(-1.0F, 2.0F, -3.0F);
  probe->SetQuaternion(0.0F, 0.0F, 0.0F, 1.0F);
  q->AddQuaternionTrackingDataElement(probe);
  auto ts = stamp_at(2);
  q->SetTimeStamp(ts);
  q->Pack();
  robot.send(igtl::MessageBase::Pointer(q.GetPointer()));
  robot.send(sensor_message("ContactForce", {0.7}, 2));
  ASSERT_TRUE(wait_for_force(*src, 0.7, out));
  EXPECT_NEAR(out.contact_x_m, -0.001, 1e-7);
  EXPECT_NEAR(out.indentation_m, 0.003, 1e-7);
  EXPECT_EQ(src->stats().poses, 2U);
  // A tracker that does not carry the tool.
  robot.send(tdata("Needle", -1.0F, 3));
  ASSERT_TRUE(eventually([&] { return src->stats().of(DropReason::device) == 1U; }));
  EXPECT_TRUE(eventually(
      [&] { return has_event(*src, "TDATA from 'Tracker' has no tool 'Probe'", "'Reference', 'Needle'"); }));
}

// A pose in the robot's frame: rotated, then offset by the robot's origin in the tissue frame.
TEST(IgtlField, PosesAreMappedFromTheRobotsFrame) {
  SourceOptions o;
  o.robot_to_tissue = rotation_from_rpy_deg(0.0, 0.0, 90.0);  // robot +x is tissue +y
  o.robot_origin_m = {0.001, 0.0, 0.005};                     // the robot's origin 5 mm above the surface
  auto src = open_stream("igtl-listen://127.0.0.1:0", o);
  Robot robot(*src);
  ASSERT_TRUE(robot.connected());
  robot.send(transform_message(3.0F, 0.0F, -7.0F, 1));
  robot.send(force_message(0.3, 1));
  SlaveSample out;
  ASSERT_TRUE(wait_for_force(*src, 0.3, out));
  EXPECT_NEAR(out.contact_x_m, 0.001, 1e-7);
  EXPECT_NEAR(out.contact_y_m, 0.003, 1e-7);
  EXPECT_NEAR(out.indentation_m, 0.002, 1e-7);  // 7 mm below the robot's origin, 2 mm below the surface
}

// igtl:// to a port where nothing listens: reported at once with the OS's reason, retried.
TEST(IgtlField, ARefusedConnectionIsReportedAtOnceAndRetried) {
  std::uint16_t port = 0;
  {
    LoopbackServer closed(false);  // a free port, closed again before the source connects
    port = closed.port();
  }
  SourceOptions o;
  o.reconnect_min_s = 0.01;
  o.reconnect_max_s = 0.02;
  auto src = open_stream("igtl://127.0.0.1:" + std::to_string(port), o);
  ASSERT_TRUE(eventually([&] { return src->stats().connect_failures >= 3U; }));
  EXPECT_TRUE(eventually([&] { return has_event(*src, "cannot connect: Connection refused", "retrying"); }));
  EXPECT_EQ(src->event_count(), 1U);  // once, not once per attempt
  EXPECT_NE(src->last_warning().find("Connection refused"), std::string::npos);
}

// The local address of a socket bound to port, from /proc/net/{tcp,udp}: "0100007F" is 127.0.0.1.
std::string proc_local_address(const char* table, std::uint16_t port) {
  std::FILE* f = std::fopen(table, "r");
  if (f == nullptr) {
    return "unreadable";
  }
  std::array<char, 512> line{};
  char port_hex[8];
  (void)std::snprintf(port_hex, sizeof port_hex, ":%04X ", port);
  std::string found = "absent";
  while (std::fgets(line.data(), static_cast<int>(line.size()), f) != nullptr) {
    const std::string text(line.data());
    const auto colon = text.find(port_hex);
    if (colon != std::string::npos && colon > 8 && text.find(':') < colon) {
      found = text.substr(colon - 8, 8);
      break;
    }
  }
  (void)std::fclose(f);
  return found;
}

TEST(Sources, ListeningSocketsBindLoopbackUnlessAnAddressIsGiven) {
  auto igtl = open_stream("igtl-listen://:0");
  EXPECT_EQ(proc_local_address("/proc/net/tcp", igtl->local_port()), "0100007F");
  auto udp = open_stream("udp://:0");
  EXPECT_EQ(proc_local_address("/proc/net/udp", udp->local_port()), "0100007F");
  auto client = igtl::ClientSocket::New();
  ASSERT_EQ(client->ConnectToServer("127.0.0.1", igtl->local_port()), 0);
  client->CloseSocket();
  auto v6 = open_stream("igtl-listen://[::1]:0");
  EXPECT_NE(v6->local_port(), 0);
}

}  // namespace
}  // namespace mrskin::bridge
