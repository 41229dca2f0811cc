// Helpers shared by the protocol tests: hex, message printing, golden messages and the
// golden vector file, and reassembly of classic CAN blocks into whole messages.
#pragma once

#include <algorithm>
#include <array>
#include <cstdint>
#include <fstream>
#include <optional>
#include <ostream>
#include <sstream>
#include <stdexcept>
#include <string>
#include <string_view>
#include <utility>
#include <variant>
#include <vector>

#include "mrskin/protocol/can.hpp"
#include "mrskin/protocol/errors.hpp"
#include "mrskin/protocol/messages.hpp"
#include "mrskin/protocol/packed_report.hpp"
#include "mrskin/protocol/packet.hpp"

namespace mrskin::protocol {

// ---- printing (gtest finds these through ADL, rapidcheck through operator<<) ----------

inline std::ostream& operator<<(std::ostream& os, Error e) { return os << to_string(e); }

namespace test_detail {
template <class Range>
void list(std::ostream& os, const Range& values, std::size_t n) {
  os << '[';
  for (std::size_t i = 0; i < n; ++i) {
    os << (i == 0 ? "" : ",") << static_cast<long>(values[i]);
  }
  os << ']';
}
inline int u(std::uint8_t v) { return v; }
}  // namespace test_detail

inline std::ostream& operator<<(std::ostream& os, const IdentifyRequest& m) {
  return os << "IdentifyRequest{" << test_detail::u(m.host_major) << '.' << test_detail::u(m.host_minor)
            << '}';
}
inline std::ostream& operator<<(std::ostream& os, const Identity& m) {
  using test_detail::u;
  return os << "Identity{proto=" << u(m.proto_major) << '.' << u(m.proto_minor) << " fw=" << u(m.fw_major)
            << '.' << u(m.fw_minor) << '.' << u(m.fw_patch) << " grid=" << u(m.rows) << 'x' << u(m.cols)
            << " fluid=" << m.fluid_cells << " valves=" << m.valves << " sensors=" << m.sensors
            << " serial=" << m.serial << " current_lsb_nA=" << m.current_lsb_nA
            << " current_max=" << m.current_max_counts << " quantity=" << u(m.sensor_quantity)
            << " sensor_lsb_nano=" << m.sensor_lsb_nano << " hb_timeout_ms=" << m.heartbeat_timeout_ms
            << " telemetry_hz=" << m.telemetry_rate_hz << '}';
}
inline std::ostream& operator<<(std::ostream& os, const ValveCurrents& m) {
  os << "ValveCurrents{first=" << m.first << " count=" << test_detail::u(m.count) << ' ';
  test_detail::list(os, m.counts, std::min<std::size_t>(m.count, kMaxValveCurrents));
  return os << '}';
}
inline std::ostream& operator<<(std::ostream& os, const CellTargets& m) {
  os << "CellTargets{first=" << m.first << " count=" << test_detail::u(m.count);
  for (std::size_t i = 0; i < std::min<std::size_t>(m.count, kMaxCellTargets); ++i) {
    const CellTarget& t = m.targets[i];
    os << " (" << t.stiffness << ',' << t.offset << ',' << t.ceiling << ',' << test_detail::u(t.validity)
       << ')';
  }
  return os << '}';
}
inline std::ostream& operator<<(std::ostream& os, const Telemetry& m) {
  os << "Telemetry{t=" << m.device_time_us << " first=" << m.first << " count=" << test_detail::u(m.count)
     << ' ';
  test_detail::list(os, m.counts, std::min<std::size_t>(m.count, kMaxTelemetryValues));
  return os << '}';
}
inline std::ostream& operator<<(std::ostream& os, const TimeSync& m) {
  return os << "TimeSync{" << m.device_time_us << '}';
}
inline std::ostream& operator<<(std::ostream& os, const Status& m) {
  using test_detail::u;
  return os << "Status{state=" << u(m.state) << " fault=" << u(m.fault) << " detail=" << m.fault_detail
            << " flags=" << u(m.flags) << '}';
}
inline std::ostream& operator<<(std::ostream& os, const Heartbeat& m) {
  return os << "Heartbeat{" << m.counter << '}';
}
inline std::ostream& operator<<(std::ostream& os, const StateRequest& m) {
  return os << "StateRequest{" << test_detail::u(m.request) << '}';
}
inline std::ostream& operator<<(std::ostream& os, const ConfigRead& m) {
  return os << "ConfigRead{key=" << m.key << " offset=" << m.offset << " length=" << test_detail::u(m.length)
            << '}';
}
inline std::ostream& operator<<(std::ostream& os, const ConfigChunk& m) {
  os << "{key=" << m.key << " offset=" << m.offset << " total=" << m.total
     << " length=" << test_detail::u(m.length) << ' ';
  test_detail::list(os, m.bytes, std::min<std::size_t>(m.length, kMaxConfigBytes));
  return os << '}';
}
inline std::ostream& operator<<(std::ostream& os, const ConfigData& m) {
  return os << "ConfigData" << static_cast<const ConfigChunk&>(m);
}
inline std::ostream& operator<<(std::ostream& os, const ConfigWrite& m) {
  return os << "ConfigWrite" << static_cast<const ConfigChunk&>(m);
}
inline std::ostream& operator<<(std::ostream& os, const ConfigAck& m) {
  return os << "ConfigAck{key=" << m.key << " offset=" << m.offset << " status=" << test_detail::u(m.status)
            << '}';
}
inline std::ostream& operator<<(std::ostream& os, const UsbSlots& m) {
  return os << "UsbSlots{report_bytes=" << m.report_bytes
            << " reports_per_interval=" << test_detail::u(m.reports_per_interval)
            << " interval_us=" << m.interval_us << '}';
}
inline std::ostream& operator<<(std::ostream& os, const SensorDeadband& m) {
  return os << "SensorDeadband{counts=" << test_detail::u(m.counts) << '}';
}
inline std::ostream& operator<<(std::ostream& os, const Message& m) {
  std::visit([&os](const auto& v) { os << v; }, m);
  return os;
}
inline void PrintTo(const Message& m, std::ostream* os) { *os << m; }
inline void PrintTo(Error e, std::ostream* os) { *os << to_string(e); }

}  // namespace mrskin::protocol

