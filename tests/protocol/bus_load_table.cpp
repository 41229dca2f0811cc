// Prints the Cost tables of docs/protocol.md: bytes and frames per full update, bus load
// at 1 kHz with worst-case bit stuffing, and the largest grid each bus can update at 1 kHz.
//   build/release/tests/protocol/mrskin_bus_load_table          the tables (Markdown)
//   build/release/tests/protocol/mrskin_bus_load_table --check  also checks the 5x5
//                                                                classic CAN figure (CTest)
//   ... --doc docs/protocol.md   checks that the document quotes every table row (CTest)
// Frame sizes come from the encoder (packet_payload_length, encode_can) and bit counts
// from can_frame_bits_worst_case, so the tables follow the protocol if it changes.
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "mrskin/protocol/can.hpp"
#include "mrskin/protocol/messages.hpp"
#include "mrskin/protocol/packet.hpp"

namespace {

using namespace mrskin::protocol;

// ---- assumptions (also stated in docs/protocol.md) -------------------------------------
constexpr double kTickHz = 1000.0;
constexpr double kHeartbeatHz = 50.0;  // DeviceSession's default heartbeat period, 20 ms
constexpr double kStatusHz = 10.0;     // device status every 100 ms (and on change)
constexpr double kClassicBitRate = 1e6;
constexpr double kFdNominalRate = 1e6;  // arbitration phase
constexpr double kFdDataRate = 5e6;     // data phase, bit-rate switch on
constexpr double kRefreshTicks = 10.0;  // deltas: an unchanged block is re-sent every 10 ms
// Deltas, "typical" palpation (averaged over a scene): per tick 1 valve block and 1 sensor
// block (4 values each) change. "busy" (one fingertip loading, worst tick): 3 and 3.
constexpr double kTypicalChangedBlocks = 1.0;
constexpr double kBusyChangedBlocks = 3.0;
constexpr double kHidFsReportsPerMs = 1.0;  // full speed: one 64-byte report per 1 ms frame
constexpr double kHidHsReportsPerMs = 8.0;  // high speed, 64-byte reports every 125 us

struct Grid {
  int rows;
  int cols;
  [[nodiscard]] int cells() const { return rows * cols; }
  [[nodiscard]] int fluid() const { return (cells() + 1) / 2; }
  [[nodiscard]] int valves() const { return cells() / 2; }
  [[nodiscard]] int sensors() const { return cells() / 2; }  // one under each valve cell
};

int ceil_div(int a, int b) { return (a + b - 1) / b; }

std::size_t packet_bytes(const Message& m) {
  return kPacketHeaderBytes + packet_payload_length(m) + kPacketCrcBytes;
}

std::size_t valve_packet_bytes(int n) {
  ValveCurrents v;
  v.count = static_cast<std::uint8_t>(n);
  return packet_bytes(v);
}
std::size_t telemetry_packet_bytes(int n) {
  Telemetry t;
  t.count = static_cast<std::uint8_t>(n);
  return packet_bytes(t);
}

// ---- classic CAN -----------------------------------------------------------------------

double classic_frame_us() {
  return static_cast<double>(can_frame_bits_worst_case(8, false)) / kClassicBitRate * 1e6;
}

// Frames per tick; every classic frame of v1 is 8 bytes.
double classic_frames_full(const Grid& g) {
  return ceil_div(g.valves(), 4) + ceil_div(g.sensors(), 4) + 1.0;  // + TimeSync
}
double classic_frames_delta(const Grid& g, double changed) {
  auto blocks = [changed](int values) {
    const double b = ceil_div(values, 4);
    const double c = std::min(changed, b);
    return c + (b - c) / kRefreshTicks;
  };
  return blocks(g.valves()) + blocks(g.sensors()) + 1.0;
}
double classic_background_frames() { return (kHeartbeatHz + kStatusHz) / kTickHz; }
double classic_load(double frames) {
  return (frames + classic_background_frames()) * classic_frame_us() / 1000.0;
}

// ---- CAN FD (bit-rate switch) -----------------------------------------------------------

// A CAN FD frame's worst-case time with the bit-rate switch (can_frame_time_worst_case_s), us.
double fd_frame_us(std::size_t packet) {
  return can_frame_time_worst_case_s(packet, true, kFdNominalRate, kFdDataRate) * 1e6;
}
// Time on the bus per tick for `values` values sent as packets of at most `cap` values.
template <class Bytes>
double fd_values_us(int values, int cap, Bytes bytes) {
  double us = 0.0;
  for (int left = values; left > 0; left -= cap) us += fd_frame_us(bytes(std::min(left, cap)));
  return us;
}
double fd_background_us() {
  return (kHeartbeatHz * fd_frame_us(packet_bytes(Heartbeat{})) +
          kStatusHz * fd_frame_us(packet_bytes(Status{}))) /
         kTickHz;
}
double fd_full_us(const Grid& g) {
  return fd_values_us(g.valves(), kMaxValveCurrents, valve_packet_bytes) +
         fd_values_us(g.sensors(), kMaxTelemetryValues, telemetry_packet_bytes);
}
// Deltas: the changed values as one run, plus a refresh run of 1/10 of the rest.
double fd_delta_us(const Grid& g, double changed_blocks) {
  auto dir = [changed_blocks](int values, int cap, auto bytes) {
    const int changed = std::min(values, static_cast<int>(changed_blocks * 4));
    const int refresh = static_cast<int>(std::ceil((values - changed) / kRefreshTicks));
    // A sender sends the whole range instead when that is cheaper.
    return std::min(fd_values_us(changed, cap, bytes) + fd_values_us(refresh, cap, bytes),
                    fd_values_us(values, cap, bytes));
  };
  return dir(g.valves(), kMaxValveCurrents, valve_packet_bytes) +
         dir(g.sensors(), kMaxTelemetryValues, telemetry_packet_bytes);
}
double fd_load(double us) { return (us + fd_background_us()) / 1000.0; }

// ---- USB HID ---------------------------------------------------------------------------

// One packet per report: reports per tick in the busier direction, over the reports the
// endpoint moves per tick.
double hid_full_reports(const Grid& g, bool with_background) {
  const double out =
      ceil_div(g.valves(), kMaxValveCurrents) + (with_background ? kHeartbeatHz / kTickHz : 0.0);
  const double in =
      ceil_div(g.sensors(), kMaxTelemetryValues) + (with_background ? kStatusHz / kTickHz : 0.0);
  return std::max(out, in);
}
// Protocol 1.2 packs packets back to back into 64-byte reports (append_packet's rule: a packet
// that does not fit starts the next report). Reports for packets of these sizes, in order.
double packed_reports(const std::vector<std::size_t>& packets) {
  double reports = 0.0;
  std::size_t used = kHidReportBytes;
  for (const std::size_t bytes : packets) {
    if (used + bytes > kHidReportBytes) {
      reports += 1.0;
      used = 0;
    }
    used += bytes;
  }
  return reports;
}
// Packet sizes of one full update in one direction, values split as the session splits them.
std::vector<std::size_t> update_packets(int values, int cap, std::size_t (*bytes)(int)) {
  std::vector<std::size_t> sizes;
  for (int left = values; left > 0; left -= cap) sizes.push_back(bytes(std::min(left, cap)));
  return sizes;
}
// 1.2 with packing agreed: the heartbeat rides with the valve currents (first in the host's
// report), status and heartbeat echo with the telemetry (first in the unit's report). Reports
// per tick, averaged over whether a heartbeat (50 Hz) and a status (10 Hz) fall in the tick;
// the busier direction.
double hid_packed_reports(const Grid& g) {
  const double p_heartbeat = kHeartbeatHz / kTickHz;
  const double p_status = kStatusHz / kTickHz;
  const std::size_t heartbeat = packet_bytes(Heartbeat{});
  const std::size_t status = packet_bytes(Status{});
  const std::vector<std::size_t> currents = update_packets(g.valves(), kMaxValveCurrents, valve_packet_bytes);
  const std::vector<std::size_t> telemetry =
      update_packets(g.sensors(), kMaxTelemetryValues, telemetry_packet_bytes);
  auto with = [](std::vector<std::size_t> first, const std::vector<std::size_t>& rest) {
    first.insert(first.end(), rest.begin(), rest.end());
    return packed_reports(first);
  };
  const double out = (1.0 - p_heartbeat) * with({}, currents) + p_heartbeat * with({heartbeat}, currents);
  double in = 0.0;
  for (const bool s : {false, true}) {
    for (const bool h : {false, true}) {
      std::vector<std::size_t> first;
      if (s) first.push_back(status);
      if (h) first.push_back(heartbeat);  // the echo is a Heartbeat packet
      in += (s ? p_status : 1.0 - p_status) * (h ? p_heartbeat : 1.0 - p_heartbeat) * with(first, telemetry);
    }
  }
  return std::max(out, in);
}
double hid_delta_reports(const Grid& g, double changed_blocks) {
  auto dir = [changed_blocks](int values, int cap) {
    const int changed = std::min(values, static_cast<int>(changed_blocks * 4));
    const int refresh = static_cast<int>(std::ceil((values - changed) / kRefreshTicks));
    return std::min(ceil_div(changed, cap) + ceil_div(refresh, cap), ceil_div(values, cap));
  };
  return std::max(dir(g.valves(), kMaxValveCurrents), dir(g.sensors(), kMaxTelemetryValues));
}

// ---- largest grids ---------------------------------------------------------------------

// Largest cell count n (any R x C with R*C = n has the same cost) whose load fits.
template <class Load>
int largest_cells(Load load, double limit) {
  int best = 0;
  for (int n = 2; n <= 64 * 64; ++n) {
    if (load(Grid{1, n}) <= limit + 1e-12) best = n;
  }
  return best;
}
std::string grid_text(int cells) {
  if (cells < 4) return "none";
  const int side = static_cast<int>(std::floor(std::sqrt(static_cast<double>(cells))));
  return std::to_string(cells) + " cells (" + std::to_string(side) + "x" + std::to_string(side) + ")";
}

// Everything printed, kept for the --doc check.
std::string g_printed;

template <class... Args>
void out(const char* format, Args... args) {
  char buf[1024];
  std::snprintf(buf, sizeof buf, format, args...);
  g_printed += buf;
  std::fputs(buf, stdout);
}
void out(const char* text) {
  g_printed += text;
  std::fputs(text, stdout);
}

std::string pct(double load) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.1f %%", load * 100.0);
  return buf;
}

