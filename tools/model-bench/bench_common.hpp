// Shared by the model-bench suites: options, number formatting, percentiles, a progress bar on
// stderr (only when it is a terminal) and a log-log SVG plot.
#pragma once

#include <cstddef>
#include <functional>
#include <ostream>
#include <string>
#include <vector>

#include "mrskin/driver/model/device_model.hpp"

namespace mrskin::bench {

struct BenchOptions {
  std::string out = ".";
  std::string profile;  // valve suite: the fluid's profile (default profile if empty)
  int reps = 41;        // valve suite: timing repetitions
  bool check = false;   // valve suite: exit 1 unless the fast law meets its figure
  bool quick = false;   // design suite: one scene cycle, a coarser search (for the test)
};

// The `fraction` of the unit's fluid cells nearest its design cell (at least one), nearest first.
std::vector<std::size_t> pressed_cells(const model::DeviceModel& m, double fraction);

// Keeps timed results observable so that no call is optimised away.
void keep(double v) noexcept;

double percentile(std::vector<double> v, double p);
std::string fixed(double v, int prec);
std::string sci(double v, int prec);
std::string general(double v, int prec);
std::string signed_sci(double v, int prec);
std::string pad(const std::string& s, std::size_t width, bool left = false);

// "[=====>     ] 12/40 label" redrawn on stderr when stderr is a terminal; silent otherwise.
class Progress {
 public:
  Progress(std::string label, std::size_t total);
  ~Progress();
  Progress(const Progress&) = delete;
  Progress& operator=(const Progress&) = delete;
  Progress(Progress&&) = delete;
  Progress& operator=(Progress&&) = delete;
  void tick(const std::string& what = "");

 private:
  void draw(const std::string& what) const;
  std::string label_;
  std::size_t total_;
  std::size_t done_ = 0;
  bool tty_;
};

// SVG markup shared by the plot writers: the document with its title and subtitle at x = left,
// a line, a text.
void svg_open(std::ostream& f, double width, double height, double left, const std::string& title,
              const std::string& subtitle);
void svg_line(std::ostream& f, double xa, double ya, double xb, double yb, const std::string& style);
void svg_text(std::ostream& f, double x, double y, const std::string& attrs, const std::string& body);

struct PlotPoint {
  double x = 0.0;
  double y = 0.0;
  std::string label;  // drawn beside the point when not empty
};
struct PlotSeries {
  std::string name;
  std::string colour;
  std::vector<PlotPoint> points;
  bool line = true;  // join the points
  std::string dash;  // SVG stroke-dasharray of the line ("" solid)
};
// The series' points joined, through the frame's coordinate maps.
void svg_polyline(std::ostream& f, const PlotSeries& s, const std::function<double(double)>& sx,
                  const std::function<double(double)>& sy);

struct RefLine {
  bool vertical = false;
  double at = 0.0;
  std::string label;
  std::string colour = "#c00";
};

// Log-log axes spanning whole decades [10^x_lo, 10^x_hi] x [10^y_lo, 10^y_hi]; points outside
// are clamped to the frame.
struct LogLogPlot {
  std::string title;
  std::string subtitle;
  std::string x_label;
  std::string y_label;
  int x_lo = 0;
  int x_hi = 1;
  int y_lo = 0;
  int y_hi = 1;
  int y_tick_every = 1;
  std::function<std::string(double)> x_tick = [](double v) { return general(v, 3); };
  std::function<std::string(double)> y_tick = [](double v) { return general(v, 3); };
  std::vector<PlotSeries> series;
  std::vector<RefLine> refs;
  bool legend = true;
  double legend_width = 230;  // px right of the frame
  // false (and a message on stderr) when the file cannot be written.
  [[nodiscard]] bool write(const std::string& path) const;
};

}  // namespace mrskin::bench
