// The device session against the mock device's firmware, on the simulated clock.
#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <deque>
#include <fstream>
#include <functional>
#include <memory>
#include <span>
#include <sstream>
#include <string>
#include <vector>

#include "mrskin/driver/device.hpp"
#include "mrskin/protocol/packet.hpp"
#include "mrskin/protocol/units.hpp"
#include "mrskin/sim/open_mock.hpp"
#include "rig.hpp"

namespace mrskin {
namespace {

namespace proto = mrskin::protocol;

using test::Rig;

TEST(Session, HandshakeReadsIdentityProfileAndCalibration) {
  Rig rig("mock://?seed=1");
  const DeviceInfo& info = rig.dev.session->info();
  EXPECT_EQ(info.protocol_major, 1);
  EXPECT_EQ(info.rows, 5);
  EXPECT_EQ(info.cols, 5);
  EXPECT_EQ(info.fluid_cells, 13U);
  EXPECT_EQ(info.valves, 12U);
  // From the default profile's [coil]: 0.1 A in steps of 25 uA.
  EXPECT_NEAR(info.current_lsb_A, 25e-6, 1e-12);
  EXPECT_NEAR(info.max_current_A, 0.1, 1e-9);
  EXPECT_EQ(info.sensor_quantity, "displacement");
  EXPECT_EQ(info.sensor_unit, "m");
  EXPECT_NEAR(info.sensor_lsb, 2.5e-6, 1e-12);
  EXPECT_NE(info.calibration.find("version = 1"), std::string::npos) << info.calibration;
  EXPECT_NE(info.profile.find("name = \"mr-skin-5x5\""), std::string::npos) << info.profile;
  const model::DeviceProfile* profile = rig.dev.session->profile();
  ASSERT_NE(profile, nullptr);
  EXPECT_EQ(profile->name, "mr-skin-5x5");
  EXPECT_EQ(profile->rows, 5);
  EXPECT_DOUBLE_EQ(profile->coil.max_current_A, 0.1);
  // One displacement sensor under each valve cell, as the profile declares.
  EXPECT_EQ(profile->sensors.size(), 12U);
  EXPECT_EQ(info.sensors, 12U);
  rig.run(10);
  EXPECT_EQ(rig.dev.session->state(), DeviceState::disabled);
  EXPECT_GT(rig.dev.session->counters().telemetry, 5U);
}

// Answers every request with a fixed packet.
class ScriptedTransport final : public Transport {
 public:
  explicit ScriptedTransport(std::vector<std::uint8_t> reply) : reply_(std::move(reply)) {}
  ResultCode send(std::span<const std::uint8_t> /*bytes*/) noexcept override {
    Datagram d;
    std::copy(reply_.begin(), reply_.end(), d.bytes.begin());
    d.length = static_cast<std::uint16_t>(reply_.size());
    queue_.push_back(d);
    return ResultCode::ok;
  }
  ResultCode receive(Datagram& out) noexcept override {
    if (queue_.empty()) {
      return ResultCode::would_block;
    }
    out = queue_.front();
    queue_.pop_front();
    return ResultCode::ok;
  }
  [[nodiscard]] TransportState state() const noexcept override { return TransportState::open; }
  [[nodiscard]] std::string_view uri() const noexcept override { return "scripted://"; }