void print_tables() {
  const Grid g5{5, 5};
  out("## Per full 5x5 update (13 fluid cells, 12 valves, 12 sensors)\n\n");
  out("| bus | host->device | device->host | on the wire per update |\n|---|---|---|---|\n");
  out("| USB-HID full speed | 1 report: ValveCurrents packet %zu B in 64 B | 1 report: Telemetry packet %zu "
      "B in 64 B | 128 B of reports (70 B used) |\n",
      valve_packet_bytes(12), telemetry_packet_bytes(12));
  out("| classic CAN | 3 valve-block frames | 1 TimeSync + 3 sensor-block frames | 7 frames x 8 B = 56 B, 7 "
      "x %zu = %zu bits |\n",
      can_frame_bits_worst_case(8, false), 7 * can_frame_bits_worst_case(8, false));
  out("| CAN FD | 1 frame, %zu B packet in %zu B | 1 frame, %zu B packet in %zu B | %zu + %zu bits (%.1f us) "
      "|\n\n",
      valve_packet_bytes(12), canfd_padded_length(valve_packet_bytes(12)), telemetry_packet_bytes(12),
      canfd_padded_length(telemetry_packet_bytes(12)),
      can_frame_bits_worst_case(valve_packet_bytes(12), true),
      can_frame_bits_worst_case(telemetry_packet_bytes(12), true), fd_full_us(g5));

  out("## Worst-case frame times\n\n| frame | bits (worst-case stuffing, with IFS) | time "
      "|\n|---|---|---|\n");
  out("| classic, 8 data bytes | %zu | %.1f us at 1 Mbit/s |\n", can_frame_bits_worst_case(8, false),
      classic_frame_us());
  for (const std::size_t n : {std::size_t{8}, std::size_t{12}, std::size_t{48}, std::size_t{64}}) {
    out("| FD, %zu data bytes | %zu | %.1f us at 1/5 Mbit/s |\n", n, can_frame_bits_worst_case(n, true),
        fd_frame_us(n));
  }
  out("\n");

  out("## Load at 1 kHz (heartbeat %.0f Hz and status %.0f Hz included)\n\n", kHeartbeatHz, kStatusHz);
  out("| grid | fluid/valves/sensors | HID FS full 1.1 | HID FS full 1.2 | classic CAN full | classic CAN "
      "delta "
      "typical | classic CAN delta busy | CAN FD full | CAN FD delta typical | full updates/s at 100 % "
      "classic "
      "CAN |\n");
  out("|---|---|---|---|---|---|---|---|---|---|\n");
  for (const Grid g : {Grid{3, 3}, Grid{4, 4}, Grid{5, 5}, Grid{7, 7}, Grid{8, 8}, Grid{10, 10}, Grid{16, 16},
                       Grid{64, 64}}) {
    const double classic_full = classic_load(classic_frames_full(g));
    const double per_update_us = (classic_frames_full(g) + classic_background_frames()) * classic_frame_us();
    out("| %dx%d | %d/%d/%d | %s | %s | %s (%.1f frames) | %s | %s | %s | %s | %.0f |\n", g.rows, g.cols,
        g.fluid(), g.valves(), g.sensors(), pct(hid_full_reports(g, true) / kHidFsReportsPerMs).c_str(),
        pct(hid_packed_reports(g) / kHidFsReportsPerMs).c_str(), pct(classic_full).c_str(),
        classic_frames_full(g), pct(classic_load(classic_frames_delta(g, kTypicalChangedBlocks))).c_str(),
        pct(classic_load(classic_frames_delta(g, kBusyChangedBlocks))).c_str(),
        pct(fd_load(fd_full_us(g))).c_str(), pct(fd_load(fd_delta_us(g, kTypicalChangedBlocks))).c_str(),
        1e6 / per_update_us);
  }
  out("\nHID FS load = reports per 1 ms frame in the busier direction. 1.1: one packet a report\n"
      "(heartbeat host->device, status device->host; echoes not counted); above 100 % the\n"
      "heartbeat must ride on valve traffic and status displaces telemetry reports. 1.2: packed\n"
      "reports, heartbeat with the currents, status and echo with the telemetry (echoes counted).\n\n");

  out("## Largest grid updated at 1 kHz (cells = R*C; checkerboard: valves = sensors = floor(R*C/2))\n\n");
  out("| bus | full, <= 100 %% | full, <= 50 %% | delta typical, <= 100 %% | delta typical, <= 50 %% | delta "
      "busy, <= 100 %% |\n");
  out("|---|---|---|---|---|---|\n");
  // The 50 % columns are the CAN target (arbitration latency for the lowest-priority frame);
  // USB interrupt slots are reserved for the endpoint, so every slot is usable there.
  auto row = [](const char* name, auto full, auto typical, auto busy) {
    const bool usb = std::strncmp(name, "USB", 3) == 0;
    out("| %s | %s | %s | %s | %s | %s |\n", name, grid_text(largest_cells(full, 1.0)).c_str(),
        usb ? "n/a" : grid_text(largest_cells(full, 0.5)).c_str(),
        grid_text(largest_cells(typical, 1.0)).c_str(),
        usb ? "n/a" : grid_text(largest_cells(typical, 0.5)).c_str(),
        grid_text(largest_cells(busy, 1.0)).c_str());
  };
  row(
      "classic CAN 1 Mbit/s", [](const Grid& g) { return classic_load(classic_frames_full(g)); },
      [](const Grid& g) { return classic_load(classic_frames_delta(g, kTypicalChangedBlocks)); },
      [](const Grid& g) { return classic_load(classic_frames_delta(g, kBusyChangedBlocks)); });
  row(
      "CAN FD 1/5 Mbit/s", [](const Grid& g) { return fd_load(fd_full_us(g)); },
      [](const Grid& g) { return fd_load(fd_delta_us(g, kTypicalChangedBlocks)); },
      [](const Grid& g) { return fd_load(fd_delta_us(g, kBusyChangedBlocks)); });
  row(
      "USB-HID full speed (no heartbeat/status)",
      [](const Grid& g) { return hid_full_reports(g, false) / kHidFsReportsPerMs; },
      [](const Grid& g) { return hid_delta_reports(g, kTypicalChangedBlocks) / kHidFsReportsPerMs; },
      [](const Grid& g) { return hid_delta_reports(g, kBusyChangedBlocks) / kHidFsReportsPerMs; });
  row(
      "USB-HID high speed, 64 B reports (no heartbeat/status)",
      [](const Grid& g) { return hid_full_reports(g, false) / kHidHsReportsPerMs; },
      [](const Grid& g) { return hid_delta_reports(g, kTypicalChangedBlocks) / kHidHsReportsPerMs; },
      [](const Grid& g) { return hid_delta_reports(g, kBusyChangedBlocks) / kHidHsReportsPerMs; });
  out("\nClassic CAN addresses 16 blocks (64 valves, 64 sensors) and 256 cells per node; larger\n"
      "grids need several node ids on the same bus, which changes nothing in the load.\n");
}

