// A linear-axis SVG plot for the model bench (LogLogPlot draws log-log only): one frame, series
// of points joined or not, vertical or horizontal reference lines, a legend on the right.
#pragma once

#include <string>
#include <vector>

#include "bench_common.hpp"

namespace mrskin::bench {

struct LinearPlot {
  std::string title;
  std::string subtitle;
  std::string x_label;
  std::string y_label;
  double x_lo = 0.0;
  double x_hi = 1.0;
  double y_lo = 0.0;
  double y_hi = 1.0;
  int x_ticks = 5;  // intervals between labelled grid lines
  int y_ticks = 5;
  std::vector<PlotSeries> series;
  std::vector<RefLine> refs;
  double legend_width = 230;  // px right of the frame
  // false (and a message on stderr) when the file cannot be written.
  [[nodiscard]] bool write(const std::string& path) const;
};

}  // namespace mrskin::bench
