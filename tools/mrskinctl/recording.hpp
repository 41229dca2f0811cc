// A recording of mrskinctl record, read back (format: ctl_device_record.hpp, docs/cli.md "record,
// replay"): versions 1 and 2. Shared by replay and plot.
#pragma once

#include <cstddef>
#include <string>
#include <vector>

namespace mrskin::ctl {

// Version 2's per-cell picture of a bridged run (one "cells" line, fluid cells in grid order).
struct CellsSample {
  std::vector<double> rendered_n;  // the truth (mock) or the observer's estimate: the header says
  std::vector<double> target_n;    // the law clamped into the envelope
  std::vector<double> law_n;       // the tissue law, not clamped
  std::vector<double> floor_n;     // the envelope, where loaded (0 elsewhere)
  std::vector<double> ceiling_n;
  std::vector<double> loaded;  // 1 where the bridge loaded the cell, else 0
};

struct RecordedEvent {
  std::size_t line = 0;
  double t_s = 0.0;
  bool tx = false;
  std::string kind;
  std::string request;  // state requests
  std::string state;    // status
  std::string fault;
  std::size_t first = 0;
  double device_time_s = 0.0;
  std::vector<double> values;
  CellsSample cells;  // kind "cells"
};

struct Recording {
  int version = 0;
  std::string uri;
  std::size_t valves = 0;
  std::size_t fluid_cells = 0;
  std::size_t sensors = 0;
  std::string sensor_unit;
  double max_current_a = 0.0;
  std::string rendered = "none";  // version 2: "truth", "observer" or "none" (no cells lines)
  std::vector<RecordedEvent> events;
};

// Reads and checks a whole recording. Throws InvalidArgument naming the file, the line and what
// is wrong (not the format, an unknown event, a value of the wrong type or size, time going back).
Recording read_recording(const std::string& path);

}  // namespace mrskin::ctl