// The figure worked by hand in docs/protocol.md: (3 valve + 1 TimeSync + 3 sensor) frames
// x 135 bits = 945 bits per 1 ms tick at 1 Mbit/s = 94.5 %.
int check() {
  const Grid g5{5, 5};
  const double frames = classic_frames_full(g5);
  const std::size_t bits_per_frame = can_frame_bits_worst_case(8, false);
  const double bits = frames * static_cast<double>(bits_per_frame);
  const double load = bits / (kClassicBitRate / kTickHz);
  std::array<CanFrame, 16> out{};
  ValveCurrents v;
  v.count = 12;
  Telemetry t;
  t.count = 12;
  const std::size_t encoded = encode_can(v, 1, 0, 0, out).frames + encode_can(t, 1, 0, 0, out).frames +
                              encode_can(TimeSync{}, 1, 0, 0, out).frames;
  const bool ok = frames == 7.0 && encoded == 7 && bits_per_frame == 135 && bits == 945.0 &&
                  std::fabs(load - 0.945) < 1e-12;
  std::printf(
      "check: 5x5 classic CAN full update = %.0f frames x %zu bits = %.0f bits/ms = %.1f %% at 1 Mbit/s: "
      "%s\n",
      frames, bits_per_frame, bits, load * 100.0, ok ? "ok" : "MISMATCH");
  std::printf("check: with heartbeat and status: %s\n", pct(classic_load(frames)).c_str());
  return ok ? 0 : 1;
}