 private:
  std::vector<std::uint8_t> reply_;
  std::deque<Datagram> queue_;
};

TEST(Session, VersionMismatchNamesBothVersions) {
  std::vector<std::uint8_t> packet(64);
  proto::Identity id;
  id.proto_major = 2;
  id.proto_minor = 3;
  id.current_lsb_nA = 1;
  id.sensor_lsb_nano = 1;
  const auto r = proto::encode_packet(id, 0, packet);
  ASSERT_EQ(r.error, proto::Error::ok);
  packet.resize(r.bytes);
  SimulatedClock clock;
  try {
    DeviceSession session(std::make_unique<ScriptedTransport>(packet), clock);
    FAIL() << "handshake accepted protocol v2";
  } catch (const ProtocolMismatch& e) {
    EXPECT_NE(std::string(e.what()).find("v2.3"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("v1." + std::to_string(proto::kVersionMinor)), std::string::npos)
        << e.what();
  }
  // A packet whose framing itself is another major version.
  packet[0] = 7;
  try {
    DeviceSession session(std::make_unique<ScriptedTransport>(packet), clock);
    FAIL() << "handshake accepted framing v7";
  } catch (const ProtocolMismatch& e) {
    EXPECT_NE(std::string(e.what()).find("v7"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("v1"), std::string::npos) << e.what();
  }
}

// Protocol 1.1: a disabled unit with a bipolar driver degausses on request (a decaying
// alternating current, the degaussing flag while it runs) and stays disabled; a unipolar one
// ignores the request.
TEST(Session, DegaussRunsAnAlternatingDecayOnBipolarUnitsOnly) {
  for (const bool bipolar : {true, false}) {
    test::Rig rig(bipolar ? "mock://?seed=7" : "mock://?seed=7&bipolar=0");
    DeviceSession& s = *rig.dev.session;
    ASSERT_EQ(s.request_enable(), ResultCode::ok);
    std::fill(rig.currents.begin(), rig.currents.end(), s.info().max_current_A);
    rig.run(50);
    std::fill(rig.currents.begin(), rig.currents.end(), 0.0);
    rig.run(5);
    ASSERT_EQ(s.request_disable(), ResultCode::ok);
    rig.run(20);
    ASSERT_EQ(s.state(), DeviceState::disabled);
    ASSERT_EQ(s.request_degauss(), ResultCode::ok);
    bool seen = false;
    double lowest_A = 0.0;
    std::vector<double> applied(rig.currents.size());
    int ms = 0;
    for (; ms < 3000 && (ms < 300 || s.degaussing()); ++ms) {
      rig.run(1);
      seen = seen || s.degaussing();
      sim::mock_of(rig.dev)->applied_currents(applied);
      lowest_A = std::min(lowest_A, *std::min_element(applied.begin(), applied.end()));
    }
    EXPECT_EQ(seen, bipolar);
    EXPECT_FALSE(s.degaussing());
    EXPECT_EQ(s.state(), DeviceState::disabled);
    sim::mock_of(rig.dev)->applied_currents(applied);
    for (const double a : applied) {
      EXPECT_EQ(a, 0.0);
    }
    if (bipolar) {
      EXPECT_LT(lowest_A, -0.5 * s.info().max_current_A);  // the field was reversed
      EXPECT_GT(ms, 500);                                  // ~57 half-cycles of 20 ms
      EXPECT_LT(ms, 3000);
    } else {
      EXPECT_EQ(lowest_A, 0.0);
    }
  }
}

TEST(Session, HeartbeatLossLeadsToSafeStateAndEnableRecovers) {
  Rig rig("mock://?seed=2");
  ASSERT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
  std::fill(rig.currents.begin(), rig.currents.end(), 0.05);
  rig.run(50);
  EXPECT_EQ(rig.dev.session->state(), DeviceState::enabled);
  std::vector<double> applied(rig.currents.size());
  sim::mock_of(rig.dev)->applied_currents(applied);
  EXPECT_NEAR(applied[0], 0.05, 1e-4);
  rig.run(150, /*host_alive=*/false);
  sim::mock_of(rig.dev)->applied_currents(applied);
  for (const double a : applied) {
    EXPECT_EQ(a, 0.0);
  }
  rig.run(1);
  EXPECT_EQ(rig.dev.session->state(), DeviceState::fault);
  EXPECT_STREQ(fault_name(rig.dev.session->fault_code()), "heartbeat lost");
  EXPECT_EQ(rig.last, ResultCode::device_fault);
  EXPECT_EQ(rig.dev.session->counters().faults, 1U);
  EXPECT_FALSE(rig.dev.session->fault_log().empty());
  // The fault latches until an explicit enable.
  rig.run(20);
  EXPECT_EQ(rig.dev.session->state(), DeviceState::fault);
  ASSERT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
  rig.run(20);
  EXPECT_EQ(rig.dev.session->state(), DeviceState::enabled);
  EXPECT_EQ(rig.dev.session->fault_code(), 0);
}

TEST(Session, DroppedFramesAreCountedAndTheLinkKeepsWorking) {
  Rig rig("mock://?seed=3&faults=drop:0.2");
  rig.run(500);
  const auto& c = rig.dev.session->counters();
  EXPECT_GT(sim::mock_of(rig.dev)->fault_counters().dropped, 50U);
  EXPECT_GT(c.sequence_gaps, 20U);
  EXPECT_GT(c.telemetry, 300U);
}

TEST(Session, CorruptedFramesFailTheirCrc) {
  Rig rig("mock://?seed=4&faults=corrupt:0.1");
  rig.run(500);
  EXPECT_GT(sim::mock_of(rig.dev)->fault_counters().corrupted, 20U);
  EXPECT_GT(rig.dev.session->counters().decode_errors, 10U);
  EXPECT_GT(rig.dev.session->counters().crc_errors, 5U);
}

TEST(Session, DuplicatesAreDroppedAndCounted) {
  // An ideal link: on a bus a duplicated telemetry report that waits gives its slot to the next
  // sample (the bus model's drop), and the count under test is the session's.
  Rig rig("mock://?seed=5&faults=dup:0.1&bus=none");
  rig.run(500);
  EXPECT_GT(rig.dev.session->counters().duplicates, 10U);
}

TEST(Session, ReorderedFramesShowAsGaps) {
  Rig rig("mock://?seed=6&faults=reorder:0.05");
  rig.run(500);
  EXPECT_GT(sim::mock_of(rig.dev)->fault_counters().reordered, 5U);
  EXPECT_GT(rig.dev.session->counters().sequence_gaps, 5U);
}

TEST(Session, DelayShowsInTheRoundTripHistogram) {
  Rig rig("mock://?seed=7&faults=delay:0.005");
  rig.run(500);
  const auto& rtt = rig.dev.session->counters().round_trip;
  ASSERT_GT(rtt.count(), 10U);
  EXPECT_GE(rtt.percentile_ns(0.5), 5e6);
  EXPECT_LE(rtt.percentile_ns(0.5), 8e6);
}

TEST(Session, ReconnectsAfterUnplugAndKeepsItsConfiguration) {
  Rig rig("mock://?seed=8&faults=disconnect:0.2+0.1");
  ASSERT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
  rig.run(150);
  EXPECT_EQ(rig.dev.session->state(), DeviceState::enabled);
  rig.run(100);
  EXPECT_EQ(rig.last, ResultCode::disconnected);
  EXPECT_FALSE(rig.dev.session->connected());
  rig.run(300);
  const auto& c = rig.dev.session->counters();
  EXPECT_EQ(c.disconnects, 1U);
  EXPECT_EQ(c.reconnects, 1U);
  EXPECT_TRUE(rig.dev.session->connected());
  EXPECT_EQ(rig.dev.session->state(), DeviceState::enabled);  // re-enabled after the reboot
}

TEST(Session, StuckSensorFreezesWhileTheFingerMoves) {
  // Sensors 3 and 6 sit under valves (1,2) and (2,3), both beside the centre cell (fluid cell 6)
  // and three more fluid cells: each reads a quarter of the centre's depth.
  Rig rig("mock://?seed=9&faults=stuck:6");
  rig.finger[6] = 2e-3;
  rig.run(50);
  const auto sensors = rig.dev.session->sensors();
  EXPECT_NEAR(sensors[6], 0.0, 1e-5);  // frozen at its first reading
  EXPECT_NEAR(sensors[3], 0.5e-3, 1e-5);
}

TEST(Session, NoisySensorIsNoisy) {
  Rig rig("mock://?seed=10&faults=noisy:3");
  double sum_sq_noisy = 0.0;
  double sum_sq_quiet = 0.0;
  for (int k = 0; k < 200; ++k) {
    rig.run(1);
    sum_sq_noisy += rig.dev.session->sensors()[3] * rig.dev.session->sensors()[3];
    sum_sq_quiet += rig.dev.session->sensors()[4] * rig.dev.session->sensors()[4];
  }
  EXPECT_GT(std::sqrt(sum_sq_noisy / 200), 20e-6);
  EXPECT_LT(std::sqrt(sum_sq_quiet / 200), 5e-6);
}

TEST(Session, LeakingValveHoldsLessPressure) {
  // Press the centre cell (fluid cell 6) to 2 mm with every valve at 50 mA, then hold: the
  // trapped fluid escapes through one of its valves when that valve leaks.
  auto held_force_N = [](const std::string& uri) {
    Rig rig(uri);
    EXPECT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
    std::fill(rig.currents.begin(), rig.currents.end(), 0.05);
    for (int k = 0; k < 200; ++k) {
      rig.finger[6] = 2e-3 * (k + 1) / 200.0;
      rig.run(1);
    }
    rig.run(300);
    std::vector<double> force_N(rig.finger.size());
    sim::mock_of(rig.dev)->true_contact_forces(force_N);
    return force_N[6];
  };
  std::size_t valve = 0;
  {
    const Rig probe("mock://?seed=13");  // one owner per unit: closed before the runs
    valve = sim::mock_of(probe.dev)->layout().valves_of_cell(6)[0];
  }
  const double tight_N = held_force_N("mock://?seed=13");
  const double leaky_N = held_force_N("mock://?seed=13&faults=leak:" + std::to_string(valve));
  std::printf("held force: tight %.3f N, leaking valve %zu %.3f N\n", tight_N, valve, leaky_N);
  EXPECT_GT(tight_N, 0.3);
  EXPECT_LT(leaky_N, 0.8 * tight_N);
}

TEST(Session, OverheatedCoilDeratesThenFaults) {
  Rig rig("mock://?seed=11&faults=overheat:2");
  ASSERT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
  std::fill(rig.currents.begin(), rig.currents.end(), 0.08);
  bool saw_derated = false;
  for (int k = 0; k < 60 && rig.dev.session->state() != DeviceState::fault; ++k) {
    rig.run(100);
    saw_derated = saw_derated || rig.dev.session->derated();
  }
  EXPECT_TRUE(saw_derated);
  EXPECT_EQ(rig.dev.session->state(), DeviceState::fault);
  EXPECT_STREQ(fault_name(rig.dev.session->fault_code()), "coil overtemperature");
  EXPECT_GE(sim::mock_of(rig.dev)->max_coil_temperature_C(), 100.0);
}

TEST(Session, BusOffFaultsAndEnableRecovers) {
  Rig rig("mock://?seed=12&faults=busoff:0.1");
  ASSERT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
  rig.run(300);
  EXPECT_EQ(rig.dev.session->state(), DeviceState::fault);
  EXPECT_STREQ(fault_name(rig.dev.session->fault_code()), "bus off");
  EXPECT_GT(rig.dev.session->counters().telemetry_timeouts, 0U);
  ASSERT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
  rig.run(20);
  EXPECT_EQ(rig.dev.session->state(), DeviceState::enabled);
}

TEST(Session, EstopReleasesEverythingAndLatches) {
  Rig rig("mock://?seed=13");
  ASSERT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
  std::fill(rig.currents.begin(), rig.currents.end(), 0.05);
  rig.run(20);
  ASSERT_EQ(rig.dev.session->request_estop(), ResultCode::ok);
  // On the 5x5's full-speed bus the request may wait a frame behind the tick's report, and the
  // unit's FAULT status rides in its next telemetry report, a frame later still (with
  // config_reads_beside_telemetry off the open ends at another phase of the frames: 3 ms).
  rig.run(3);
  std::vector<double> applied(rig.currents.size());
  sim::mock_of(rig.dev)->applied_currents(applied);
  for (const double a : applied) {
    EXPECT_EQ(a, 0.0);
  }
  EXPECT_EQ(rig.dev.session->state(), DeviceState::fault);
  EXPECT_STREQ(fault_name(rig.dev.session->fault_code()), "emergency stop");
}

TEST(Session, InvalidCurrentsAreRefusedAndNothingIsSent) {
  Rig rig("mock://?seed=14");
  rig.run(5);
  const auto sent = rig.dev.session->counters().sent;
  std::vector<double> bad(rig.currents.size(), 0.05);
  bad[3] = std::nan("");
  EXPECT_EQ(rig.dev.session->send_valve_currents(bad), ResultCode::invalid_value);
  bad[3] = 0.2;  // above the device's 0.1 A
  EXPECT_EQ(rig.dev.session->send_valve_currents(bad), ResultCode::invalid_value);
  bad.pop_back();
  EXPECT_EQ(rig.dev.session->send_valve_currents(bad), ResultCode::invalid_value);
  EXPECT_EQ(rig.dev.session->counters().sent, sent);
  EXPECT_EQ(rig.dev.session->counters().invalid_commands, 3U);
}

// One tick of a host that commands through send_valve_current_changes, as the bridge does; returns
// the currents packets that tick sent (read from the traffic log).
std::size_t tick_changes(Rig& rig, Duration refresh_period, std::size_t max_refresh) {
  DeviceSession& s = *rig.dev.session;
  sim::mock_of(rig.dev)->set_finger_indentation(rig.finger);
  sim::mock_of(rig.dev)->step(rig.clock.now());
  const TimePoint now = rig.clock.now();
  rig.last = s.poll(now);
  if (rig.last == ResultCode::ok) {
    rig.last = s.send_valve_current_changes(rig.currents, now, refresh_period, max_refresh);
  }
  rig.clock.advance(std::chrono::milliseconds(1));
  const std::vector<LogEntry> log = s.decode_log(s.ring_log());
  return static_cast<std::size_t>(std::count_if(log.begin(), log.end(), [&](const LogEntry& e) {
    return e.sent && e.kind == "currents" && e.host_time == now;
  }));
}

// 128 valves go in five blocks of 27: a block goes when its counts change, and each goes again once
// a refresh period, at most max_refresh a tick.
TEST(ValveCurrentChanges, OnlyChangedBlocksGoAndTheRefreshSpreadsOverTheTicks) {
  Rig rig("mock://fingertip-16x16?seed=1");
  DeviceSession& s = *rig.dev.session;
  ASSERT_EQ(s.valve_current_blocks(), 5U);
  ASSERT_EQ(s.request_enable(), ResultCode::ok);
  rig.run(50);  // send_valve_currents: every block, every tick
  ASSERT_EQ(s.state(), DeviceState::enabled);
  const Duration period = std::chrono::milliseconds(20);
  std::fill(rig.currents.begin(), rig.currents.end(), 0.02);
  EXPECT_EQ(tick_changes(rig, period, 2), 5U);  // every block changed
  std::vector<std::size_t> sent;
  for (int k = 1; k <= 45; ++k) {
    sent.push_back(tick_changes(rig, period, 2));
  }
  // Nothing for 19 ms; then the five blocks as 2, 2, 1 over three ticks, once a period.
  const std::vector<std::size_t> cycle = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 2, 2, 1};
  for (std::size_t k = 0; k < sent.size(); ++k) {
    const std::size_t want = k < 19 ? 0U : k < 22 ? cycle[k] : k >= 39 && k < 42 ? cycle[k - 20] : 0U;
    EXPECT_EQ(sent[k], want) << "tick " << k + 1;
  }
  // One valve of the second block: that block alone.
  rig.currents[30] = 0.03;
  EXPECT_EQ(tick_changes(rig, period, 2), 1U);
  // A change smaller than a count changes no count: nothing goes.
  const double lsb_A = s.info().current_lsb_A;
  rig.currents[30] = 0.03 + 0.1 * lsb_A;
  EXPECT_EQ(tick_changes(rig, period, 2), 0U);
  EXPECT_EQ(s.commanded_currents()[30], std::round(0.03 / lsb_A) * lsb_A);
  // Refused as send_valve_currents: nothing goes and the last command stands.
  rig.currents[31] = std::nan("");
  EXPECT_EQ(tick_changes(rig, period, 2), 0U);
  EXPECT_EQ(rig.last, ResultCode::invalid_value);
  rig.currents[31] = 0.02;
  tick_changes(rig, period, 2);
  tick_changes(rig, period, 2);
  const std::span<const double> unit_A = sim::mock_of(rig.dev)->commanded_currents();
  for (std::size_t v = 0; v < rig.currents.size(); ++v) {
    EXPECT_EQ(unit_A[v], s.commanded_currents()[v]) << v;
  }
}

// Frames lost on the way to the unit: only the refresh brings back what they carried, and it does
// within a few refresh periods of the last change.
TEST(ValveCurrentChanges, TheRefreshHealsLostFrames) {
  Rig rig("mock://fingertip-16x16?seed=2&faults=drop:0.2");
  DeviceSession& s = *rig.dev.session;
  ASSERT_EQ(s.request_enable(), ResultCode::ok);
  rig.run(60);
  ASSERT_EQ(s.state(), DeviceState::enabled);
  const Duration period = std::chrono::milliseconds(20);
  const auto differing = [&] {
    const std::span<const double> unit_A = sim::mock_of(rig.dev)->commanded_currents();
    std::size_t n = 0;
    for (std::size_t v = 0; v < rig.currents.size(); ++v) {
      n += unit_A[v] != s.commanded_currents()[v] ? 1U : 0U;
    }
    return n;
  };
  // New currents on every block until a change is lost (three ticks later the unit still differs).
  std::size_t lost = 0;
  for (int k = 1; k <= 200 && lost == 0; ++k) {
    for (std::size_t b = 0; b < 5; ++b) {
      rig.currents[b * 27 + static_cast<std::size_t>(k) % 27] = 0.001 * static_cast<double>(k % 40);
    }
    for (int t = 0; t < 3; ++t) {
      tick_changes(rig, period, 2);
    }
    lost = differing();
  }
  ASSERT_GT(lost, 0U);
  EXPECT_GT(sim::mock_of(rig.dev)->fault_counters().dropped, 0U);
  for (int k = 0; k < 100; ++k) {  // nothing changes: only the refresh sends
    tick_changes(rig, period, 2);
  }
  EXPECT_EQ(s.state(), DeviceState::enabled);
  EXPECT_EQ(differing(), 0U);  // the unit holds the host's currents again
}

TEST(Session, SecondOpenerIsRefusedNamingTheOwner) {
  Rig first("mock://");
  try {
    Rig second("mock://");
    FAIL() << "second opener was not refused";
  } catch (const DeviceBusy& e) {
    EXPECT_NE(std::string(e.what()).find("owned by process"), std::string::npos) << e.what();
  }
}

TEST(Session, RingLogKeepsTheLastPackets) {
  Rig rig("mock://?seed=15");
  rig.run(300);
  const auto log = rig.dev.session->ring_log();
  EXPECT_EQ(log.size(), 256U);
  EXPECT_LE(log.front().time, log.back().time);
  const std::string text = rig.dev.session->format_log(log);
  EXPECT_NE(text.find(" rx #"), std::string::npos) << text;
  EXPECT_NE(text.find("telemetry"), std::string::npos) << text;
  EXPECT_NE(text.find("heartbeat"), std::string::npos) << text;
}

TEST(RingLog, FaultReportIsDecodedIntoSiUnits) {
  SessionOptions options;
  options.ring_log_packets = 64;
  Rig rig("mock://?seed=22", options);
  DeviceSession& session = *rig.dev.session;
  EXPECT_EQ(session.fault_report(), "");
  ASSERT_EQ(session.request_enable(), ResultCode::ok);
  rig.finger[6] = 2e-3;
  std::fill(rig.currents.begin(), rig.currents.end(), 0.05);
  rig.run(30);
  ASSERT_EQ(session.request_estop(), ResultCode::ok);
  rig.run(30);
  ASSERT_EQ(session.state(), DeviceState::fault);
  const std::vector<TrafficRecord> frozen = session.fault_log();
  ASSERT_EQ(frozen.size(), 64U);
  EXPECT_EQ(session.last_fault_code(), static_cast<std::uint8_t>(proto::FaultCode::estop));
  const std::vector<LogEntry> entries = session.decode_log(frozen);
  // The frozen log ends with the FAULT status, after the e-stop request.
  EXPECT_EQ(entries.back().kind, "status");
  EXPECT_EQ(entries.back().state, "FAULT");
  EXPECT_EQ(entries.back().fault, "emergency stop");
  bool saw_currents = false;
  bool saw_telemetry = false;
  for (const LogEntry& e : entries) {
    if (e.kind == "currents") {
      saw_currents = true;
      EXPECT_EQ(e.unit, "A");
      ASSERT_EQ(e.values.size(), 12U);
      EXPECT_NEAR(e.values[0], 0.05, 1e-9);
    } else if (e.kind == "telemetry") {
      saw_telemetry = true;
      EXPECT_TRUE(e.has_device_time);
      EXPECT_EQ(e.unit, "m");
      ASSERT_EQ(e.values.size(), 12U);  // under the valves; valve 6 is beside the pressed centre
      EXPECT_NEAR(e.values[6], 2e-3 / 4, 1e-4);
    }
  }
  EXPECT_TRUE(saw_currents);
  EXPECT_TRUE(saw_telemetry);
  const std::string report = session.fault_report();
  for (const char* needle : {"fault: emergency stop at ", "last 64 packets", "tx #", "rx #", "currents",
                             "valves 0..11 [A]: 0.050000", "telemetry", "device ", "sensors 0..11 [m]:",
                             "state request e-stop", "status", "FAULT (fault: emergency stop)"}) {
    EXPECT_NE(report.find(needle), std::string::npos) << needle << "\n" << report;
  }
  // An undecodable record is shown as such, with its bytes.
  std::vector<TrafficRecord> bad(1);
  bad[0].packet.length = 3;
  bad[0].packet.bytes = {1, 2, 3};
  EXPECT_NE(session.format_log(bad).find("undecodable"), std::string::npos);
}

TEST(Session, TimeScaleStretchesTheDeviceWatchdog) {
  SessionOptions options;
  options.time_scale = 10.0;
  Rig rig("mock://?seed=16", options);
  EXPECT_NEAR(rig.dev.session->info().heartbeat_timeout_s, 1.0, 1e-9);
  ASSERT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
  rig.run(10);
  rig.run(500, /*host_alive=*/false);  // silent for 0.5 s: within the scaled 1 s
  rig.run(1);
  EXPECT_EQ(rig.dev.session->state(), DeviceState::enabled);
}

TEST(Session, TelemetryCallbackSeesEveryPacket) {
  Rig rig("mock://?seed=17");
  int calls = 0;
  rig.dev.session->set_telemetry_callback(
      [](void* ctx, const TelemetryView& view) noexcept {
        ++*static_cast<int*>(ctx);
        (void)view;
      },
      &calls);
  rig.run(100);
  EXPECT_GE(calls, 95);
}

// The callback runs inside poll() on the packet poll() is reading: a poll() from it must not
// read into that buffer. It reads nothing and says would_block; the outer poll goes on.
TEST(Session, PollFromTheTelemetryCallbackReadsNothing) {
  Rig rig("mock://?seed=18");
  struct Seen {
    DeviceSession* session = nullptr;
    TimePoint now{};
    int calls = 0;
    int refused = 0;
  } seen{rig.dev.session.get(), {}, 0, 0};
  rig.dev.session->set_telemetry_callback(
      [](void* ctx, const TelemetryView& view) noexcept {
        auto& s = *static_cast<Seen*>(ctx);
        ++s.calls;
        s.refused += s.session->poll(s.now) == ResultCode::would_block ? 1 : 0;
        (void)view;
      },
      &seen);
  rig.run(100);
  EXPECT_GE(seen.calls, 95);
  EXPECT_EQ(seen.refused, seen.calls);
  rig.dev.session->set_telemetry_callback(nullptr, nullptr);
  EXPECT_NE(rig.dev.session->poll(rig.clock.now()), ResultCode::would_block);  // outside: as ever
}

TEST(MockProfiles, GridCurrentRangeAndSensorsComeFromTheProfile) {
  struct Case {
    const char* uri;
    int rows;
    double max_current_A;
    double current_lsb_A;
    double sensor_lsb_m;
  };
  for (const Case& c : {Case{"mock://default?seed=1", 5, 0.1, 25e-6, 2.5e-6},
                        Case{"mock://mr-skin-5x5?seed=1", 5, 0.1, 25e-6, 2.5e-6},
                        Case{"mock://fingertip-16x16?seed=1", 16, 0.04, 10e-6, 0.5e-6},
                        Case{"mock://palm-64x64?seed=1", 64, 0.05, 12.5e-6, 1e-6}}) {
    SCOPED_TRACE(c.uri);
    Rig rig(c.uri);
    const DeviceInfo& info = rig.dev.session->info();
    const GridLayout layout(c.rows, c.rows);
    EXPECT_EQ(info.rows, c.rows);
    EXPECT_EQ(info.cols, c.rows);
    EXPECT_EQ(info.fluid_cells, layout.fluid_cell_count());
    EXPECT_EQ(info.valves, layout.valve_count());
    EXPECT_NEAR(info.max_current_A, c.max_current_A, 1e-12);
    EXPECT_NEAR(info.current_lsb_A, c.current_lsb_A, 1e-12);
    EXPECT_NEAR(info.sensor_lsb, c.sensor_lsb_m, 1e-12);
    ASSERT_NE(rig.dev.session->profile(), nullptr);
    EXPECT_EQ(rig.dev.session->profile()->rows, c.rows);
    EXPECT_EQ(rig.dev.session->profile()->sensors.size(), info.sensors);
    EXPECT_EQ(sim::mock_of(rig.dev)->profile().name, rig.dev.session->profile()->name);
    // Every sensor reports: telemetry covers the whole grid.
    // The last sensor sits under the last valve, which reads the mean depth of its fluid cells.
    rig.finger.back() = 1e-4;
    rig.run(20);
    const double joined = static_cast<double>(layout.cells_of_valve(layout.valve_count() - 1).size());
    EXPECT_NEAR(rig.dev.session->sensors().back(), 1e-4 / joined, 10 * c.sensor_lsb_m);
  }
}

// A fault on a sensor or valve the unit does not have is refused, naming the range (issue 25):
// the 5 x 5 has 12 sensors and 12 valves.
TEST(MockProfiles, AFaultOutsideTheUnitIsRefused) {
  SimulatedClock clock;
  for (const char* bad : {"stuck:12", "noisy:99", "offset:12", "leak:12", "overheat:1000"}) {
    try {
      (void)open_device(std::string("mock://?faults=") + bad, clock);
      ADD_FAILURE() << bad << " was accepted";
    } catch (const InvalidArgument& e) {
      EXPECT_NE(std::string(e.what()).find("(0 to 11)"), std::string::npos) << e.what();
    }
  }
  MonotonicClock real;  // the last of each opens (and identifies in real time)
  EXPECT_NO_THROW((void)open_device("mock://?faults=stuck:11,leak:11", real));
}

TEST(MockProfiles, UnknownProfileListsTheSearchPathAndTheNames) {
  SimulatedClock clock;
  try {
    (void)open_device("mock://no-such-skin", clock);
    FAIL() << "an unknown profile was accepted";
  } catch (const ProfileNotFound& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("no-such-skin"), std::string::npos) << what;
    for (const std::string& dir : model::profile_search_path()) {
      EXPECT_NE(what.find(dir), std::string::npos) << what;
    }
    for (const char* name : {"mr-skin-5x5", "fingertip-16x16", "palm-64x64"}) {
      EXPECT_NE(what.find(name), std::string::npos) << what;
    }
  }
  EXPECT_THROW((void)open_device("mock://no-such-skin", clock), InvalidArgument);  // a kind of
  EXPECT_THROW((void)open_device("mock:///nonexistent/unit.toml", clock), InvalidArgument);
  try {
    (void)sim::parse_mock_uri("mock://?rows=7");
    FAIL() << "rows= was accepted";
  } catch (const InvalidArgument& e) {
    EXPECT_NE(std::string(e.what()).find("profile"), std::string::npos) << e.what();
  }
}

// A profile written to a temporary file, opened as mock:///path.
struct TempProfile {
  explicit TempProfile(const std::string& text) {
    path = testing::TempDir() + "mrskin-test-" + std::to_string(::getpid()) + "-" +
           std::to_string(next_index()) + ".toml";
    std::ofstream(path) << text;
  }
  TempProfile(const TempProfile&) = delete;
  TempProfile& operator=(const TempProfile&) = delete;
  TempProfile(TempProfile&&) = delete;
  TempProfile& operator=(TempProfile&&) = delete;
  ~TempProfile() { std::remove(path.c_str()); }
  std::string path;
  static int next_index() {
    static int next = 0;
    return next++;
  }
};

std::string default_profile_text() { return model::load_profile_with_text("").text; }

// profile_text with its [sensors] table (up to the next table header) replaced by sensors_toml.
std::string replace_sensors_section(const std::string& profile_text, const std::string& sensors_toml) {
  std::string out;
  std::istringstream in(profile_text);
  bool skipping = false;
  for (std::string line; std::getline(in, line);) {
    if (line.starts_with("[")) {
      skipping = line.starts_with("[sensors");
    }
    if (!skipping) {
      out += line + "\n";
    }
  }
  return out + sensors_toml;
}

TEST(MockProfiles, AProfileFileWithForceSensorsAtTheFluidCellsIsStoredVerbatim) {
  const std::string text =
      replace_sensors_section(default_profile_text(),
                              "[sensors]\ngenerate = \"per_fluid_cell\"\nquantity = \"force\"\nunit = \"N\"\n"
                              "resolution = 1.0e-3\nnoise_std = 0.0\n");
  const TempProfile file(text);
  Rig rig("mock://" + file.path + "?seed=2");
  const DeviceInfo& info = rig.dev.session->info();
  EXPECT_EQ(info.profile, text);
  EXPECT_EQ(info.sensor_quantity, "force");
  EXPECT_EQ(info.sensor_unit, "N");
  EXPECT_NEAR(info.sensor_lsb, 1e-3, 1e-12);
  rig.finger[6] = 1e-3;
  rig.run(20);
  std::vector<double> truth(rig.finger.size());
  sim::mock_of(rig.dev)->true_contact_forces(truth);
  EXPECT_GT(truth[6], 0.1);
  EXPECT_NEAR(rig.dev.session->sensors()[6], truth[6], 2e-3);
}

TEST(MockProfiles, ProfilesBeyondProtocolV1AreRefusedWithTheReason) {
  SimulatedClock clock;
  std::string text = default_profile_text();
  const auto at = text.find("current_resolution_A = 25.0e-6");
  ASSERT_NE(at, std::string::npos);
  text.replace(at, std::string("current_resolution_A = 25.0e-6").size(), "current_resolution_A = 1.0e-6");
  const TempProfile file(text);
  try {
    (void)open_device("mock://" + file.path, clock);
    FAIL() << "100000 current counts were accepted";
  } catch (const InvalidArgument& e) {
    EXPECT_NE(std::string(e.what()).find("4095"), std::string::npos) << e.what();
  }
}

TEST(Session, ReadsALargeProfileOverAThreadedMockInTime) {
  MonotonicClock clock;
  OpenOptions open;
#if defined(__SANITIZE_THREAD__)
  // ThreadSanitizer runs the palm's plant 5-15 times slower: on a loaded machine its chunks
  // missed the 500 ms handshake timeout. The session's own knob for slow environments.
  open.session.time_scale = 4.0;
#endif
  OpenedDevice dev = open_device("mock://palm-64x64?seed=3", clock, open);  // the mock runs its own thread
  ASSERT_NE(dev.session->profile(), nullptr);
  const model::LoadedProfile file = model::load_profile_with_text("palm-64x64");
  EXPECT_EQ(dev.session->info().profile, file.text);
  EXPECT_EQ(dev.session->profile()->sensors.size(), dev.session->info().sensors);
}

// Packets the session sent after a point of its ring log, decoded.
std::vector<LogEntry> sent_since(const DeviceSession& session, TimePoint since) {
  std::vector<LogEntry> out;
  for (LogEntry& e : session.decode_log(session.ring_log())) {
    if (e.sent && e.host_time >= since) {
      out.push_back(std::move(e));
    }
  }
  return out;
}

TEST(Enable, ReseedsTargetsFromTheMeasuredStateAfterAFault) {
  Rig rig("mock://?seed=20");
  DeviceSession& session = *rig.dev.session;
  ASSERT_EQ(session.request_enable(), ResultCode::ok);
  rig.finger[6] = 2e-3;
  std::fill(rig.currents.begin(), rig.currents.end(), 0.05);
  rig.run(20);
  // Stale commands: a stiff spring from the surface on every cell, valid 0.5 s.
  const auto stale = proto::quantize_cell_target({1000.0, 0.0, 2.0, 0.5});
  ASSERT_EQ(stale.error, proto::Error::ok);
  const std::vector<proto::CellTarget> targets(rig.finger.size(), stale.counts);
  ASSERT_EQ(session.send_cell_targets(0, targets), ResultCode::ok);
  rig.run(20);
  EXPECT_EQ(sim::mock_of(rig.dev)->held_target(6).target, stale.counts);
  EXPECT_NEAR(sim::mock_of(rig.dev)->commanded_currents()[0], 0.05, 1e-9);

  ASSERT_EQ(session.request_estop(), ResultCode::ok);
  rig.run(5);
  ASSERT_EQ(session.state(), DeviceState::fault);
  rig.finger[6] = 3e-3;  // the finger moves while the unit is in FAULT
  rig.run(30);           // the session polls; it sends no currents in FAULT
  // The seeding rule's estimate for the centre: the non-negative fit of the 12 valve sensors
  // recovers its depth (each of its four valves reads a quarter of it).
  const double measured_m = TargetSeeder(*session.profile()).displacement_m(6, session.sensors());
  EXPECT_NEAR(measured_m, 3e-3, 2e-5);

  const TimePoint enabled_at = rig.clock.now();
  ASSERT_EQ(session.request_enable(), ResultCode::ok);
  EXPECT_EQ(session.counters().reseeds, 2U);
  // The first frames after the enable carry the re-seeded command state.
  const std::vector<LogEntry> frames = sent_since(session, enabled_at);
  ASSERT_GE(frames.size(), 4U);
  EXPECT_EQ(frames[0].kind, "state request");
  EXPECT_EQ(frames[0].state, "enable");
  EXPECT_EQ(frames[1].kind, "currents");
  for (const double a : frames[1].values) {
    EXPECT_EQ(a, 0.0);
  }
  ASSERT_EQ(frames[2].kind, "targets");
  ASSERT_EQ(frames[3].kind, "targets");
  ASSERT_EQ(frames[2].targets.size() + frames[3].targets.size(), rig.finger.size());
  const proto::CellTargetSi cell6 = frames[2].targets[6];
  EXPECT_EQ(cell6.stiffness_N_per_m, 0.0);
  EXPECT_NEAR(cell6.offset_m, measured_m, 1e-6);  // quantised to 2 um
  EXPECT_EQ(cell6.ceiling_N, 0.0);                // displacement sensors: no measured force
  EXPECT_NEAR(cell6.validity_s, 0.5, 1e-9);       // the host's validity, from now
  EXPECT_NEAR(frames[2].targets[0].offset_m, 0.0, 1e-5);
  // The session's command mirror holds the same.
  EXPECT_EQ(session.cell_targets()[6], proto::quantize_cell_target(cell6).counts);
  for (const double a : session.commanded_currents()) {
    EXPECT_EQ(a, 0.0);
  }

  // The firmware re-seeds too, and drives nothing until the host commands again.
  rig.run(1, /*host_alive=*/false);
  EXPECT_EQ(session.state(), DeviceState::fault);  // the status is not polled yet
  const sim::MockDevice::HeldTarget held = sim::mock_of(rig.dev)->held_target(6);
  EXPECT_EQ(held.target.stiffness, 0);
  EXPECT_NEAR(held.target.offset * proto::kOffsetLsb_m, measured_m, 2e-5);
  EXPECT_EQ(held.target.validity, stale.counts.validity);
  EXPECT_GE(held.validity_start, enabled_at);
  for (const double a : sim::mock_of(rig.dev)->commanded_currents()) {
    EXPECT_EQ(a, 0.0);
  }
  std::vector<double> applied(rig.currents.size());
  sim::mock_of(rig.dev)->applied_currents(applied);
  EXPECT_EQ(*std::max_element(applied.begin(), applied.end()), 0.0);
  rig.run(5);  // the host commands again
  EXPECT_EQ(session.state(), DeviceState::enabled);
  EXPECT_NEAR(sim::mock_of(rig.dev)->commanded_currents()[0], 0.05, 1e-9);
}

TEST(Enable, LeavingPauseDoesNotResumeStaleCurrents) {
  Rig rig("mock://?seed=21");
  ASSERT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
  std::fill(rig.currents.begin(), rig.currents.end(), 0.06);
  rig.run(20);
  ASSERT_EQ(rig.dev.session->request_pause(), ResultCode::ok);
  rig.run(5, /*host_alive=*/false);
  EXPECT_NEAR(sim::mock_of(rig.dev)->commanded_currents()[3], 0.06, 1e-9);  // PAUSED holds
  ASSERT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
  rig.run(1, /*host_alive=*/false);
  for (const double a : sim::mock_of(rig.dev)->commanded_currents()) {
    EXPECT_EQ(a, 0.0);
  }
}

TEST(Enable, SeederUsesTheProfilesSensors) {
  // The default profile's 12 displacement sensors under the valves, plus a force sensor on
  // the centre cell: the cells' displacements are the non-negative fit of the valve readings,
  // the centre's force is measured.
  const std::string text = default_profile_text() +
                           "\n[[sensors.sensor]]\nquantity = \"force\"\nunit = \"N\"\n"
                           "place = \"cell 2,2\"\nresolution = 1.0e-3\nnoise_std = 0.0\n";
  const model::DeviceProfile profile = model::parse_profile(text, "test");
  ASSERT_EQ(profile.sensors.size(), 13U);
  const TargetSeeder seeder(profile);
  const GridLayout layout(5, 5);
  const std::size_t centre = 6;
  ASSERT_EQ(layout.fluid_cells()[centre].row, 2);
  // A press of 2 mm on the centre and 1 mm on corner cell 0, as the valves read it.
  std::vector<double> depth(13, 0.0);
  depth[centre] = 2e-3;
  depth[0] = 1e-3;
  std::vector<double> sensors(13, 0.0);
  for (std::size_t v = 0; v < 12; ++v) {
    for (const std::size_t c : layout.cells_of_valve(v)) {
      sensors[v] += depth[c] / static_cast<double>(layout.cells_of_valve(v).size());
    }
  }
  sensors[12] = 0.75;  // N on the centre cell
  for (std::size_t c = 0; c < 13; ++c) {
    EXPECT_NEAR(seeder.displacement_m(c, sensors), depth[c], 1e-6) << c;
  }
  EXPECT_NEAR(seeder.force_N(centre, sensors), 0.75, 1e-15);
  EXPECT_EQ(seeder.force_N(0, sensors), 0.0);
  // One fit for every cell (an enable's re-seed) gives each cell what a fit of its own gives.
  seeder.fit_displacements(sensors);
  std::vector<proto::CellTarget> from_fit;
  std::vector<double> fitted;
  for (std::size_t c = 0; c < 13; ++c) {
    from_fit.push_back(seeder.seed_from_fit(c, sensors, 7));
    fitted.push_back(seeder.fitted_displacement_m(c));
  }
  for (std::size_t c = 0; c < 13; ++c) {
    const proto::CellTarget own = seeder.seed(c, sensors, 7);
    EXPECT_EQ(from_fit[c].offset, own.offset) << c;
    EXPECT_EQ(from_fit[c].ceiling, own.ceiling) << c;
    EXPECT_EQ(fitted[c], seeder.displacement_m(c, sensors)) << c;
  }
  EXPECT_EQ(seeder.fitted_displacement_m(13), 0.0);  // past the cells
  const proto::CellTarget t = seeder.seed(centre, sensors, 7);
  EXPECT_EQ(t.stiffness, 0);
  EXPECT_NEAR(t.offset, 2e-3 / proto::kOffsetLsb_m, 1.0);
  EXPECT_EQ(t.ceiling, 750);
  EXPECT_EQ(t.validity, 7);
  // Out-of-range and non-finite readings clamp into the target's fields.
  sensors[12] = std::nan("");
  std::fill(sensors.begin(), sensors.begin() + 12, 1.0);
  const proto::CellTarget c = seeder.seed(centre, sensors, 200);
  EXPECT_EQ(c.offset, proto::kOffsetCountMax);
  EXPECT_EQ(c.ceiling, 0);
  EXPECT_EQ(c.validity, proto::kValidityCountMax);
}

TEST(MockUri, BadParametersAreNamed) {
  EXPECT_THROW(sim::parse_mock_uri("mock://?faults=drop:1.5"), InvalidArgument);
  EXPECT_THROW(sim::parse_mock_uri("mock://?faults=melt:1"), InvalidArgument);
  EXPECT_THROW(sim::parse_mock_uri("mock://?seed=abc"), InvalidArgument);
  EXPECT_THROW(sim::parse_mock_uri("mock://?colour=red"), InvalidArgument);
  // Indices are sensors or valves; times are finite seconds within an hour.
  for (const char* bad :
       {"stuck:-1", "noisy:-2", "offset:-1", "leak:-1", "overheat:-1", "overheat:1+0", "disconnect:nan+1",
        "disconnect:1+inf", "disconnect:-1+1", "delay:1e9", "busoff:-0.5"}) {
    EXPECT_THROW(sim::parse_mock_uri(std::string("mock://?faults=") + bad), InvalidArgument) << bad;
  }
  EXPECT_THROW(sim::parse_mock_uri("mock://?finger="), InvalidArgument);
  EXPECT_THROW(sim::parse_mock_uri("mock://?finger=Demo!"), InvalidArgument);
  EXPECT_EQ(sim::parse_mock_uri("mock://?finger=demo").options.finger_scene, "demo");
  const sim::MockUri u =
      sim::parse_mock_uri("mock://fingertip-16x16?seed=3&faults=drop:0.1,disconnect:2+0.5,overheat:4");
  EXPECT_EQ(u.profile, "fingertip-16x16");
  const sim::MockOptions& o = u.options;
  EXPECT_EQ(o.seed, 3U);
  EXPECT_DOUBLE_EQ(o.faults.drop_probability, 0.1);
  EXPECT_DOUBLE_EQ(o.faults.disconnect_at_s, 2.0);
  EXPECT_DOUBLE_EQ(o.faults.disconnect_for_s, 0.5);
  EXPECT_EQ(o.faults.overheat_valve, 4);
  // The plant's substep (issue 21: a coarser one lets a large grid's plant keep real time).
  EXPECT_DOUBLE_EQ(sim::parse_mock_uri("mock://?physics_dt=1e-3").options.physics_dt_s, 1e-3);
  EXPECT_DOUBLE_EQ(sim::parse_mock_uri("mock://").options.physics_dt_s, 1e-4);
  for (const char* bad : {"0", "1e-6", "2e-3", "nan", "-1e-4", "x"}) {
    EXPECT_THROW(sim::parse_mock_uri(std::string("mock://?physics_dt=") + bad), InvalidArgument) << bad;
  }
}

}  // namespace
}  // namespace mrskin

