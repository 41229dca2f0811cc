// mrskinctl monitor: the grid live, from a device opened here (--device) or from a running
// mrskin-bridged (--bridge, its grid telemetry). In a terminal the grid is redrawn in place with a
// colour heatmap; piped it is one plain summary line per refresh; --json one object per line.
#include <fmt/format.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdlib>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "../mrskin-bridged/grid_snapshot.hpp"
#include "bridge_client.hpp"
#include "command.hpp"
#include "exit_codes.hpp"
#include "json_reply.hpp"
#include "json_text.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/driver/layout.hpp"
#include "mrskin/driver/model/device_model.hpp"
#include "mrskin/driver/model/observer.hpp"
#include "mrskin/sim/open_mock.hpp"

namespace mrskin::ctl {
namespace {

using namespace std::chrono_literals;

struct MonitorOptions {
  std::string device = "mock://";
  std::string bridge;       // the daemon's socket ("": its default)
  bool use_bridge = false;  // --bridge given, with or without a value
  double duration_s = 0.0;  // 0: until SIGINT
  double period_ms = 100.0;
  std::string color = "auto";  // auto, always, never
};

// One refresh: what is known now. Arrays are in GridLayout order (fluid cells, valves).
struct Frame {
  double t_s = 0.0;
  std::string source;
  std::string state = "?";
  std::string fault = "?";
  std::string last_fault;
  std::string faults;
  std::string valves_released;
  std::string connected;
  std::string derated;  // --device: the status flag
  std::string halted;   // --bridge
  std::string stream;   // --bridge
  int rows = 0;
  int cols = 0;
  double max_current_A = 0.0;
  double force_range_N = 2.0;
  std::string force_from;  // "observer estimate" or "force sensors"
  std::vector<double> force_N;
  std::vector<double> displacement_m;
  std::vector<double> target_N;  // --bridge
  std::vector<double> current_A;
  std::vector<double> temperature_C;  // host estimate
  double max_coil_C = NAN;            // mock only: the simulated hottest coil
  std::vector<double> sensors;        // --device: the readings, in sensor_unit
  std::string sensor_unit;
};

std::string json_numbers(const std::vector<double>& v) {
  std::string out = "[";
  for (std::size_t i = 0; i < v.size(); ++i) {
    if (i != 0) {
      out += ',';
    }
    out += json_number(v[i]);
  }
  out += ']';
  return out;
}

std::string json_bool_or_null(const std::string& v) { return v == "true" || v == "false" ? v : "null"; }

std::string to_json(const Frame& f) {
  std::string out =
      fmt::format(R"({{"t_s":{},"source":"{}","state":"{}","fault":"{}","last_fault":"{}","faults":{},)"
                  R"("valves_released":{},"connected":{},)",
                  json_number(f.t_s), json_escape(f.source), json_escape(f.state), json_escape(f.fault),
                  json_escape(f.last_fault), f.faults.empty() ? "null" : f.faults,
                  json_bool_or_null(f.valves_released), json_bool_or_null(f.connected));
  if (!f.derated.empty()) {
    out += fmt::format(R"("derated":{},)", json_bool_or_null(f.derated));
  }
  if (!f.halted.empty()) {
    out += fmt::format(R"("halted":{},"stream":"{}",)", json_bool_or_null(f.halted), json_escape(f.stream));
  }
  out += fmt::format(R"("rows":{},"cols":{},"force_from":"{}","force_n":{},"displacement_m":{},)", f.rows,
                     f.cols, f.force_from, json_numbers(f.force_N), json_numbers(f.displacement_m));
  if (!f.target_N.empty()) {
    out += fmt::format(R"("target_n":{},)", json_numbers(f.target_N));
  }
  out += fmt::format(R"("current_a":{},"temperature_c":{},"max_coil_temperature_c":{})",
                     json_numbers(f.current_A), json_numbers(f.temperature_C), json_number(f.max_coil_C));
  if (!f.sensor_unit.empty()) {
    out += fmt::format(R"(,"sensors":{},"sensor_unit":"{}")", json_numbers(f.sensors), f.sensor_unit);
  }
  out += '}';
  return out;
}

// The largest finite value and its index (index = size when there is none).
std::pair<double, std::size_t> peak(const std::vector<double>& v) {
  double best = 0.0;
  std::size_t at = v.size();
  for (std::size_t i = 0; i < v.size(); ++i) {
    if (std::isfinite(v[i]) && (at == v.size() || v[i] > best)) {
      best = v[i];
      at = i;
    }
  }
  return {best, at};
}

std::string where(const std::vector<GridCell>& cells, std::size_t i) {
  return i < cells.size() ? fmt::format("({},{})", cells[i].row, cells[i].col) : "(-)";
}

std::string state_words(const Frame& f) {
  std::string s = fmt::format("state {} fault {}", f.state, f.fault);
  if (f.halted == "true") {
    s += " halted";
  }
  if (f.derated == "true") {
    s += " derated";
  }
  if (f.connected == "false") {
    s += " disconnected";
  }
  if (!f.stream.empty() && f.stream != "live") {
    s += " stream " + f.stream;
  }
  return s;
}

// Piped: one line per refresh with the peaks (the whole grid is in --json).
std::string plain_line(const Frame& f, const GridLayout& layout) {
  const auto [force, fi] = peak(f.force_N);
  const auto [depth, di] = peak(f.displacement_m);
  const auto [amps, ai] = peak(f.current_A);
  const auto [hot, hi] = peak(f.temperature_C);
  std::string line = fmt::format(
      "t={:.2f} s  {}  force max {:.3f} N at {}  displacement max {:.3f} mm at {}  current max {:.4f} A at "
      "{}  "
      "coil est. max {:.1f} C at {}",
      f.t_s, state_words(f), force, where(layout.fluid_cells(), fi), depth * 1e3,
      where(layout.fluid_cells(), di), amps, where(layout.valves(), ai), hot, where(layout.valves(), hi));
  if (std::isfinite(f.max_coil_C)) {
    line += fmt::format(" (mock hottest {:.1f} C)", f.max_coil_C);
  }
  return line;
}

// 256-colour background ramp, cold to hot.
int heat_colour(double fraction) {
  static constexpr std::array<int, 12> kRamp = {17, 19, 25, 31, 37, 43, 78, 148, 184, 214, 208, 196};
  if (!std::isfinite(fraction)) {
    return 236;
  }
  const double x = std::clamp(fraction, 0.0, 1.0);
  return kRamp.at(static_cast<std::size_t>(std::lround(x * static_cast<double>(kRamp.size() - 1))));
}

// In a terminal: the checkerboard, each position two text lines wide 8: a fluid cell shows
// force (N) and displacement (mm) on a force heatmap, a valve its current (mA) and estimated
// coil temperature (C) on a current heatmap.
std::string grid_screen(const Frame& f, const GridLayout& layout, bool colour) {
  std::string out = "\x1b[H";  // home: redrawn in place
  out += fmt::format("mrskinctl monitor  {}  t={:.2f} s  {}\x1b[K\n", f.source, f.t_s, state_words(f));
  out += fmt::format(
      "cells: force N / displacement mm ({}); valves: current mA / coil C (host estimate){}\x1b[K\n",
      f.force_from,
      std::isfinite(f.max_coil_C) ? fmt::format("; mock hottest coil {:.1f} C", f.max_coil_C)
                                  : std::string());
  // Index of each grid position in its list.
  std::vector<int> index(static_cast<std::size_t>(f.rows) * static_cast<std::size_t>(f.cols), -1);
  for (std::size_t i = 0; i < layout.fluid_cells().size(); ++i) {
    const GridCell c = layout.fluid_cells()[i];
    index.at(static_cast<std::size_t>(c.row) * static_cast<std::size_t>(f.cols) +
             static_cast<std::size_t>(c.col)) = static_cast<int>(i);
  }
  for (std::size_t i = 0; i < layout.valves().size(); ++i) {
    const GridCell c = layout.valves()[i];
    index.at(static_cast<std::size_t>(c.row) * static_cast<std::size_t>(f.cols) +
             static_cast<std::size_t>(c.col)) = static_cast<int>(i);
  }
  const auto at = [](const std::vector<double>& v, int i) {
    return i >= 0 && static_cast<std::size_t>(i) < v.size() ? v[static_cast<std::size_t>(i)] : NAN;
  };
  const int max_cols = 24;  // wider grids: the first columns (the whole grid is in --json)
  const int shown_cols = std::min(f.cols, max_cols);
  for (int r = 0; r < f.rows; ++r) {
    for (int line = 0; line < 2; ++line) {
      for (int c = 0; c < shown_cols; ++c) {
        const int i = index.at(static_cast<std::size_t>(r) * static_cast<std::size_t>(f.cols) +
                               static_cast<std::size_t>(c));
        const bool fluid = (r + c) % 2 == 0;
        double fraction = 0.0;
        std::string text;
        if (fluid) {
          fraction = at(f.force_N, i) / std::max(1e-9, f.force_range_N);
          text = line == 0 ? fmt::format("{:6.3f}", at(f.force_N, i))
                           : fmt::format("{:6.2f}", at(f.displacement_m, i) * 1e3);
        } else {
          fraction = at(f.current_A, i) / std::max(1e-12, f.max_current_A);
          text = line == 0 ? fmt::format("{:6.1f}", at(f.current_A, i) * 1e3)
                           : fmt::format("{:6.1f}", at(f.temperature_C, i));
        }
        if (colour) {
          const int bg = heat_colour(fraction);
          const bool dark_text = bg >= 148 && bg != 236;
          out += fmt::format("\x1b[48;5;{}m\x1b[{}m {} \x1b[0m", bg, dark_text ? "30" : "97", text);
        } else {
          out += fmt::format(" {}{}", text, fluid ? ' ' : '|');
        }
      }
      out += "\x1b[K\n";
    }
  }
  if (shown_cols < f.cols) {
    out += fmt::format("(columns {}..{} not shown; --json has them all)\x1b[K\n", shown_cols, f.cols - 1);
  }
  out += "\x1b[J";
  return out;
}

class Renderer {
 public:
  Renderer(const GlobalOptions& global, const MonitorOptions& o) : json_(global.json) {
    const bool tty = ::isatty(STDOUT_FILENO) == 1;
    // NOLINTNEXTLINE(concurrency-mt-unsafe): read once at start, one thread
    const char* term = std::getenv("TERM");
    // NOLINTNEXTLINE(concurrency-mt-unsafe): read once at start, one thread
    const bool no_color = std::getenv("NO_COLOR") != nullptr;
    screen_ = !json_ && (o.color == "always" || (tty && term != nullptr && std::string_view(term) != "dumb"));
    colour_ = screen_ && (o.color == "always" || !no_color);
    if (o.color == "never") {
      colour_ = false;
    }
  }
  Renderer(const Renderer&) = delete;
  Renderer& operator=(const Renderer&) = delete;
  Renderer(Renderer&&) = delete;
  Renderer& operator=(Renderer&&) = delete;
  ~Renderer() {
    if (drawn_) {
      std::fputs("\x1b[?25h", stdout);  // the cursor back
      std::fflush(stdout);
    }
  }
  void show(const Frame& f) {
    if (!layout_ || layout_->rows() != f.rows || layout_->cols() != f.cols) {
      layout_ = std::make_unique<GridLayout>(f.rows, f.cols);
    }
    if (json_) {
      fmt::print("{}\n", to_json(f));
    } else if (screen_) {
      if (!drawn_) {
        std::fputs("\x1b[2J\x1b[?25l", stdout);  // clear once, hide the cursor while drawing
        drawn_ = true;
      }
      fmt::print("{}", grid_screen(f, *layout_, colour_));
    } else {
      fmt::print("{}\n", plain_line(f, *layout_));
    }
    std::fflush(stdout);
    ++frames_;
  }
  [[nodiscard]] std::uint64_t frames() const noexcept { return frames_; }

