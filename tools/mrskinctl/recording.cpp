#include "recording.hpp"

#include <fmt/format.h>

#include <cerrno>
#include <cmath>
#include <cstring>
#include <fstream>
#include <string_view>

#include "ctl_device_record.hpp"
#include "ctl_device_rig.hpp"
#include "mrskin/driver/errors.hpp"

namespace mrskin::ctl {
namespace {

void read_header(const RecordLine& f, Recording& r) {
  const double version = f.number("version");
  if (f.text("format") != kRecordFormat || (version != 1.0 && version != kRecordVersion)) {
    throw InvalidArgument(
        fmt::format("{}: not a {} version 1 or {} header", f.where(), kRecordFormat, kRecordVersion));
  }
  r.version = static_cast<int>(version);
  r.uri = f.text("uri");
  r.valves = f.index("valves");
  r.fluid_cells = f.index("fluid_cells");
  r.sensors = f.index("sensors");
  r.sensor_unit = f.text("sensor_unit");
  r.max_current_a = f.number("max_current_a");
  if (r.version >= 2) {
    r.rendered = f.text("rendered");
    if (r.rendered != "truth" && r.rendered != "observer" && r.rendered != "none") {
      throw InvalidArgument(fmt::format(R"({}: "rendered" must be "truth", "observer" or "none", not "{}")",
                                        f.where(), r.rendered));
    }
  }
}

// One per fluid cell, finite.
std::vector<double> cell_array(const RecordLine& f, std::string_view key, std::size_t cells) {
  std::vector<double> v = f.array(key);
  if (v.size() != cells) {
    throw InvalidArgument(
        fmt::format(R"({}: "{}" has {} values for {} fluid cells)", f.where(), key, v.size(), cells));
  }
  return v;
}

void read_cells(const RecordLine& f, const Recording& r, CellsSample& c) {
  if (r.version < 2) {
    throw InvalidArgument(fmt::format("{}: a cells line needs a version 2 header", f.where()));
  }
  c.rendered_n = cell_array(f, "rendered_n", r.fluid_cells);
  c.target_n = cell_array(f, "target_n", r.fluid_cells);
  c.law_n = cell_array(f, "law_n", r.fluid_cells);
  c.floor_n = cell_array(f, "floor_n", r.fluid_cells);
  c.ceiling_n = cell_array(f, "ceiling_n", r.fluid_cells);
  c.loaded = cell_array(f, "loaded", r.fluid_cells);
  for (const double l : c.loaded) {
    if (l != 0.0 && l != 1.0) {
      throw InvalidArgument(fmt::format(R"({}: "loaded" holds 0 or 1 per cell)", f.where()));
    }
  }
}

void read_event(const RecordLine& f, Recording& r, RecordedEvent& e) {
  const std::string& where = f.where();
  const std::string& dir = f.text("dir");
  if (dir != "tx" && dir != "rx") {
    throw InvalidArgument(fmt::format(R"({}: dir must be "tx" or "rx", not "{}")", where, dir));
  }
  e.tx = dir == "tx";
  e.kind = f.text("kind");
  if (e.tx && e.kind == "state") {
    e.request = f.text("request");
    if (e.request != "enable" && e.request != "disable" && e.request != "pause" && e.request != "estop") {
      throw InvalidArgument(fmt::format("{}: unknown state request \"{}\"", where, e.request));
    }
  } else if (e.tx && e.kind == "currents") {
    e.values = f.array("values");
    DeviceInfo recorded;
    recorded.valves = r.valves;
    recorded.max_current_A = r.max_current_a;
    check_currents(e.values, recorded, where);
  } else if (e.tx && e.kind == "targets") {
    e.first = f.index("first");
    e.values = f.array("values");
    if (e.values.size() != 4) {
      throw InvalidArgument(
          fmt::format("{}: a target has 4 values: stiffness N/m, offset m, ceiling N, validity s", where));
    }
  } else if (!e.tx && e.kind == "telemetry") {
    e.device_time_s = f.number("device_time_s");
    e.first = f.index("first");
    e.values = f.array("values");
  } else if (!e.tx && e.kind == "status") {
    e.state = f.text("state");
    e.fault = f.text("fault");
  } else if (!e.tx && e.kind == "cells") {
    read_cells(f, r, e.cells);
  } else {
    throw InvalidArgument(fmt::format("{}: unknown event {} \"{}\"", where, dir, e.kind));
  }
}

}  // namespace

Recording read_recording(const std::string& path) {
  std::ifstream in(path);
  if (!in) {
    throw InvalidArgument(fmt::format("cannot read {}: {}", path, std::strerror(errno)));
  }
  Recording r;
  std::string text;
  std::size_t n = 0;
  double last_t_s = 0.0;
  while (std::getline(in, text)) {
    ++n;
    const std::string where = fmt::format("{}:{}", path, n);
    if (text.empty() || text.find_first_not_of(" \t\r") == std::string::npos) {
      continue;
    }
    const RecordLine f(text, where);
    if (n == 1) {
      read_header(f, r);
      continue;
    }
    RecordedEvent e;
    e.line = n;
    e.t_s = f.number("t_s");
    if (!(e.t_s >= last_t_s) || !std::isfinite(e.t_s)) {
      throw InvalidArgument(
          fmt::format("{}: t_s {} goes back in time (previous {})", where, e.t_s, last_t_s));
    }
    last_t_s = e.t_s;
    read_event(f, r, e);
    r.events.push_back(std::move(e));
  }
  if (n == 0) {
    throw InvalidArgument(fmt::format("{}:1: empty file; expected a {} header", path, kRecordFormat));
  }
  return r;
}

}  // namespace mrskin::ctl