namespace mrskin::test {
namespace {

// Presses the centre cell 0 -> 3 mm over 600 ms with the host sending either per-cell targets
// (300 N/m, 2 N ceiling, 0.2 s validity, every 10 ms) or nothing; returns the true force at
// the end of the press.
double press_centre(Rig& rig, bool send_targets) {
  DeviceSession& session = *rig.dev.session;
  const proto::CellTarget target{150, 0, 2000, 20};
  const std::vector<proto::CellTarget> targets(rig.finger.size(), target);
  EXPECT_EQ(session.request_enable(), ResultCode::ok);
  for (int k = 0; k < 620; ++k) {
    rig.finger[6] = 3e-3 * std::min(1.0, k / 600.0);
    sim::mock_of(rig.dev)->set_finger_indentation(rig.finger);
    sim::mock_of(rig.dev)->step(rig.clock.now());
    if (session.poll(rig.clock.now()) == ResultCode::ok && send_targets && k % 10 == 0) {
      EXPECT_EQ(session.send_cell_targets(0, targets), ResultCode::ok);
    }
    rig.clock.advance(std::chrono::milliseconds(1));
  }
  std::vector<double> truth(rig.finger.size());
  sim::mock_of(rig.dev)->true_contact_forces(truth);
  return truth[6];
}

TEST(Firmware, RendersPerCellTargetsThenReleasesWhenTheyExpire) {
  double without_N = 0.0;
  {
    Rig open_valves("mock://?seed=4");  // one owner of mock://?seed=4 at a time
    without_N = press_centre(open_valves, false);
  }
  Rig rendered("mock://?seed=4");
  const double with_targets_N = press_centre(rendered, true);
  EXPECT_TRUE(sim::mock_of(rendered.dev)->rendering_targets());
  // The centre's four valves (3, 5, 6, 8) resist: the finger feels more than the bare membrane.
  for (const std::size_t v : {3U, 5U, 6U, 8U}) {
    EXPECT_GT(sim::mock_of(rendered.dev)->commanded_currents()[v], 0.0) << v;
  }
  EXPECT_GT(with_targets_N, without_N + 0.2) << with_targets_N << " vs " << without_N;
  // The host goes quiet about targets (heartbeats continue): after the 0.2 s validity every
  // valve is released.
  for (int k = 0; k < 300; ++k) {
    sim::mock_of(rendered.dev)->step(rendered.clock.now());
    (void)rendered.dev.session->poll(rendered.clock.now());
    rendered.clock.advance(std::chrono::milliseconds(1));
  }
  for (const double a : sim::mock_of(rendered.dev)->commanded_currents()) {
    EXPECT_EQ(a, 0.0);
  }
  // Currents from the host take the coils back.
  rendered.currents.assign(rendered.currents.size(), 0.01);
  rendered.run(5);
  EXPECT_FALSE(sim::mock_of(rendered.dev)->rendering_targets());
  EXPECT_NEAR(sim::mock_of(rendered.dev)->commanded_currents()[0], 0.01, 1e-9);
}

// Issue 21: a unit whose plant runs slower than real time (fingertip-16x16's on a loaded machine)
// hears the host at its substeps' times, up to max_catch_up_s and a step's length behind the clock.
// This plant costs three times its simulated time on the clock, and the host beats every 20 ms of
// the clock meanwhile, as a session does from its own thread.
class SlowPlant final : public sim::Plant {
 public:
  SlowPlant(std::size_t sensors, SimulatedClock& clock, std::function<void()> host)
      : sensors_(sensors), clock_(clock), host_(std::move(host)) {}
  [[nodiscard]] std::size_t sensor_count() const noexcept override { return sensors_; }
  void set_valve_currents(std::span<const double> /*current_A*/) noexcept override {}
  void set_finger_indentation(std::span<const double> /*indentation_m*/) noexcept override {}
  void step(double dt_s) noexcept override {
    clock_.advance(from_seconds(3.0 * dt_s));
    host_();
  }
  void read_sensors(std::span<double> out) const noexcept override { std::fill(out.begin(), out.end(), 0.0); }
  void contact_forces(std::span<double> out_N) const noexcept override {
    std::fill(out_N.begin(), out_N.end(), 0.0);
  }

