// Issue 6's promises that need more than the happy path: every injected fault leads to the
// right state and counters and then recovers; reconnect backs off and refuses another unit;
// every timeout follows the time scale; a lost state request is repeated; a second process is
// refused naming the owner; current and slew limits; the versioned calibration.
#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include "mrskin/driver/device.hpp"
#include "mrskin/protocol/messages.hpp"
#include "mrskin/sim/open_mock.hpp"
#include "rig.hpp"

namespace mrskin {
namespace {

namespace proto = mrskin::protocol;
using test::Rig;

// Between the session and the mock's transport: pulls the cable, mutes the device, eats
// chosen state requests, and records what the session sends.
class TestLink final : public Transport {
 public:
  TestLink(std::unique_ptr<Transport> inner, const Clock& clock) : inner_(std::move(inner)), clock_(clock) {}
  ResultCode send(std::span<const std::uint8_t> bytes) noexcept override {
    if (down) {
      return ResultCode::disconnected;
    }
    const auto type = static_cast<proto::MessageType>(bytes.size() > 1 ? bytes[1] : 0);
    if (type == proto::MessageType::identify_request && identify_times.size() < identify_times.capacity()) {
      identify_times.push_back(clock_.now());  // capacity reserved by the test: no allocation here
    }
    heartbeats += type == proto::MessageType::heartbeat ? 1U : 0U;
    if (type == proto::MessageType::state_request && drop_state_requests > 0) {
      --drop_state_requests;
      return ResultCode::ok;  // lost on the way
    }
    return mute ? ResultCode::ok : inner_->send(bytes);
  }
  ResultCode receive(Datagram& out) noexcept override {
    if (down) {
      return ResultCode::disconnected;
    }
    if (mute) {
      while (inner_->receive(out) == ResultCode::ok) {
      }
      return ResultCode::would_block;
    }
    return inner_->receive(out);
  }
  [[nodiscard]] TransportState state() const noexcept override {
    return down ? TransportState::disconnected : TransportState::open;
  }
  [[nodiscard]] std::string_view uri() const noexcept override { return "test://"; }
  void replace_device(std::unique_ptr<Transport> inner) { inner_ = std::move(inner); }

  bool down = false;
  bool mute = false;
  int drop_state_requests = 0;
  std::vector<TimePoint> identify_times;
  std::uint64_t heartbeats = 0;