// Every data row of the tables must appear verbatim in the document (docs/protocol.md).
int check_doc(const char* path) {
  std::ifstream in(path);
  if (!in) {
    std::printf("doc: cannot open %s: MISSING\n", path);
    return 1;
  }
  std::stringstream ss;
  ss << in.rdbuf();
  const std::string doc = ss.str();
  std::istringstream lines(g_printed);
  int rows = 0;
  int missing = 0;
  for (std::string line; std::getline(lines, line);) {
    if (line.rfind("| ", 0) != 0) continue;
    if (line.rfind("| bus ", 0) == 0 || line.rfind("| grid ", 0) == 0 || line.rfind("| frame ", 0) == 0)
      continue;
    ++rows;
    if (doc.find(line) == std::string::npos) {
      std::printf("doc: MISSING row: %s\n", line.c_str());
      ++missing;
    }
  }
  std::printf("doc: %d of %d table rows quoted in %s\n", rows - missing, rows, path);
  return missing == 0 ? 0 : 1;
}

}  // namespace

int main(int argc, char** argv) {
  print_tables();
  int status = 0;
  for (int i = 1; i < argc; ++i) {
    if (std::strcmp(argv[i], "--check") == 0) {
      std::printf("\n");
      status |= check();
    } else if (std::strcmp(argv[i], "--doc") == 0 && i + 1 < argc) {
      status |= check_doc(argv[++i]);
    }
  }
  return status;
}