 private:
  std::size_t sensors_;
  SimulatedClock& clock_;
  std::function<void()> host_;
};

struct BehindRun {
  std::uint8_t state = 0;
  std::uint8_t fault = 0;
  double skipped_s = 0.0;
  std::uint64_t beats = 0;
  std::uint64_t host_to_device_dropped = 0;
};

// fingertip-16x16 on high-speed HID, enabled, 2 s of the clock on a SlowPlant. between_steps: the
// host also beats just before each step (the unit books that at the step's start, at now).
BehindRun run_behind(bool between_steps, double silent_from_s = 1e9) {
  const model::LoadedProfile loaded = model::load_profile_with_text("fingertip-16x16");
  sim::MockOptions options;
  options.calibration_error = -1.0;  // no network plant to measure
  options.bus.kind = sim::MockBusKind::hid_hs;
  SimulatedClock clock;
  std::unique_ptr<Transport> link;
  std::uint8_t sequence = 0;
  std::uint16_t beats = 0;
  const auto send = [&](const proto::Message& message) {
    std::array<std::uint8_t, kMaxDatagramBytes> bytes{};
    const proto::EncodeResult r = proto::encode_packet(message, sequence++, bytes);
    (void)link->send(std::span<const std::uint8_t>(bytes.data(), r.bytes));
  };
  TimePoint next_beat{0};
  const auto host = [&] {
    Datagram d;
    while (link->receive(d) == ResultCode::ok) {
    }
    if (clock.now() >= next_beat && to_seconds(clock.now()) < silent_from_s) {
      next_beat = clock.now() + std::chrono::milliseconds(20);
      send(proto::Heartbeat{beats++});
    }
  };
  auto mock = std::make_shared<sim::MockDevice>(
      loaded.profile, loaded.text, options,
      std::make_unique<SlowPlant>(loaded.profile.sensors.size(), clock, host));
  link = mock->connect(/*synchronous=*/false);
  mock->step(clock.now());
  send(proto::StateRequest{static_cast<std::uint8_t>(proto::StateRequestCode::enable)});
  clock.advance(std::chrono::milliseconds(1));
  mock->step(clock.now());
  EXPECT_EQ(mock->state(), static_cast<std::uint8_t>(proto::DeviceState::enabled));
  while (clock.now() < std::chrono::seconds(2)) {
    if (between_steps) {
      send(proto::Heartbeat{beats++});
    }
    mock->step(clock.now());
  }
  return {mock->state(), mock->fault(), mock->skipped_time_s(), beats,
          mock->bus_stats().host_to_device.dropped};
}

TEST(Firmware, AUnitBehindRealTimeKeepsItsWatchdogOnItsOwnClock) {
  const BehindRun r = run_behind(false);
  EXPECT_GT(r.skipped_s, 1.0);  // it fell behind and skipped, as the 16 x 16 does
  EXPECT_GT(r.beats, 90U);      // the host beat every 20 ms of the clock
  EXPECT_EQ(r.state, static_cast<std::uint8_t>(proto::DeviceState::enabled));
  EXPECT_EQ(r.fault, 0U);  // not heartbeat_lost
}

TEST(Firmware, AUnitBehindRealTimeStillFaultsWhenTheHostFallsSilent) {
  // The watchdog on the unit's clock must still see a host that really stopped.
  const BehindRun r = run_behind(false, 0.5);
  EXPECT_GT(r.skipped_s, 0.5);
  EXPECT_EQ(r.state, static_cast<std::uint8_t>(proto::DeviceState::fault));
  EXPECT_EQ(r.fault, static_cast<std::uint8_t>(proto::FaultCode::heartbeat_lost));
}

TEST(Firmware, AUnitBehindRealTimeDropsNoHostPacketBookedBehindAnother) {
  const BehindRun r = run_behind(true);
  EXPECT_GT(r.skipped_s, 1.0);
  EXPECT_EQ(r.host_to_device_dropped, 0U);  // a queue of one or two is never 64 deep
  EXPECT_EQ(r.state, static_cast<std::uint8_t>(proto::DeviceState::enabled));
}

// ---- protocol 1.2: packed reports, negotiated both ways --------------------------------

struct PackedRun {
  sim::MockBusStats bus;
  SessionCounters counters;
  DeviceState state = DeviceState::disabled;
  bool packed = false;
  DeviceInfo info;
};

// Enabled, valve currents every tick, `ms` on the simulated clock.
PackedRun run_enabled(const std::string& uri, SessionOptions options = {}, int ms = 1000) {
  Rig rig(uri, options);
  EXPECT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
  for (int k = 0; k < ms; ++k) {
    std::fill(rig.currents.begin(), rig.currents.end(), 0.001 * (k % 20));  // changes every tick
    rig.run(1);
  }
  return {sim::mock_of(rig.dev)->bus_stats(), rig.dev.session->counters(), rig.dev.session->state(),
          rig.dev.session->packed_reports(), rig.dev.session->info()};
}

TEST(SessionPacked, AtOnePointTwoBothWaysOneReportAFrameOnFullSpeedHid) {
  const PackedRun r = run_enabled("mock://?seed=1&bus=hid-fs");
  EXPECT_TRUE(r.packed);
  EXPECT_EQ(r.info.protocol_minor, 2);
  EXPECT_EQ(r.state, DeviceState::enabled);  // the heartbeats inside the currents' reports fed the watchdog
  const double frames = r.bus.elapsed_s / 1e-3;
  // Heartbeats rode with the currents: more packets than reports, at most one report a frame.
  EXPECT_LE(static_cast<double>(r.bus.host_to_device.carried), frames + 1.0);
  EXPECT_GE(r.bus.host_to_device.packets, r.bus.host_to_device.carried + 45U);  // 50 Hz heartbeats
  // Status and echoes rode with the telemetry.
  EXPECT_LE(static_cast<double>(r.bus.device_to_host.carried), frames + 1.0);
  EXPECT_GE(r.bus.device_to_host.packets, r.bus.device_to_host.carried + 45U);
  EXPECT_EQ(r.bus.host_to_device.dropped, 0U);
  EXPECT_EQ(r.bus.device_to_host.dropped, 0U);
  EXPECT_LE(r.bus.host_to_device.max_wait_s, 1e-3);
  EXPECT_LE(r.bus.device_to_host.max_wait_s, 1e-3);
  EXPECT_GE(r.counters.round_trip.count(), 45U);  // every echo came back inside a telemetry report
  EXPECT_GT(r.counters.sent, r.counters.reports_sent);
  EXPECT_GT(r.counters.received, r.counters.reports_received);
  EXPECT_EQ(r.counters.decode_errors, 0U);
  EXPECT_EQ(r.counters.sequence_gaps, 0U);
}

TEST(SessionPacked, AOnePointTwoHostDrivesAOnePointOneUnitAsOnePointOne) {
  const PackedRun r = run_enabled("mock://?seed=1&bus=hid-fs&protocol_minor=1");
  EXPECT_FALSE(r.packed);
  EXPECT_EQ(r.info.protocol_minor, 1);
  EXPECT_EQ(r.state, DeviceState::enabled);  // a 1.1 unit reads every heartbeat: none was packed
  EXPECT_EQ(r.bus.host_to_device.packets, r.bus.host_to_device.carried);  // one packet a report
  EXPECT_EQ(r.bus.device_to_host.packets, r.bus.device_to_host.carried);
  EXPECT_EQ(r.counters.sent, r.counters.reports_sent);
  EXPECT_EQ(r.counters.received, r.counters.reports_received);
  EXPECT_GE(r.counters.round_trip.count(), 40U);
}

TEST(SessionPacked, AOnePointOneHostSeesOnePointOneFromAOnePointTwoUnit) {
  SessionOptions host11;
  host11.protocol_minor = 1;
  const PackedRun r = run_enabled("mock://?seed=1&bus=hid-fs", host11);
  EXPECT_FALSE(r.packed);
  EXPECT_EQ(r.info.protocol_minor, 2);  // the unit speaks 1.2, but the host said 1.1
  EXPECT_EQ(r.state, DeviceState::enabled);
  EXPECT_EQ(r.bus.host_to_device.packets, r.bus.host_to_device.carried);
  EXPECT_EQ(r.bus.device_to_host.packets, r.bus.device_to_host.carried);  // the unit did not pack
  EXPECT_EQ(r.counters.received, r.counters.reports_received);
  EXPECT_EQ(r.counters.decode_errors, 0U);
}

// Packing changes no classic CAN frame: the transport splits a packed report into its packets'
// frames. A 1.2 host with a 1.1 unit sends exactly a 1.1 host's frames; with a 1.2 unit, 1.2's
// delta blocks leave out the sensor blocks a sample did not change (here every valve changes every
// tick, so every valve block goes).
TEST(SessionPacked, PackingChangesNoClassicCanFrame) {
  SessionOptions host11;
  host11.protocol_minor = 1;
  const PackedRun packed = run_enabled("mock://?seed=1&bus=can&protocol_minor=1", {}, 500);
  const PackedRun plain = run_enabled("mock://?seed=1&bus=can&protocol_minor=1", host11, 500);
  const PackedRun delta = run_enabled("mock://?seed=1&bus=can", {}, 500);
  EXPECT_FALSE(packed.packed);
  EXPECT_TRUE(delta.packed);
  for (const PackedRun* r : {&packed, &plain, &delta}) {
    EXPECT_EQ(r->state, DeviceState::enabled);
    EXPECT_EQ(r->counters.decode_errors, 0U);
    EXPECT_EQ(r->counters.sequence_gaps, 0U);
  }
  EXPECT_EQ(packed.bus.host_to_device.carried, plain.bus.host_to_device.carried);
  EXPECT_EQ(packed.bus.host_to_device.bytes, plain.bus.host_to_device.bytes);
  EXPECT_EQ(packed.bus.device_to_host.carried, plain.bus.device_to_host.carried);
  // A classic CAN unit sends no heartbeat echo (none would fit a frame; it cost a gap a heartbeat).
  EXPECT_EQ(packed.bus.device_to_host.unsent, 0U);
  EXPECT_EQ(delta.bus.device_to_host.unsent, 0U);
  EXPECT_EQ(delta.bus.host_to_device.carried, plain.bus.host_to_device.carried);
  EXPECT_LT(delta.bus.device_to_host.carried, plain.bus.device_to_host.carried);
}

// The 16x16 on its own bus (high-speed USB, bus=profile): six telemetry blocks a sample, each
// waiting for its own slot. A newer sample replaces only the same block's waiting report (it
// replaced any waiting telemetry report before, which lost five blocks in six: 299 gaps here).
TEST(SessionPacked, ALargerGridOnItsHighSpeedBusLosesNoTelemetryBlock) {
  const PackedRun r = run_enabled("mock://fingertip-16x16?seed=1&bus=profile", {}, 300);
  EXPECT_TRUE(r.packed);
  EXPECT_EQ(r.bus.kind, sim::MockBusKind::hid_hs);
  EXPECT_EQ(r.state, DeviceState::enabled);
  EXPECT_EQ(r.counters.sequence_gaps, 0U);
  EXPECT_GE(r.counters.telemetry, 6U * 290U);
  EXPECT_EQ(r.bus.device_to_host.dropped, 0U);
  EXPECT_EQ(r.bus.host_to_device.dropped, 0U);
}

// 1.2 on USB: the unit declares its reports (UsbSlots) and both sides pack up to them. A 16x16's
// sample (six Telemetry packets, 378 bytes) and its currents (five packets) each fit one of the
// high-speed unit's 1024-byte reports, where 64-byte reports take a report a packet.
TEST(SessionPacked, AHighSpeedUnitsDeclaredReportsCarryATicksPacketsInOne) {
  const PackedRun large = run_enabled("mock://fingertip-16x16?seed=1", {}, 300);
  const PackedRun small = run_enabled("mock://fingertip-16x16?seed=1&report_bytes=64", {}, 300);
  ASSERT_TRUE(large.info.usb_slots.has_value());
  EXPECT_EQ(large.info.usb_slots->report_bytes, 1024U);
  EXPECT_EQ(large.info.usb_slots->reports_per_interval, 3U);
  EXPECT_DOUBLE_EQ(large.info.usb_slots->interval_s, 125e-6);
  ASSERT_TRUE(small.info.usb_slots.has_value());
  EXPECT_EQ(small.info.usb_slots->report_bytes, 64U);
  for (const PackedRun* r : {&large, &small}) {
    EXPECT_EQ(r->state, DeviceState::enabled);
    EXPECT_EQ(r->counters.sequence_gaps, 0U);
    EXPECT_EQ(r->counters.decode_errors, 0U);
    EXPECT_GE(r->counters.telemetry, 6U * 290U);
    EXPECT_EQ(r->bus.device_to_host.dropped, 0U);
    EXPECT_EQ(r->bus.host_to_device.dropped, 0U);
  }
  // Both ways, at least three times fewer reports for the same packets.
  EXPECT_LT(3 * large.bus.host_to_device.carried, small.bus.host_to_device.carried);
  EXPECT_LT(3 * large.bus.device_to_host.carried, small.bus.device_to_host.carried);
  EXPECT_GE(large.counters.telemetry, small.counters.telemetry);
}

// A reconnect's Identity comes with the unit's UsbSlots: on a full-speed bus whose every slot
// carries a sample, packed behind it in one report, which the session reads whole (it read only
// the Identity once). The session forgets the declaration while the unit is away. On high speed
// both sides pack up to 1024 bytes again.
TEST(SessionPacked, AReconnectReadsTheDeclaredReportsPackedBehindTheIdentity) {
  for (const char* uri : {"mock://?seed=2&bus=hid-fs&faults=disconnect:0.2+0.1",
                          "mock://fingertip-16x16?seed=2&faults=disconnect:0.2+0.1"}) {
    SCOPED_TRACE(uri);
    Rig rig(uri);
    ASSERT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
    rig.run(250);
    EXPECT_FALSE(rig.dev.session->connected());
    EXPECT_FALSE(rig.dev.session->info().usb_slots.has_value());
    rig.run(300);
    const SessionCounters& c = rig.dev.session->counters();
    EXPECT_EQ(c.reconnects, 1U);
    ASSERT_TRUE(rig.dev.session->connected());
    ASSERT_TRUE(rig.dev.session->info().usb_slots.has_value());
    EXPECT_EQ(c.decode_errors, 0U);
    EXPECT_EQ(rig.dev.session->state(), DeviceState::enabled);
    if (rig.dev.session->info().usb_slots->report_bytes < 1024U) {
      continue;
    }
    // A sample's six blocks in one report, and a tick's five packets of currents in one.
    const std::uint64_t received = c.received;
    const std::uint64_t reports_received = c.reports_received;
    const std::uint64_t sent = c.sent;
    const std::uint64_t reports_sent = c.reports_sent;
    rig.run(100);
    EXPECT_GT(c.received - received, 4 * (c.reports_received - reports_received));
    EXPECT_GT(c.sent - sent, 3 * (c.reports_sent - reports_sent));
  }
}

// Protocol 1.2's SensorDeadband: a classic CAN unit declares its deadband (2 counts by default)
// to a 1.2 host and then leaves out the sensor blocks the band holds, so its frames fall below
// the TimeSync and 3 blocks of every sample; with no deadband, or to a 1.1 host (which would not
// know), every sample goes whole. The declaration is cleared while the unit is away and comes
// back with its Identity.
TEST(SessionPacked, AClassicCanUnitDeclaresItsSensorDeadbandToAOnePointTwoHostOnly) {
  const auto frames_per_ms = [](const PackedRun& r) {
    return static_cast<double>(r.bus.device_to_host.carried) / (r.bus.elapsed_s / 1e-3);
  };
  const PackedRun banded = run_enabled("mock://?seed=1&bus=can", {}, 500);
  EXPECT_EQ(banded.info.sensor_deadband_counts, 2);
  EXPECT_LT(frames_per_ms(banded), 2.5);  // at rest the band holds most blocks
  EXPECT_EQ(banded.state, DeviceState::enabled);
  const PackedRun none = run_enabled("mock://?seed=1&bus=can&deadband=0", {}, 500);
  EXPECT_EQ(none.info.sensor_deadband_counts, 0);
  EXPECT_GT(frames_per_ms(none), 3.5);
  SessionOptions v11;
  v11.protocol_minor = 1;
  const PackedRun old = run_enabled("mock://?seed=1&bus=can", v11, 500);
  EXPECT_EQ(old.info.sensor_deadband_counts, 0);
  EXPECT_GT(frames_per_ms(old), 3.9);  // every sample whole: a TimeSync and 3 blocks
  EXPECT_EQ(old.counters.decode_errors, 0U);
  // Any bus may carry it: on USB only when asked for (mock://?deadband=N).
  EXPECT_EQ(run_enabled("mock://?seed=1&bus=hid-fs", {}, 50).info.sensor_deadband_counts, 0);
  EXPECT_EQ(run_enabled("mock://?seed=1&bus=hid-fs&deadband=3", {}, 50).info.sensor_deadband_counts, 3);

  Rig rig("mock://?seed=2&bus=can&faults=disconnect:0.2+0.1");
  ASSERT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
  rig.run(250);
  EXPECT_FALSE(rig.dev.session->connected());
  EXPECT_EQ(rig.dev.session->info().sensor_deadband_counts, 0);
  rig.run(300);
  ASSERT_TRUE(rig.dev.session->connected());
  EXPECT_EQ(rig.dev.session->counters().reconnects, 1U);
  EXPECT_EQ(rig.dev.session->info().sensor_deadband_counts, 2);
}

// A full-speed unit declares full speed; a 1.1 host is sent no UsbSlots (it would not know it) and
// gets 64-byte reports from a high-speed unit.
TEST(SessionPacked, AFullSpeedUnitDeclaresFullSpeedAndAOnePointOneHostHearsNothing) {
  const PackedRun fs = run_enabled("mock://?seed=1&bus=hid-fs", {}, 100);
  ASSERT_TRUE(fs.info.usb_slots.has_value());
  EXPECT_EQ(fs.info.usb_slots->report_bytes, 64U);
  EXPECT_EQ(fs.info.usb_slots->reports_per_interval, 1U);
  EXPECT_DOUBLE_EQ(fs.info.usb_slots->interval_s, 1e-3);
  SessionOptions v11;
  v11.protocol_minor = 1;
  const PackedRun old = run_enabled("mock://fingertip-16x16?seed=1", v11, 100);
  EXPECT_FALSE(old.packed);
  EXPECT_FALSE(old.info.usb_slots.has_value());
  EXPECT_EQ(old.counters.decode_errors, 0U);
  EXPECT_EQ(old.state, DeviceState::enabled);
  // No bus, nothing declared.
  EXPECT_FALSE(run_enabled("mock://?seed=1&bus=none", {}, 50).info.usb_slots.has_value());
  // CAN units never declare USB reports.
  EXPECT_FALSE(run_enabled("mock://?seed=1&bus=canfd", {}, 50).info.usb_slots.has_value());
}

// Configuration reads beside the telemetry (an option): on full-speed USB the unit answers each
// 14-byte chunk in a sample's report; the default reads 48-byte chunks in reports of their own.
TEST(SessionPacked, ConfigurationReadsBesideTheTelemetryRideWithTheSamples) {
  SessionOptions beside;
  beside.config_reads_beside_telemetry = true;
  for (const bool ride : {true, false}) {
    MonotonicClock clock;  // a real-time unit: it streams samples while the host reads
    OpenOptions open;
    open.session = ride ? beside : SessionOptions{};
    open.session.time_scale = 10.0;  // sanitizer builds
    const OpenedDevice dev = open_device("mock://?seed=1&bus=hid-fs", clock, open);
    ASSERT_NE(dev.session->profile(), nullptr);
    EXPECT_EQ(dev.session->info().profile, model::load_profile_with_text("mr-skin-5x5").text);
    const sim::MockBusStats bus = sim::mock_of(dev)->bus_stats();
    const double chunks = static_cast<double>(dev.session->info().profile.size()) / 14.0;
    // Riding: every chunk shared a sample's report, so at least as many packets beyond the reports.
    if (ride) {
      EXPECT_GE(static_cast<double>(bus.device_to_host.packets - bus.device_to_host.carried), chunks);
    }
    EXPECT_EQ(dev.session->counters().sequence_gaps, 0U);
  }
}

TEST(SessionPacked, CanFdCarriesPackedReportsInOneFrame) {
  const PackedRun r = run_enabled("mock://?seed=1&bus=canfd", {}, 500);
  EXPECT_TRUE(r.packed);
  EXPECT_EQ(r.state, DeviceState::enabled);
  EXPECT_GE(r.bus.host_to_device.packets, r.bus.host_to_device.carried + 20U);
  EXPECT_GE(r.bus.device_to_host.packets, r.bus.device_to_host.carried + 20U);
  EXPECT_GE(r.counters.round_trip.count(), 20U);  // echoes came back inside FD frames
  EXPECT_EQ(r.counters.decode_errors, 0U);
}

TEST(SessionPacked, ALargerGridSendsWhatDoesNotFitInTheNextReport) {
  // 128 valves and sensors: five ValveCurrents and six Telemetry packets a tick, most too big to
  // share a 64-byte report (a high-speed unit that declares 64-byte reports); whatever is packed or
  // not, every packet arrives once and in order.
  const PackedRun r = run_enabled("mock://fingertip-16x16?seed=1&report_bytes=64", {}, 300);
  EXPECT_TRUE(r.packed);
  EXPECT_EQ(r.state, DeviceState::enabled);
  EXPECT_EQ(r.counters.decode_errors, 0U);
  EXPECT_EQ(r.counters.sequence_gaps, 0U);
  EXPECT_GE(r.counters.telemetry, 6U * 290U);
  EXPECT_GE(r.counters.round_trip.count(), 12U);
  EXPECT_GE(r.counters.reports_sent, 5U * 300U);  // each currents packet in a report of its own
}

TEST(SessionPacked, TheRingLogKeepsPackets) {
  Rig rig("mock://?seed=1");
  ASSERT_TRUE(rig.dev.session->packed_reports());
  ASSERT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
  rig.currents[0] = 0.01;
  rig.run(40);
  int heartbeats_sent = 0;
  int echoes = 0;
  for (const LogEntry& e : rig.dev.session->decode_log(rig.dev.session->ring_log())) {
    EXPECT_EQ(e.error, "") << e.kind;
    heartbeats_sent += e.kind == "heartbeat" && e.sent ? 1 : 0;
    echoes += e.kind == "heartbeat" && !e.sent ? 1 : 0;
  }
  EXPECT_GE(heartbeats_sent, 1);
  EXPECT_GE(echoes, 1);
}

TEST(SessionPacked, MinorVersionsAboveTheLibraryAreRefused) {
  SessionOptions future;
  future.protocol_minor = proto::kVersionMinor + 1;
  EXPECT_THROW(Rig("mock://?seed=1", future), InvalidArgument);
  EXPECT_THROW(Rig("mock://?seed=1&protocol_minor=3"), InvalidArgument);
}

}  // namespace
}  // namespace mrskin::test