 private:
  bool json_;
  bool screen_ = false;
  bool colour_ = false;
  bool drawn_ = false;
  std::uint64_t frames_ = 0;
  std::unique_ptr<GridLayout> layout_;
};

Duration period_of(const MonitorOptions& o) {
  return std::chrono::microseconds(static_cast<std::int64_t>(o.period_ms * 1e3));
}

int monitor_device(const MonitorOptions& o, Renderer& out) {
  MonotonicClock clock;
  const OpenedDevice dev = open_device(o.device, clock);
  const std::shared_ptr<sim::MockDevice> mock = sim::mock_of(dev);
  DeviceSession& session = *dev.session;
  const DeviceInfo& info = session.info();
  const model::DeviceProfile* profile = session.profile();
  Frame f;
  f.source = o.device;
  f.rows = info.rows;
  f.cols = info.cols;
  f.max_current_A = info.max_current_A;
  f.sensor_unit = info.sensor_unit;
  f.force_N.assign(info.fluid_cells, NAN);
  f.displacement_m.assign(info.fluid_cells, NAN);
  // Force: the force sensors where there are some; else the observer's nominal-model estimate
  // from the displacement sensors and the commanded currents (what the bridge uses).
  bool force_sensors = false;
  bool displacement_sensors = false;
  if (profile != nullptr) {
    f.force_range_N = profile->design.force_range_N;
    for (const model::SensorSpec& s : profile->sensors) {
      force_sensors = force_sensors || s.quantity == model::SensorQuantity::force;
      displacement_sensors = displacement_sensors || s.quantity == model::SensorQuantity::displacement;
    }
  }
  std::unique_ptr<model::DeviceModel> nominal;
  std::unique_ptr<model::CellObserver> observer;
  if (profile != nullptr && displacement_sensors) {
    nominal = std::make_unique<model::DeviceModel>(*profile);
    observer = std::make_unique<model::CellObserver>(*nominal, model::ObserverOptions{});
  }
  f.force_from = force_sensors ? "force sensors" : observer ? "observer estimate" : "unknown";
  bridged::CoilThermalEstimate thermal;
  thermal.reset(info.valves, profile != nullptr ? profile->coil.resistance_ohm : 0.0);

  const TimePoint t0 = clock.now();
  const TimePoint end = t0 + from_seconds(o.duration_s);
  TimePoint last = t0;
  TimePoint next_frame = t0 + period_of(o);
  for (;;) {
    const TimePoint now = clock.now();
    (void)session.poll(now);
    const double dt_s = to_seconds(now - last);
    last = now;
    if (observer && dt_s > 0.0) {
      (void)observer->update(session.sensors(), session.commanded_currents(), dt_s);  // errors: keep the last
    }
    thermal.step(session.commanded_currents(), session.valves_released(), dt_s);
    const bool over = (o.duration_s > 0.0 && now >= end) || stop_requested();
    if (now >= next_frame || (over && out.frames() == 0)) {
      next_frame = std::max(next_frame + period_of(o), now);
      f.t_s = to_seconds(now - t0);
      f.state = to_string(session.state());
      f.fault = fault_name(session.fault_code());
      f.last_fault = fault_name(session.last_fault_code());
      f.faults = std::to_string(session.counters().faults);
      f.valves_released = session.valves_released() ? "true" : "false";
      f.connected = session.connected() ? "true" : "false";
      f.derated = session.derated() ? "true" : "false";
      const std::span<const double> sensors = session.sensors();
      f.sensors.assign(sensors.begin(), sensors.end());
      if (observer == nullptr && displacement_sensors) {
        session.seeder().fit_displacements(sensors);  // once for every cell
      }
      for (std::size_t c = 0; c < info.fluid_cells; ++c) {
        f.force_N[c] = force_sensors ? session.seeder().force_N(c, sensors)
                       : observer    ? observer->force_N()[c]
                                     : NAN;
        f.displacement_m[c] = observer               ? observer->indentation_m()[c]
                              : displacement_sensors ? session.seeder().fitted_displacement_m(c)
                                                     : NAN;
      }
      const std::span<const double> commanded = session.commanded_currents();
      f.current_A.assign(commanded.begin(), commanded.end());
      const std::span<const double> temperature = thermal.temperature_C();
      f.temperature_C.assign(temperature.begin(), temperature.end());
      f.max_coil_C = mock ? mock->max_coil_temperature_C() : NAN;
      out.show(f);
    }
    if (over) {
      break;
    }
    clock.sleep_until(now + 1ms);
  }
  return tools::kOk;
}

// A daemon's grid event -> frame; false when it carries no grid yet (or is not one).
bool frame_from_event(const JsonReply& event, const std::string& path, Frame& f) {
  if (event.text("event") != "telemetry") {
    return false;
  }
  std::optional<std::vector<double>> force = event.numbers("force_n");
  std::optional<std::vector<double>> depth = event.numbers("displacement_m");
  std::optional<std::vector<double>> current = event.numbers("current_a");
  const double rows = event.number("rows").value_or(0.0);
  const double cols = event.number("cols").value_or(0.0);
  if (!force || !depth || !current || !(rows >= 1.0 && rows <= 255.0) || !(cols >= 1.0 && cols <= 255.0)) {
    return false;
  }
  const auto text = [&](std::string_view key, std::string_view fallback = "") {
    return event.text(key).value_or(std::string(fallback));
  };
  f = Frame{};
  f.source = "bridge:" + path;
  f.t_s = event.number("t_s").value_or(NAN);
  f.state = text("state", "?");
  f.fault = text("fault", "?");
  f.last_fault = text("last_fault");
  f.faults = text("faults");
  f.valves_released = text("valves_released");
  f.connected = text("connected");
  f.halted = text("halted");
  f.stream = text("stream");
  f.rows = static_cast<int>(rows);
  f.cols = static_cast<int>(cols);
  f.max_current_A = event.number("max_current_a").value_or(0.1);
  f.force_range_N = event.number("force_range_n").value_or(2.0);
  f.force_from = "observer estimate";
  f.force_N = *std::move(force);
  f.displacement_m = *std::move(depth);
  f.current_A = *std::move(current);
  f.target_N = event.numbers("target_n").value_or(std::vector<double>{});
  f.temperature_C = event.numbers("temperature_c").value_or(std::vector<double>{});
  f.max_coil_C = event.number("max_coil_temperature_c").value_or(NAN);
  // A grid that does not match its rows x cols is not drawn (a daemon of another version).
  const GridLayout layout(f.rows, f.cols);
  return f.force_N.size() == layout.fluid_cell_count() &&
         f.displacement_m.size() == layout.fluid_cell_count() && f.current_A.size() == layout.valve_count();
}

int monitor_bridge(const MonitorOptions& o, Renderer& out) {
  const std::string path = bridge_socket(o.bridge);
  Frame f;
  return stream_bridge_grid(path, o.period_ms, o.duration_s, "monitor", [&](const JsonReply& event) {
    if (frame_from_event(event, path, f)) {
      out.show(f);
    }
  });
}

}  // namespace

void add_monitor_command(CliCommand app, const GlobalOptions& global, int& exit_code) {
  auto o = std::make_shared<MonitorOptions>();  // shared with the callback, which CLI11 keeps
  CliCommand sub = app.subcommand(
      "monitor",
      "show the grid live: force and displacement per cell, current and coil temperature per valve, state "
      "and fault cause; from a device (--device) or a running mrskin-bridged (--bridge)");
  CliOption device =
      sub.option("--device", o->device, "device URI (mock://[PROFILE][?seed=N&faults=...])").show_default();
  CliOption bridge =
      sub.option("--bridge", o->bridge,
                 "attach to a running mrskin-bridged on this control socket instead of opening a device "
                 "(the daemon owns the device); without a value, its default socket (" +
                     bridged::default_socket_path() + " here)")
          .value_optional()
          .excludes(device);
  sub.option("--duration", o->duration_s, "seconds to run; 0 runs until Ctrl-C")
      .range(0.0, 1e6)
      .show_default();
  sub.option("--period-ms", o->period_ms, "refresh period, ms").range(10.0, 60000.0).show_default();
  sub.option("--color", o->color,
             "colour heatmap: auto (a terminal, TERM not dumb, NO_COLOR unset), "
             "always or never")
      .one_of({"auto", "always", "never"})
      .show_default();
  sub.footer(
      "Output: in a terminal the grid is redrawn in place (cells: force N / displacement mm; valves: current "
      "mA / coil temperature C); piped, one line per refresh with the peaks; with --json one object per "
      "refresh line with every array. Force and displacement are the observer's estimates from the sensors "
      "(force sensors where the profile has them); current is what the host commanded; coil temperature is "
      "a host estimate (the protocol reports none). See docs/cli.md.\n"
      "Exit codes: 0 the duration ended or Ctrl-C; 1 the daemon refused, closed or went silent; 2 bad "
      "arguments or URI; 3 no device, or no mrskin-bridged on the socket; 4 protocol mismatch; 5 device busy "
      "(use --bridge when a daemon owns it).");
  sub.callback([o, bridge, &global, &exit_code] {
    o->use_bridge = bridge.given();
    Renderer out(global, *o);
    const StopSignals signals;
    exit_code = o->use_bridge ? monitor_bridge(*o, out) : monitor_device(*o, out);
  });
}

}  // namespace mrskin::ctl