 private:
  std::unique_ptr<Transport> inner_;
  const Clock& clock_;
};

// A session on a TestLink to a synchronous mock, at a time scale.
struct LinkRig {
  explicit LinkRig(double time_scale, std::uint32_t serial = 0x4D520001) {
    sim::MockOptions mock_options;
    mock_options.time_scale = time_scale;
    mock_options.serial = serial;
    mock = sim::MockDevice::make(mock_options);
    auto owned = std::make_unique<TestLink>(mock->connect(true, &clock), clock);
    link = owned.get();
    link->identify_times.reserve(1000);
    SessionOptions options;
    options.time_scale = time_scale;
    session = std::make_unique<DeviceSession>(std::move(owned), clock, options);
  }
  void run(int ms) {
    for (int k = 0; k < ms; ++k) {
      mock->step(clock.now());
      if (other) {
        other->step(clock.now());
      }
      last = session->poll(clock.now());
      clock.advance(std::chrono::milliseconds(1));
    }
  }
  SimulatedClock clock;
  std::shared_ptr<sim::MockDevice> mock;
  std::shared_ptr<sim::MockDevice> other;
  TestLink* link = nullptr;
  std::unique_ptr<DeviceSession> session;
  ResultCode last = ResultCode::ok;
};

double ms(Duration d) { return to_seconds(d) * 1e3; }

class TimeScale : public testing::TestWithParam<double> {};

TEST_P(TimeScale, ScalesHeartbeatTelemetryTimeoutAndReconnectBackoff) {
  const double s = GetParam();
  LinkRig rig(s);
  // Heartbeat period 20 ms x s.
  const std::uint64_t before = rig.link->heartbeats;
  rig.run(static_cast<int>(1000 * s));
  EXPECT_NEAR(static_cast<double>(rig.link->heartbeats - before), 50.0, 1.0);
  // Telemetry timeout 50 ms x s.
  rig.link->mute = true;
  rig.run(static_cast<int>(40 * s));
  EXPECT_EQ(rig.session->counters().telemetry_timeouts, 0U);
  rig.run(static_cast<int>(20 * s));
  EXPECT_EQ(rig.session->counters().telemetry_timeouts, 1U);
  rig.link->mute = false;
  rig.run(10);

  // Unplugged, then plugged into a unit that does not answer yet: identify requests back off
  // from 10 ms x s, doubling, to 1 s x s.
  rig.link->down = true;
  rig.run(5);
  EXPECT_EQ(rig.last, ResultCode::disconnected);
  EXPECT_EQ(rig.session->counters().disconnects, 1U);
  rig.link->down = false;
  rig.link->mute = true;
  rig.link->identify_times.clear();
  rig.run(static_cast<int>(4500 * s));
  const std::vector<TimePoint>& t = rig.link->identify_times;
  ASSERT_GE(t.size(), 9U);
  for (std::size_t k = 0; k + 1 < t.size(); ++k) {
    const double expected_ms =
        std::min(10.0 * static_cast<double>(1U << std::min<std::size_t>(k, 20)), 1000.0) * s;
    EXPECT_NEAR(ms(t[k + 1] - t[k]), expected_ms, 1.0) << "interval " << k;
  }
  EXPECT_EQ(rig.last, ResultCode::disconnected);
  // The unit answers: back within one capped backoff, and the configuration is kept.
  rig.link->mute = false;
  rig.run(static_cast<int>(1100 * s));
  EXPECT_TRUE(rig.session->connected());
  EXPECT_EQ(rig.session->counters().reconnects, 1U);
  EXPECT_EQ(rig.session->info().serial, 0x4D520001U);
  ASSERT_NE(rig.session->profile(), nullptr);
}

TEST_P(TimeScale, ScalesTheHandshakeTimeout) {
  class Silent final : public Transport {
   public:
    ResultCode send(std::span<const std::uint8_t> /*b*/) noexcept override { return ResultCode::ok; }
    ResultCode receive(Datagram& /*d*/) noexcept override { return ResultCode::would_block; }
    [[nodiscard]] TransportState state() const noexcept override { return TransportState::open; }
    [[nodiscard]] std::string_view uri() const noexcept override { return "silent://"; }
  };
  SimulatedClock clock;
  SessionOptions options;
  options.time_scale = GetParam();
  try {
    DeviceSession session(std::make_unique<Silent>(), clock, options);
    FAIL() << "a silent device passed the handshake";
  } catch (const Timeout& e) {
    EXPECT_NE(std::string(e.what()).find("raise the time scale"), std::string::npos) << e.what();
  }
  EXPECT_NEAR(ms(clock.now()), 500.0 * GetParam(), 1.0);
}

INSTANTIATE_TEST_SUITE_P(Driver, TimeScale, testing::Values(1.0, 4.0));

TEST(Reconnect, AnotherUnitOnThePortIsRefused) {
  LinkRig rig(1.0);
  rig.run(50);
  rig.link->down = true;
  rig.run(5);
  sim::MockOptions other_options;
  other_options.serial = 0x4D520002;
  rig.other = sim::MockDevice::make(other_options, "fingertip-16x16");
  rig.link->replace_device(rig.other->connect(true, &rig.clock));
  rig.link->down = false;
  rig.run(500);
  EXPECT_EQ(rig.session->counters().identity_changes, 1U);
  EXPECT_EQ(rig.session->counters().reconnects, 0U);
  EXPECT_FALSE(rig.session->connected());
  EXPECT_EQ(rig.last, ResultCode::disconnected);
  EXPECT_EQ(rig.session->info().rows, 5);  // still the first unit's description
}

TEST(StateRequests, ALostEnableIsSentAgain) {
  LinkRig rig(1.0);
  rig.run(20);
  rig.link->drop_state_requests = 1;
  ASSERT_EQ(rig.session->request_enable(), ResultCode::ok);
  rig.run(200);
  EXPECT_EQ(rig.session->state(), DeviceState::enabled);
  EXPECT_EQ(rig.session->counters().state_retries, 1U);
  // A request the device answers is not repeated.
  ASSERT_EQ(rig.session->request_disable(), ResultCode::ok);
  rig.run(200);
  EXPECT_EQ(rig.session->state(), DeviceState::disabled);
  EXPECT_EQ(rig.session->counters().state_retries, 1U);
}

// Link and sensor faults on an ENABLED unit: the right counters move, the unit stays ENABLED
// with the host's currents applied, and no fault is latched.
struct LinkFault {
  const char* faults;
  // The mock's injection counter and the session's counter that must show it (null: none).
  std::uint64_t sim::MockDevice::FaultCounters::*injected = nullptr;
  std::uint64_t injected_min = 0;
  std::uint64_t SessionCounters::*seen = nullptr;
  std::uint64_t seen_min = 0;
  void (*check)(const DeviceSession& session) = nullptr;  // anything else
};

class EnabledUnderFault : public testing::TestWithParam<LinkFault> {};

TEST_P(EnabledUnderFault, CountsItAndKeepsWorking) {
  const LinkFault& f = GetParam();
  Rig rig(std::string("mock://?seed=30&faults=") + f.faults);
  ASSERT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
  std::fill(rig.currents.begin(), rig.currents.end(), 0.05);
  rig.finger[3] = 1e-3;
  rig.finger[4] = 1e-3;
  rig.run(800);
  const SessionCounters& c = rig.dev.session->counters();
  EXPECT_EQ(rig.dev.session->state(), DeviceState::enabled);
  EXPECT_EQ(rig.dev.session->fault_code(), 0);
  EXPECT_EQ(c.faults, 0U);
  EXPECT_GT(c.telemetry, 600U);
  std::vector<double> applied(rig.currents.size());
  sim::mock_of(rig.dev)->applied_currents(applied);
  EXPECT_NEAR(*std::min_element(applied.begin(), applied.end()), 0.05, 1e-6);
  if (f.injected != nullptr) {
    EXPECT_GT(sim::mock_of(rig.dev)->fault_counters().*f.injected, f.injected_min);
  }
  if (f.seen != nullptr) {
    EXPECT_GT(c.*f.seen, f.seen_min);
  }
  if (f.check != nullptr) {
    f.check(*rig.dev.session);
  }
}

using Mock = sim::MockDevice::FaultCounters;
INSTANTIATE_TEST_SUITE_P(
    Driver, EnabledUnderFault,
    testing::Values(
        LinkFault{"drop:0.1", &Mock::dropped, 100, &SessionCounters::sequence_gaps, 30},
        // An ideal link: on a bus a waiting duplicate gives its slot to the next sample.
        LinkFault{"dup:0.1&bus=none", &Mock::duplicated, 100, &SessionCounters::duplicates, 30},
        LinkFault{"corrupt:0.05", &Mock::corrupted, 50, &SessionCounters::crc_errors, 20},
        LinkFault{"reorder:0.05", &Mock::reordered, 20, &SessionCounters::sequence_gaps, 20},
        LinkFault{"delay:0.005", nullptr, 0, nullptr, 0,
                  [](const DeviceSession& s) { EXPECT_GE(s.counters().round_trip.percentile_ns(0.5), 5e6); }},
        // Sensor faults are no link faults: the unit cannot tell (docs/api.md).
        LinkFault{"stuck:3", nullptr, 0, nullptr, 0,
                  [](const DeviceSession& s) {
                    // Valve (1,2) joins both pressed cells: it would read 0.5 mm, but is frozen.
                    EXPECT_NEAR(s.sensors()[3], 0.0, 1e-5);
                    // Valve (1,4) joins three fluid cells, one of them pressed 1 mm.
                    EXPECT_NEAR(s.sensors()[4], 1e-3 / 3, 1e-5);
                  }},
        LinkFault{"noisy:4", nullptr, 0, &SessionCounters::telemetry, 600, [](const DeviceSession& s) {
                    EXPECT_EQ(s.counters().decode_errors + s.counters().sequence_gaps, 0U);
                  }}));

TEST(Faults, OverheatedCoilRefusesEnableUntilItHasCooled) {
  Rig rig("mock://?seed=11&faults=overheat:2+6");  // 10 W into coil 2 for the first 6 s
  ASSERT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
  std::fill(rig.currents.begin(), rig.currents.end(), 0.08);
  bool saw_derated = false;
  while (rig.dev.session->state() != DeviceState::fault && to_seconds(rig.clock.now()) < 6.0) {
    rig.run(10);
    saw_derated = saw_derated || rig.dev.session->derated();
  }
  ASSERT_EQ(rig.dev.session->state(), DeviceState::fault);
  EXPECT_TRUE(saw_derated);
  EXPECT_STREQ(fault_name(rig.dev.session->fault_code()), "coil overtemperature");
  // Still too hot: the enable is refused and the fault stays latched.
  ASSERT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
  rig.run(100);
  EXPECT_EQ(rig.dev.session->state(), DeviceState::fault);
  EXPECT_GE(sim::mock_of(rig.dev)->max_coil_temperature_C(), 100.0);
  // Heat off at 6 s; the coil cools (10 s time constant) below the derating knee by ~11 s.
  rig.run(static_cast<int>((12.0 - to_seconds(rig.clock.now())) * 1000.0));
  EXPECT_LT(sim::mock_of(rig.dev)->max_coil_temperature_C(), 80.0);
  ASSERT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
  rig.run(50);
  EXPECT_EQ(rig.dev.session->state(), DeviceState::enabled);
  EXPECT_FALSE(rig.dev.session->derated());
  std::vector<double> applied(rig.currents.size());
  sim::mock_of(rig.dev)->applied_currents(applied);
  EXPECT_NEAR(applied[2], 0.08, 1e-6);
}

TEST(Limits, CurrentsAreBoundedAndSlewLimited) {
  Rig rig("mock://?seed=31");
  const double max_A = rig.dev.session->info().max_current_A;
  const double lsb_A = rig.dev.session->info().current_lsb_A;
  ASSERT_EQ(rig.dev.session->request_enable(), ResultCode::ok);
  rig.run(5);
  // The host refuses above the device's maximum.
  std::vector<double> over(rig.currents.size(), max_A + lsb_A);
  EXPECT_EQ(rig.dev.session->send_valve_currents(over), ResultCode::invalid_value);
  // A full-scale step takes the driver's slew time (2.5 ms by default).
  std::fill(rig.currents.begin(), rig.currents.end(), max_A);
  std::vector<double> applied(rig.currents.size());
  double previous = 0.0;
  double largest_step = 0.0;
  for (int k = 0; k < 6; ++k) {
    rig.run(1);
    sim::mock_of(rig.dev)->applied_currents(applied);
    largest_step = std::max(largest_step, applied[0] - previous);
    previous = applied[0];
  }
  EXPECT_NEAR(largest_step, max_A * 1e-3 / 2.5e-3, 1e-9);
  EXPECT_NEAR(previous, max_A, 1e-12);
}

TEST(Calibration, WritesAreVersionedAndRefusedWhileEnabled) {
  Rig rig("mock://?seed=32");
  DeviceSession& session = *rig.dev.session;
  const std::string v2 =
      "# mrskin calibration\nversion = 2\nvalve_yield_gain = 1.04\n" + std::string(100, '#') + "\n";
  session.write_calibration(v2);  // three chunks
  EXPECT_EQ(session.info().calibration, v2);
  // Not above the stored version: refused, the stored one stays.
  try {
    session.write_calibration("version = 2\n");
    FAIL() << "a calibration of the same version was taken";
  } catch (const InvalidArgument& e) {
    EXPECT_NE(std::string(e.what()).find("version"), std::string::npos) << e.what();
  }
  EXPECT_THROW(session.write_calibration("no version line\n"), InvalidArgument);
  EXPECT_THROW(session.write_calibration(std::string(5000, 'x')), InvalidArgument);
  // Never while the coils may carry current.
  ASSERT_EQ(session.request_enable(), ResultCode::ok);
  rig.run(10);
  try {
    session.write_calibration("version = 3\n");
    FAIL() << "an ENABLED unit took a calibration";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("disable it"), std::string::npos) << e.what();
  }
  ASSERT_EQ(session.request_disable(), ResultCode::ok);
  rig.run(10);
  session.write_calibration("version = 3\n");
  EXPECT_EQ(session.info().calibration, "version = 3\n");
}

TEST(Ownership, ASecondProcessIsRefusedNamingTheOwner) {
  // A unit of our own (serial = this test's PID): the lock is per unit, whether or not it is attached.
  char serial[9];
  std::snprintf(serial, sizeof serial, "%08X", static_cast<unsigned>(::getpid()));
  const std::string uri = std::string("hid://1209:4d52?serial=") + serial;
  int to_parent[2];
  int to_child[2];
  ASSERT_EQ(::pipe(to_parent), 0);
  ASSERT_EQ(::pipe(to_child), 0);
  const pid_t child = ::fork();
  ASSERT_GE(child, 0);
  if (child == 0) {
    // The owner: take the lock, say so, wait for the word, exit (releasing it).
    char c = '0';
    try {
      const DeviceLock lock(uri);
      c = '1';
      const ssize_t said = ::write(to_parent[1], &c, 1);
      (void)said;
      const ssize_t heard = ::read(to_child[0], &c, 1);
      (void)heard;
    } catch (...) {
      const ssize_t said = ::write(to_parent[1], &c, 1);
      (void)said;
    }
    ::_exit(0);
  }
  char c = 0;
  ASSERT_EQ(::read(to_parent[0], &c, 1), 1);
  ASSERT_EQ(c, '1');
  std::string path;
  try {
    const DeviceLock second(uri);
    ADD_FAILURE() << "a second process took the lock";
  } catch (const DeviceBusy& e) {
    EXPECT_NE(std::string(e.what()).find("owned by process " + std::to_string(child)), std::string::npos)
        << e.what();
  }
  ASSERT_EQ(::write(to_child[1], "x", 1), 1);
  int status = 0;
  ASSERT_EQ(::waitpid(child, &status, 0), child);
  for (const int fd : {to_parent[0], to_parent[1], to_child[0], to_child[1]}) {
    ::close(fd);
  }
  {
    const DeviceLock again(uri);  // the owner is gone: free
    path = again.path();
  }
  std::remove(path.c_str());
}

}  // namespace
}  // namespace mrskin
