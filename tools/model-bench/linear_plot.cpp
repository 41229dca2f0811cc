#include "linear_plot.hpp"

#include <algorithm>
#include <fstream>
#include <iostream>

namespace mrskin::bench {

bool LinearPlot::write(const std::string& path) const {
  std::ofstream f(path);
  if (!f) {
    std::cerr << "cannot write " << path << "\n";
    return false;
  }
  const double w = 560 + legend_width;
  const double h = 400;
  const double ml = 80;
  const double mt = 60;
  const double mb = 55;
  const double mr = legend_width;
  const double x_span = x_hi > x_lo ? x_hi - x_lo : 1.0;
  const double y_span = y_hi > y_lo ? y_hi - y_lo : 1.0;
  auto sx = [&](double v) {
    return ml + (std::clamp(v, x_lo, x_lo + x_span) - x_lo) / x_span * (w - ml - mr);
  };
  auto sy = [&](double v) {
    return mt + (y_lo + y_span - std::clamp(v, y_lo, y_lo + y_span)) / y_span * (h - mt - mb);
  };
  auto g = [](double v) { return general(v, 6); };
  svg_open(f, w, h, ml, title, subtitle);
  for (int k = 0; k <= x_ticks; ++k) {
    const double v = x_lo + x_span * k / std::max(x_ticks, 1);
    svg_line(f, sx(v), mt, sx(v), h - mb, "stroke='#ddd'");
    svg_text(f, sx(v), h - mb + 18, "text-anchor='middle'", general(v, 3));
  }
  for (int k = 0; k <= y_ticks; ++k) {
    const double v = y_lo + y_span * k / std::max(y_ticks, 1);
    svg_line(f, ml, sy(v), w - mr, sy(v), "stroke='#ddd'");
    svg_text(f, ml - 6, sy(v) + 4, "text-anchor='end'", general(v, 3));
  }
  f << "<rect x='" << g(ml) << "' y='" << g(mt) << "' width='" << g(w - ml - mr) << "' height='"
    << g(h - mt - mb) << "' fill='none' stroke='black'/>\n";
  svg_text(f, (ml + w - mr) / 2, h - 16, "text-anchor='middle'", x_label);
  const double ymid = (mt + h - mb) / 2;
  svg_text(f, 18, ymid, "transform='rotate(-90 18 " + g(ymid) + ")' text-anchor='middle'", y_label);
  double legend_y = mt + 10;
  for (const RefLine& r : refs) {
    const std::string style = "stroke='" + r.colour + "' stroke-dasharray='6,4'";
    if (r.vertical) {
      svg_line(f, sx(r.at), mt, sx(r.at), h - mb, style);
    } else {
      svg_line(f, ml, sy(r.at), w - mr, sy(r.at), style);
    }
    // Labels go in the legend: several lines may share one x.
    svg_line(f, w - mr + 8, legend_y - 4, w - mr + 28, legend_y - 4, style);
    svg_text(f, w - mr + 34, legend_y, "", r.label);
    legend_y += 18;
  }
  for (const PlotSeries& s : series) {
    if (s.line && s.points.size() > 1) {
      svg_polyline(f, s, sx, sy);
    }
    for (const PlotPoint& p : s.points) {
      f << "<circle cx='" << g(sx(p.x)) << "' cy='" << g(sy(p.y)) << "' r='3.5' fill='" << s.colour
        << "'/>\n";
      if (!p.label.empty()) {
        svg_text(f, sx(p.x) + 6, sy(p.y) - 5, "font-size='10' fill='" + s.colour + "'", p.label);
      }
    }
    svg_line(f, w - mr + 8, legend_y - 4, w - mr + 28, legend_y - 4,
             "stroke='" + s.colour + "' stroke-width='2'");
    svg_text(f, w - mr + 34, legend_y, "", s.name);
    legend_y += 18;
  }
  f << "</svg>\n";
  return static_cast<bool>(f);
}

}  // namespace mrskin::bench
