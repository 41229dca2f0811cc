// Inside the VM: the can:// transport against a simulated node (the mock firmware behind a
// device-role CAN transport) on vcan0, classic CAN and CAN FD. candump records the bus and
// every recorded frame is checked against protocol v1; cansend injects malformed and foreign
// frames, which the session survives. Needs vcan0 up with MTU 72 (guest-tests.sh).
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <fstream>
#include <map>
#include <numeric>
#include <optional>
#include <set>
#include <span>
#include <sstream>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include "mrskin/driver/device.hpp"
#include "mrskin/protocol/bus_budget.hpp"
#include "mrskin/protocol/can.hpp"
#include "mrskin/protocol/packed_report.hpp"
#include "vm_support.hpp"

namespace mrskin::vmtest {
namespace {

namespace proto = mrskin::protocol;

constexpr std::uint8_t kNode = 3;
constexpr std::uint32_t kMarkerId = 0x7F0;  // function 7: not protocol v1, the recorder's marker

struct LoggedFrame {
  std::string text;  // as candump wrote it: ID#DATA or ID##FDATA
  proto::CanFrame frame;
};

std::optional<std::uint8_t> hex_nibble(char c) {
  if (c >= '0' && c <= '9') {
    return static_cast<std::uint8_t>(c - '0');
  }
  if (c >= 'A' && c <= 'F') {
    return static_cast<std::uint8_t>(c - 'A' + 10);
  }
  if (c >= 'a' && c <= 'f') {
    return static_cast<std::uint8_t>(c - 'a' + 10);
  }
  return std::nullopt;
}

// One candump -L line: "(TIME) IFACE ID#DATA" or "(TIME) IFACE ID##FLAGSDATA".
std::optional<LoggedFrame> parse_line(const std::string& line) {
  std::istringstream in(line);
  std::string time, iface, text;
  if (!(in >> time >> iface >> text)) {
    return std::nullopt;
  }
  const auto hash = text.find('#');
  if (hash == std::string::npos || hash == 0 || hash > 3) {
    return std::nullopt;
  }
  LoggedFrame f;
  f.text = text;  // CAN FD: without the flags digit (the kernel adds FDF to what cansend gave)
  f.frame.id = static_cast<std::uint32_t>(std::stoul(text.substr(0, hash), nullptr, 16));
  std::size_t pos = hash + 1;
  if (pos < text.size() && text[pos] == '#') {
    f.frame.fd = true;
    f.text = text.substr(0, hash) + "##" + text.substr(std::min(text.size(), pos + 2));
    pos += 2;  // '#' and the flags digit
  }
  std::size_t n = 0;
  for (; pos + 1 < text.size() + 1 && pos < text.size(); pos += 2) {
    const auto hi = hex_nibble(text[pos]);
    const auto lo = pos + 1 < text.size() ? hex_nibble(text[pos + 1]) : std::nullopt;
    if (!hi || !lo || n >= f.frame.data.size()) {
      return std::nullopt;
    }
    f.frame.data[n++] = static_cast<std::uint8_t>((*hi << 4U) | *lo);
  }
  f.frame.length = static_cast<std::uint8_t>(n);
  return f;
}

std::vector<LoggedFrame> read_log(const std::string& path) {
  std::vector<LoggedFrame> frames;
  std::ifstream in(path);
  std::string line;
  while (std::getline(in, line)) {
    if (auto f = parse_line(line)) {
      frames.push_back(*f);
    }
  }
  return frames;
}

bool logged(const std::string& path, const std::string& text) {
  for (const LoggedFrame& f : read_log(path)) {
    if (f.text == text) {
      return true;
    }
  }
  return false;
}

// What the checker found in a recording.
struct CheckReport {
  std::size_t frames = 0;
  std::size_t protocol_frames = 0;
  std::size_t injected_seen = 0;
  std::map<std::string, std::size_t> kinds;
  std::vector<std::string> problems;
  // Classic CAN, per cyclic update: the sensor blocks after each TimeSync (the last sample, which
  // the recording's end may cut short, left out), the valve blocks of each rolling-counter value
  // (the session is closed before the recording ends: every update is whole).
  std::vector<int> sensor_blocks_per_sample;
  std::vector<int> valve_blocks_per_update;
};

// Every frame except markers and injected ones must be a protocol-v1 frame of node kNode on
// this framing with a good CRC, and its rolling counter (classic) or packet sequence (FD) must
// follow the one before it of its kind. Injected frames aimed at kNode must fail to decode.
CheckReport check_recording(const std::vector<LoggedFrame>& frames, bool fd,
                            const std::set<std::string>& injected) {
  CheckReport r;
  proto::CanDecoder decoder(kNode);
  std::map<std::string, int> last;  // rolling counter / sequence per stream
  int last_valve_block = -1;
  int timesync_counter = -1;
  int sensor_blocks = -1;  // since the last TimeSync (-1: none yet)
  int valve_counter = -1;
  int valve_blocks = 0;
  const auto problem = [&r](const LoggedFrame& f, const std::string& what) {
    if (r.problems.size() < 20) {
      r.problems.push_back(f.text + ": " + what);
    }
  };
  const auto follow = [&](const LoggedFrame& f, const std::string& stream, int value, int modulo,
                          bool may_repeat) {
    const auto it = last.find(stream);
    if (it != last.end()) {
      const int delta = ((value - it->second) % modulo + modulo) % modulo;
      if (!(delta == 1 || (may_repeat && delta == 0))) {
        problem(f, stream + " went from " + std::to_string(it->second) + " to " + std::to_string(value));
      }
    }
    last[stream] = value;
  };
  for (const LoggedFrame& f : frames) {
    ++r.frames;
    if (f.frame.id == kMarkerId) {
      continue;
    }
    if (injected.contains(f.text)) {
      ++r.injected_seen;
      if ((f.frame.id & 0xFU) == kNode && (f.frame.id >> 8U) <= 5U) {
        proto::CanDecoder fresh(kNode);
        if (fresh.decode(f.frame).error == proto::Error::ok) {
          problem(f, "an injected malformed frame decodes");
        }
      }
      continue;
    }
    ++r.protocol_frames;
    const auto function = static_cast<std::uint8_t>(f.frame.id >> 8U);
    const auto block = static_cast<std::uint8_t>((f.frame.id >> 4U) & 0xFU);
    if ((f.frame.id & 0xFU) != kNode) {
      problem(f, "not node 3");
      continue;
    }
    if (f.frame.fd != fd) {
      problem(f, fd ? "a classic frame on the CAN FD session" : "an FD frame on the classic session");
      continue;
    }
    if (!fd && (f.frame.length != 8 || function > 3)) {
      problem(f, "classic frames are 8 bytes, functions 0..3");
      continue;
    }
    if (fd && (function != 4 && function != 5)) {
      problem(f, "CAN FD packets use functions 4 and 5");
      continue;
    }
    const proto::CanDecoded d = decoder.decode(f.frame);
    if (d.error != proto::Error::ok) {
      problem(f, "does not decode: " + std::string(proto::to_string(d.error)));
      continue;
    }
    if (fd) {
      // Protocol 1.2 packs several packets in one FD frame (the telemetry with a status or an
      // echo, the currents with a heartbeat): each packet carries its own sequence.
      const std::string stream = function == 4 ? "host packets" : "device packets";
      proto::PacketWalker walk(std::span<const std::uint8_t>(f.frame.data.data(), f.frame.length));
      proto::PacketDecoded p;
      while (walk.next(p)) {
        if (p.error != proto::Error::ok) {
          problem(f, "a packed packet does not decode: " + std::string(proto::to_string(p.error)));
          break;
        }
        ++r.kinds[stream];
        follow(f, stream + " sequence", p.sequence, 256, false);
      }
      continue;
    }
    const int counter = d.counter;
    switch (static_cast<proto::CanFunction>(function)) {
      case proto::CanFunction::valve_block:
        ++r.kinds["valve block"];
        // Blocks of one update share a counter; the next update starts at a lower block.
        follow(f, "valve counter", counter, 16, block > last_valve_block);
        last_valve_block = block;
        if (counter != valve_counter) {
          if (valve_counter >= 0) {
            r.valve_blocks_per_update.push_back(valve_blocks);
          }
          valve_counter = counter;
          valve_blocks = 0;
        }
        ++valve_blocks;
        break;
      case proto::CanFunction::sensor_block:
        ++r.kinds["sensor block"];
        sensor_blocks += sensor_blocks >= 0 ? 1 : 0;
        if (counter != timesync_counter) {
          problem(f, "sensor block counter " + std::to_string(counter) + " is not its TimeSync's " +
                         std::to_string(timesync_counter));
        }
        break;
      case proto::CanFunction::cell_target:
        ++r.kinds["cell target"];
        follow(f, "cell counter", counter, 16, true);
        break;
      case proto::CanFunction::management:
        switch (static_cast<proto::CanManagement>(block)) {
          case proto::CanManagement::heartbeat:
            ++r.kinds["heartbeat"];
            follow(f, "heartbeat counter", counter, 16, false);
            break;
          case proto::CanManagement::status:
            ++r.kinds["status"];
            follow(f, "status counter", counter, 16, false);
            break;
          case proto::CanManagement::time_sync:
            ++r.kinds["time sync"];
            follow(f, "sample counter", counter, 16, false);
            timesync_counter = counter;
            if (sensor_blocks >= 0) {
              r.sensor_blocks_per_sample.push_back(sensor_blocks);
            }
            sensor_blocks = 0;
            break;
          case proto::CanManagement::state_request:
            ++r.kinds["state request"];
            follow(f, "state request counter", counter, 16, false);
            break;
          case proto::CanManagement::segmented_host_to_device:
            ++r.kinds["segmented host->device"];
            break;
          case proto::CanManagement::segmented_device_to_host:
            ++r.kinds["segmented device->host"];
            break;
          default:
            problem(f, "unknown management block");
        }
        break;
      default:
        problem(f, "unknown function");
    }
  }
  if (valve_counter >= 0) {
    r.valve_blocks_per_update.push_back(valve_blocks);
  }
  return r;
}

// The framing and the host's protocol minor version (1.2: packed FD frames, classic delta blocks).
struct CanVmCase {
  bool fd = false;
  std::uint8_t host_minor = proto::kVersionMinor;
};

class CanVm : public ::testing::TestWithParam<CanVmCase> {};

TEST_P(CanVm, SessionOnVcanIsRecordedFrameByFrameAndSurvivesInjectedFrames) {
  const bool fd = GetParam().fd;
  const std::uint8_t host_minor = GetParam().host_minor;
  const std::string uri = std::string("can://vcan0?node=3") + (fd ? "&fd=1" : "");
  // Recorded to the guest's tmpfs (a 9p write per line would make candump drop frames),
  // with a large receive buffer; copied to the output folder afterwards.
  const std::string name = std::string(fd ? "candump-fd" : "candump-classic") +
                           (host_minor < 2 ? "-1." + std::to_string(host_minor) : "") + ".log";
  const std::string log = "/tmp/" + name;

  // The recorder, ready once it has logged a marker frame.
  Child candump({"stdbuf", "-oL", "candump", "-L", "-r", "8388608", "vcan0"}, log);
  bool ready = false;
  for (int i = 0; i < 200 && !ready; ++i) {
    ASSERT_EQ(run_command("cansend vcan0 7F0#00"), 0);
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    ready = logged(log, "7F0#00");
  }
  ASSERT_TRUE(ready) << "candump recorded nothing";

  MonotonicClock clock;
  auto mock = start_mock(clock);
  auto node = std::make_unique<CanNode>(mock, uri);
  OpenOptions open;
  open.session.protocol_minor = host_minor;
  auto opened = open_device(uri, clock, open);
  DeviceSession& session = *opened.session;

  // Handshake (identity and profile over the bus), enable, currents the plant's coils follow,
  // telemetry.
  expect_session_runs(session, *mock, clock);
  std::array<proto::CellTarget, 2> targets{};
  targets[0] = {100, 50, 500, 20};
  targets[1] = {200, 60, 600, 20};
  EXPECT_EQ(session.send_cell_targets(0, targets), ResultCode::ok);
  (void)poll_until(
      session, clock, [&] { return false; }, 0.2);

  // Malformed and foreign frames while the session runs.
  const std::vector<std::string> inject =
      fd ? std::vector<std::string>{"513##00112233",          // short packet
                                    "513##FFFFFFFFFFFFFFFF",  // bad CRC
                                    "515##0011223344556677",  // node 5
                                    "513#0102030405060708",   // classic on fd id
                                    "7A3#DEADBEEF"}
         : std::vector<std::string>{"013#0000000000000000",  // bad CRC
                                    "213#0102",              // short block
                                    "015#0102030405060708",  // node 5
                                    "213#FFFFFFFFFFFFFFFF",  // bad CRC
                                    "7A3#DEADBEEF"};         // function 7
  const std::uint64_t connects = session.counters().disconnects;
  for (const std::string& frame : inject) {
    // cansend takes CAN FD frames as ID##FLAGS DATA: flags 1 = bit-rate switch.
    const auto fd_at = frame.find("##");
    const std::string arg =
        fd_at == std::string::npos ? frame : frame.substr(0, fd_at + 2) + "1" + frame.substr(fd_at + 2);
    EXPECT_EQ(run_command("cansend vcan0 '" + arg + "'"), 0) << frame;
    (void)session.poll(clock.now());
  }
  const std::uint64_t t1 = session.counters().telemetry;
  EXPECT_TRUE(poll_until(
      session, clock, [&] { return session.counters().telemetry >= t1 + 50; }, 10.0))
      << "telemetry stopped after the injected frames";
  EXPECT_EQ(session.counters().disconnects, connects);
  EXPECT_EQ(session.state(), DeviceState::enabled);
  EXPECT_TRUE(session.connected());

  ASSERT_EQ(session.request_disable(), ResultCode::ok);
  EXPECT_TRUE(poll_until(
      session, clock, [&] { return session.state() == DeviceState::disabled; }, 5.0));
  const SessionCounters c = session.counters();
  std::printf(
      "vm-can[%s]: telemetry %llu, sent %llu, received %llu, decode errors %llu, gaps %llu; "
      "node to bus %llu, from bus %llu, dropped %llu\n",
      fd ? "fd" : "classic", static_cast<unsigned long long>(c.telemetry),
      static_cast<unsigned long long>(c.sent), static_cast<unsigned long long>(c.received),
      static_cast<unsigned long long>(c.decode_errors), static_cast<unsigned long long>(c.sequence_gaps),
      static_cast<unsigned long long>(node->to_bus()), static_cast<unsigned long long>(node->from_bus()),
      static_cast<unsigned long long>(node->dropped()));
  const std::size_t valves = session.info().valves;
  const std::size_t sensors = session.info().sensors;
  opened.session.reset();
  node.reset();
  mock->stop();
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  candump.stop();
  (void)run_command("cp " + log + " " + output_dir() + "/" + name);

  const std::set<std::string> injected(inject.begin(), inject.end());
  const CheckReport r = check_recording(read_log(log), fd, injected);
  std::printf("vm-can[%s]: candump recorded %zu frames, %zu protocol frames checked, %zu injected;",
              fd ? "fd" : "classic", r.frames, r.protocol_frames, r.injected_seen);
  for (const auto& [kind, n] : r.kinds) {
    std::printf(" %s %zu,", kind.c_str(), n);
  }
  std::printf(" problems %zu\n", r.problems.size());
  for (const std::string& p : r.problems) {
    ADD_FAILURE() << p;
  }
  EXPECT_GT(r.protocol_frames, 100U);
  EXPECT_EQ(r.injected_seen, inject.size());
  if (!fd) {
    // The frames of each update against the bus budget's full update (docs/protocol.md, "Bus
    // budget"): equal in 1.1; in 1.2 (delta blocks) at most that, all of it at least once.
    proto::CyclicTraffic traffic;
    traffic.valves = valves;
    traffic.sensors = sensors;
    const proto::BusBudget budget =
        proto::compute_bus_budget(proto::default_bus_spec(proto::BusKind::can_classic), traffic);
    const int valve_budget = static_cast<int>(
        std::lround((budget.host_to_device.units_per_s - traffic.heartbeat_hz) / traffic.update_rate_hz));
    const int sensor_budget =
        static_cast<int>(std::lround((budget.device_to_host.units_per_s - traffic.status_hz) /
                                     traffic.telemetry_rate_hz)) -
        1;  // less the TimeSync
    const auto summary = [](const std::vector<int>& v) {
      const double mean =
          v.empty() ? 0.0 : std::accumulate(v.begin(), v.end(), 0.0) / static_cast<double>(v.size());
      return std::tuple(v.empty() ? 0 : *std::min_element(v.begin(), v.end()),
                        v.empty() ? 0 : *std::max_element(v.begin(), v.end()), mean, v.size());
    };
    const auto [s_min, s_max, s_mean, samples] = summary(r.sensor_blocks_per_sample);
    const auto [v_min, v_max, v_mean, updates] = summary(r.valve_blocks_per_update);
    std::printf(
        "vm-can[classic, host 1.%d]: budget per update: %d valve blocks, TimeSync + %d sensor blocks; "
        "recorded: %zu samples, sensor blocks per sample min %d max %d mean %.2f; %zu valve updates, "
        "blocks per update min %d max %d mean %.2f\n",
        host_minor, valve_budget, sensor_budget, samples, s_min, s_max, s_mean, updates, v_min, v_max,
        v_mean);
    EXPECT_GT(samples, 100U);
    EXPECT_GE(updates, 1U);  // the session sends its currents once
    EXPECT_EQ(s_max, sensor_budget);
    EXPECT_EQ(v_max, valve_budget);
    if (host_minor < 2) {
      EXPECT_EQ(s_min, sensor_budget);
      EXPECT_EQ(v_min, valve_budget);
    } else {
      EXPECT_GE(v_min, 1);  // a host's update always carries a block
    }
  }
  if (fd) {
    EXPECT_GT(r.kinds.count("device packets") != 0 ? r.kinds.at("device packets") : 0U, 50U);
    EXPECT_GT(r.kinds.count("host packets") != 0 ? r.kinds.at("host packets") : 0U, 3U);
  } else {
    for (const char* kind :
         {"valve block", "sensor block", "time sync", "status", "heartbeat", "state request", "cell target",
          "segmented host->device", "segmented device->host"}) {
      EXPECT_NE(r.kinds.count(kind), 0U) << "no " << kind << " frame recorded";
    }
  }
}

INSTANTIATE_TEST_SUITE_P(Vcan, CanVm,
                         ::testing::Values(CanVmCase{false, proto::kVersionMinor}, CanVmCase{false, 1},
                                           CanVmCase{true, proto::kVersionMinor}),
                         [](const ::testing::TestParamInfo<CanVmCase>& p) {
                           return std::string(p.param.fd ? "fd" : "classic") +
                                  (p.param.host_minor < 2 ? "_host_1_1" : "");
                         });

}  // namespace
}  // namespace mrskin::vmtest