namespace mrskin::protocol::test {

// ---- hex ----------------------------------------------------------------------------

inline std::string hex(const std::uint8_t* data, std::size_t n) {
  static constexpr char kDigits[] = "0123456789ABCDEF";
  std::string s;
  s.reserve(2 * n);
  for (std::size_t i = 0; i < n; ++i) {
    s.push_back(kDigits[data[i] >> 4U]);
    s.push_back(kDigits[data[i] & 0xFU]);
  }
  return s;
}
inline std::string hex(const std::vector<std::uint8_t>& v) { return hex(v.data(), v.size()); }

inline std::vector<std::uint8_t> unhex(std::string_view s) {
  auto nibble = [](char c) -> std::uint8_t {
    if (c >= '0' && c <= '9') return static_cast<std::uint8_t>(c - '0');
    if (c >= 'A' && c <= 'F') return static_cast<std::uint8_t>(c - 'A' + 10);
    if (c >= 'a' && c <= 'f') return static_cast<std::uint8_t>(c - 'a' + 10);
    throw std::invalid_argument("bad hex digit");
  };
  if (s.size() % 2 != 0) throw std::invalid_argument("odd hex length");
  std::vector<std::uint8_t> out;
  for (std::size_t i = 0; i < s.size(); i += 2) {
    out.push_back(static_cast<std::uint8_t>((nibble(s[i]) << 4U) | nibble(s[i + 1])));
  }
  return out;
}

// A frame in can-utils' cansend syntax: classic "1A5#0102030405060708", FD "405##0<data>".
inline std::string frame_to_text(const CanFrame& f) {
  std::ostringstream os;
  static constexpr char kDigits[] = "0123456789ABCDEF";
  os << kDigits[(f.id >> 8U) & 0xFU] << kDigits[(f.id >> 4U) & 0xFU] << kDigits[f.id & 0xFU];
  os << (f.fd ? "##0" : "#") << hex(f.data.data(), f.length);
  return os.str();
}
inline CanFrame frame_from_text(std::string_view s) {
  const auto hash = s.find('#');
  if (hash == std::string_view::npos || hash != 3) throw std::invalid_argument("bad frame text");
  CanFrame f;
  f.id = static_cast<std::uint32_t>(std::stoul(std::string(s.substr(0, 3)), nullptr, 16));
  std::string_view data = s.substr(4);
  if (!data.empty() && data[0] == '#') {
    f.fd = true;
    data = data.substr(2);  // "#" and the flags nibble
  }
  const auto bytes = unhex(data);
  if (bytes.size() > f.data.size()) throw std::invalid_argument("frame too long");
  std::copy(bytes.begin(), bytes.end(), f.data.begin());
  f.length = static_cast<std::uint8_t>(bytes.size());
  return f;
}

// ---- golden messages ------------------------------------------------------------------

// Parameters every CAN golden vector uses.
inline constexpr std::uint8_t kGoldenNode = 5;
inline constexpr std::uint8_t kGoldenCounter = 9;
inline constexpr std::uint8_t kGoldenSequence = 0x2A;

inline Direction direction_of(const Message& m) {
  switch (type_of(m)) {
    case MessageType::identify_request:
    case MessageType::valve_currents:
    case MessageType::cell_targets:
    case MessageType::heartbeat:
    case MessageType::state_request:
    case MessageType::config_read:
    case MessageType::config_write:
      return Direction::host_to_device;
    default:
      return Direction::device_to_host;
  }
}

// Identity and configuration travel segmented on classic CAN; the rest as PDO-style frames.
inline bool is_segmented_type(const Message& m) {
  switch (type_of(m)) {
    case MessageType::identify_request:
    case MessageType::identity:
    case MessageType::config_read:
    case MessageType::config_data:
    case MessageType::config_write:
    case MessageType::config_ack:
    case MessageType::usb_slots:
    case MessageType::sensor_deadband:
      return true;
    default:
      return false;
  }
}

struct NamedMessage {
  std::string name;
  Message message;
};

// One fixed message per type (plus a partial valve block). Their encodings are in
// tests/protocol/golden_vectors.txt.
inline std::vector<NamedMessage> golden_messages() {
  std::vector<NamedMessage> out;
  out.push_back({"identify_request", IdentifyRequest{1, 0}});
  Identity id;
  id.proto_major = 1;
  id.proto_minor = 0;
  id.fw_major = 0;
  id.fw_minor = 3;
  id.fw_patch = 2;
  id.rows = 5;
  id.cols = 5;
  id.fluid_cells = 13;
  id.valves = 12;
  id.sensors = 12;
  id.serial = 0x4D520001;
  id.current_lsb_nA = 125000;  // 125 uA
  id.current_max_counts = 4000;
  id.sensor_quantity = static_cast<std::uint8_t>(SensorQuantity::displacement_m);
  id.sensor_lsb_nano = 2500;  // 2.5 um
  id.heartbeat_timeout_ms = 100;
  id.telemetry_rate_hz = 1000;
  out.push_back({"identity", id});

  ValveCurrents v;
  v.first = 0;
  v.count = 12;
  const std::uint16_t currents[12] = {0, 1, 2047, 4095, 0x123, 0xABC, 800, 1600, 2400, 3200, 4000, 17};
  std::copy(std::begin(currents), std::end(currents), v.counts.begin());
  out.push_back({"valve_currents", v});

  ValveCurrents vp;
  vp.first = 4;
  vp.count = 5;
  const std::uint16_t partial[5] = {0x321, 0x654, 0x987, 0xCBA, 0xFED};
  std::copy(std::begin(partial), std::end(partial), vp.counts.begin());
  out.push_back({"valve_currents_partial", vp});

  CellTargets c;
  c.first = 18;  // index above 15: its high nibble travels in the frame on classic CAN
  c.count = 2;
  c.targets[0] = CellTarget{150, 1000, 1500, 10};  // 300 N/m, 2 mm, 1.5 N, 100 ms
  c.targets[1] = CellTarget{16383, 4095, 4095, 63};
  out.push_back({"cell_targets", c});

  Telemetry t;
  t.device_time_us = 0x12345678;
  t.first = 0;
  t.count = 12;
  const std::int16_t sensors[12] = {0, 1, -1, 2047, -2048, 400, -400, 0x123, -0x123, 1000, 2000, -7};
  std::copy(std::begin(sensors), std::end(sensors), t.counts.begin());
  out.push_back({"telemetry", t});

  out.push_back({"time_sync", TimeSync{0x12345678}});
  out.push_back({"status", Status{3, 2, 0x1234, 0x05}});  // fault, overtemperature, released+calibrated
  out.push_back({"heartbeat", Heartbeat{0xBEEF}});
  out.push_back({"state_request", StateRequest{1}});  // enable
  out.push_back({"config_read", ConfigRead{2, 0x0040, 48}});

  ConfigData d;
  d.key = 2;
  d.offset = 0x0040;
  d.total = 0x0100;
  d.length = 12;
  for (std::uint8_t i = 0; i < 12; ++i) d.bytes[i] = i;
  out.push_back({"config_data", d});

  ConfigWrite w;
  w.key = 1;
  w.offset = 0;
  w.total = 5;
  w.length = 5;
  const std::uint8_t text[5] = {'m', 'r', 's', 'k', 'n'};
  std::copy(std::begin(text), std::end(text), w.bytes.begin());
  out.push_back({"config_write", w});

  out.push_back({"config_ack", ConfigAck{1, 0, 0}});
  out.push_back({"usb_slots", UsbSlots{1024, 3, 125}});  // high speed, 3 x 1024 bytes a microframe
  out.push_back({"sensor_deadband", SensorDeadband{2}});
  return out;
}

// Protocol 1.2 packed reports: the packets of one report, sequence kGoldenSequence + i. Their
// encodings are in golden_vectors.txt too (framings "report" and "canfd").
struct NamedReport {
  std::string name;
  Direction direction = Direction::host_to_device;
  std::vector<Message> messages;
};

inline std::vector<NamedReport> golden_reports() {
  const std::vector<NamedMessage> m = golden_messages();
  const auto find = [&m](const std::string& name) {
    for (const NamedMessage& nm : m) {
      if (nm.name == name) return nm.message;
    }
    throw std::runtime_error("no golden message " + name);
  };
  // What a 1.2 host sends in a tick: the heartbeat poll() made due, then the valve currents.
  NamedReport host{
      "packed_host_report", Direction::host_to_device, {find("heartbeat"), find("valve_currents")}};
  // What a 1.2 unit sends with a sample: the status and echo that waited, then the telemetry.
  NamedReport device{"packed_device_report",
                     Direction::device_to_host,
                     {find("status"), find("heartbeat"), find("telemetry")}};
  return {host, device};
}

// ---- golden vector file -------------------------------------------------------------

struct GoldenLine {
  std::string name;
  std::string framing;  // packet, can, canfd
  std::vector<std::string> tokens;
  std::string text;  // the whole line as written
};

inline std::vector<GoldenLine> read_golden(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error("cannot open " + path);
  std::vector<GoldenLine> lines;
  std::string line;
  while (std::getline(in, line)) {
    if (line.empty() || line[0] == '#') continue;
    std::istringstream ls(line);
    GoldenLine g;
    g.text = line;
    ls >> g.name >> g.framing;
    for (std::string tok; ls >> tok;) g.tokens.push_back(tok);
    lines.push_back(std::move(g));
  }
  return lines;
}

// ---- encoding all framings ------------------------------------------------------------

inline std::vector<std::uint8_t> packet_bytes(const Message& m, std::uint8_t sequence) {
  std::array<std::uint8_t, kPacketMaxBytes> buf{};
  const EncodeResult r = encode_packet(m, sequence, buf);
  if (r.error != Error::ok) throw std::runtime_error("encode_packet failed");
  return {buf.begin(), buf.begin() + static_cast<std::ptrdiff_t>(r.bytes)};
}

inline std::vector<CanFrame> can_frames(const Message& m, std::uint8_t node, std::uint8_t counter,
                                        std::uint8_t sequence) {
  std::array<CanFrame, 16> frames{};
  const CanEncodeResult r = encode_can(m, node, counter, sequence, frames);
  if (r.error != Error::ok) throw std::runtime_error("encode_can failed");
  return {frames.begin(), frames.begin() + static_cast<std::ptrdiff_t>(r.frames)};
}

// The vector lines for one message, as the golden file holds them.
inline std::vector<std::string> golden_lines_for(const NamedMessage& nm) {
  std::vector<std::string> lines;
  std::ostringstream packet;
  packet << nm.name << " packet " << hex(packet_bytes(nm.message, kGoldenSequence));
  lines.push_back(packet.str());
  std::ostringstream can;
  can << nm.name << " can";
  for (const CanFrame& f : can_frames(nm.message, kGoldenNode, kGoldenCounter, kGoldenSequence)) {
    can << ' ' << frame_to_text(f);
  }
  lines.push_back(can.str());
  CanFrame fd;
  if (encode_canfd(nm.message, kGoldenNode, direction_of(nm.message), kGoldenSequence, fd).error !=
      Error::ok) {
    throw std::runtime_error("encode_canfd failed");
  }
  std::ostringstream canfd;
  canfd << nm.name << " canfd " << frame_to_text(fd);
  lines.push_back(canfd.str());
  return lines;
}

// The report's bytes up to the end of its last packet (append_packet, sequences from sequence).
inline std::vector<std::uint8_t> report_bytes(const NamedReport& r, std::uint8_t sequence) {
  std::array<std::uint8_t, kHidReportBytes> report{};
  std::size_t used = 0;
  for (std::size_t i = 0; i < r.messages.size(); ++i) {
    const EncodeResult e =
        append_packet(r.messages[i], static_cast<std::uint8_t>(sequence + i), report, used);
    if (e.error != Error::ok) throw std::runtime_error("append_packet failed for " + r.name);
    used += e.bytes;
  }
  return {report.begin(), report.begin() + static_cast<std::ptrdiff_t>(used)};
}

inline std::vector<std::string> golden_report_lines_for(const NamedReport& r) {
  const std::vector<std::uint8_t> bytes = report_bytes(r, kGoldenSequence);
  std::ostringstream report;
  report << r.name << " report " << hex(bytes);
  CanFrame fd;
  if (encode_canfd_report(bytes, kGoldenNode, r.direction, fd).error != Error::ok) {
    throw std::runtime_error("encode_canfd_report failed for " + r.name);
  }
  std::ostringstream canfd;
  canfd << r.name << " canfd " << frame_to_text(fd);
  return {report.str(), canfd.str()};
}

// ---- reassembly of classic CAN blocks --------------------------------------------------

// Merges the per-block or per-cell messages a CanDecoder returns back into one message of
// the kind that was encoded (blocks must arrive in order and be contiguous).
class BlockMerger {
 public:
  // Returns false if m cannot extend what was merged so far.
  bool add(const Message& m) {
    if (!merged_) {
      merged_ = m;
      return true;
    }
    if (merged_->index() != m.index()) return false;
    if (auto* v = std::get_if<ValveCurrents>(&*merged_)) {
      return append(*v, std::get<ValveCurrents>(m), v->counts, std::get<ValveCurrents>(m).counts);
    }
    if (auto* t = std::get_if<Telemetry>(&*merged_)) {
      return append(*t, std::get<Telemetry>(m), t->counts, std::get<Telemetry>(m).counts);
    }
    if (auto* c = std::get_if<CellTargets>(&*merged_)) {
      return append(*c, std::get<CellTargets>(m), c->targets, std::get<CellTargets>(m).targets);
    }
    return false;
  }
  [[nodiscard]] bool empty() const { return !merged_.has_value(); }
  [[nodiscard]] const Message& result() const { return *merged_; }

 private:
  template <class M, class Arr>
  static bool append(M& into, const M& from, Arr& dst, const Arr& src) {
    if (from.first != into.first + into.count || into.count + from.count > dst.size()) return false;
    for (std::size_t i = 0; i < from.count; ++i) dst[into.count + i] = src[i];
    into.count = static_cast<std::uint8_t>(into.count + from.count);
    return true;
  }
  std::optional<Message> merged_;
};

}  // namespace mrskin::protocol::test
