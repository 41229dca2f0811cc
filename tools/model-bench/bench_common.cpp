#include "bench_common.hpp"

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iomanip>
#include <iostream>
#include <numeric>
#include <sstream>
#include <utility>

namespace mrskin::bench {

namespace {
volatile double g_sink = 0.0;  // NOLINT(cppcoreguidelines-avoid-non-const-global-variables)
}  // namespace

void keep(double v) noexcept { g_sink = g_sink + v; }

std::vector<std::size_t> pressed_cells(const model::DeviceModel& m, double fraction) {
  const auto& cells = m.layout().fluid_cells();
  const int r0 = m.profile().design.row;
  const int c0 = m.profile().design.col;
  std::vector<std::size_t> order(cells.size());
  std::iota(order.begin(), order.end(), 0);
  auto dist = [&](std::size_t i) {
    const int dr = cells[i].row - r0;
    const int dc = cells[i].col - c0;
    return dr * dr + dc * dc;
  };
  std::stable_sort(order.begin(), order.end(),
                   [&](std::size_t a, std::size_t b) { return dist(a) < dist(b); });
  const auto n = std::max<std::size_t>(
      1, static_cast<std::size_t>(std::lround(fraction * static_cast<double>(cells.size()))));
  order.resize(std::min(n, order.size()));
  return order;
}

double percentile(std::vector<double> v, double p) {
  if (v.empty()) {
    return 0.0;
  }
  std::sort(v.begin(), v.end());
  const double idx = p * static_cast<double>(v.size() - 1);
  const auto lo = static_cast<std::size_t>(std::floor(idx));
  const auto hi = std::min(lo + 1, v.size() - 1);
  return v[lo] + (v[hi] - v[lo]) * (idx - static_cast<double>(lo));
}

std::string fixed(double v, int prec) {
  std::ostringstream s;
  s << std::fixed << std::setprecision(prec) << v;
  return s.str();
}
std::string sci(double v, int prec) {
  std::ostringstream s;
  s << std::scientific << std::setprecision(prec) << v;
  return s.str();
}
std::string general(double v, int prec) {
  std::ostringstream s;
  s << std::setprecision(prec) << v;
  return s.str();
}
std::string signed_sci(double v, int prec) {
  std::string s = v >= 0.0 ? "+" : "";
  s += sci(v, prec);
  return s;
}
std::string pad(const std::string& s, std::size_t width, bool left) {
  if (s.size() >= width) {
    return s;
  }
  return left ? s + std::string(width - s.size(), ' ') : std::string(width - s.size(), ' ') + s;
}

Progress::Progress(std::string label, std::size_t total)
    : label_(std::move(label)), total_(std::max<std::size_t>(total, 1)), tty_(isatty(STDERR_FILENO) != 0) {
  draw("");
}

Progress::~Progress() {
  if (tty_) {
    std::fputs("\n", stderr);
  }
}

void Progress::tick(const std::string& what) {
  done_ = std::min(done_ + 1, total_);
  draw(what);
}

void Progress::draw(const std::string& what) const {
  if (!tty_) {
    return;
  }
  constexpr std::size_t kWidth = 30;
  const std::size_t filled = kWidth * done_ / total_;
  std::string bar(filled, '=');
  if (filled < kWidth) {
    bar += '>';
    bar += std::string(kWidth - filled - 1, ' ');
  }
  const std::string line = "\r\033[K" + label_ + " [" + bar + "] " + std::to_string(done_) + "/" +
                           std::to_string(total_) + " " + what;
  std::fputs(line.c_str(), stderr);
  std::fflush(stderr);
}

void svg_open(std::ostream& f, double width, double height, double left, const std::string& title,
              const std::string& subtitle) {
  f << "<svg xmlns='http://www.w3.org/2000/svg' width='" << general(width, 6) << "' height='"
    << general(height, 6)
    << "' font-family='sans-serif' font-size='12'>\n<rect width='100%' height='100%' fill='white'/>\n";
  svg_text(f, left, 22, "font-size='15' font-weight='bold'", title);
  svg_text(f, left, 40, "fill='#555'", subtitle);
}

void svg_line(std::ostream& f, double xa, double ya, double xb, double yb, const std::string& style) {
  f << "<line x1='" << general(xa, 6) << "' y1='" << general(ya, 6) << "' x2='" << general(xb, 6) << "' y2='"
    << general(yb, 6) << "' " << style << "/>\n";
}

void svg_text(std::ostream& f, double x, double y, const std::string& attrs, const std::string& body) {
  f << "<text x='" << general(x, 6) << "' y='" << general(y, 6) << "' " << attrs << ">" << body
    << "</text>\n";
}

void svg_polyline(std::ostream& f, const PlotSeries& s, const std::function<double(double)>& sx,
                  const std::function<double(double)>& sy) {
  f << "<polyline fill='none' stroke='" << s.colour << "' stroke-width='1.5'"
    << (s.dash.empty() ? "" : " stroke-dasharray='" + s.dash + "'") << " points='";
  for (const PlotPoint& p : s.points) {
    f << general(sx(p.x), 6) << ',' << general(sy(p.y), 6) << ' ';
  }
  f << "'/>\n";
}

bool LogLogPlot::write(const std::string& path) const {
  std::ofstream f(path);
  if (!f) {
    std::cerr << "cannot write " << path << "\n";
    return false;
  }
  const double mr = legend ? legend_width : 30;
  const double w = 730 + mr;
  const double h = 520;
  const double ml = 90;
  const double mt = 60;
  const double mb = 60;
  auto sx = [&](double v) {
    const double lv = std::clamp(std::log10(v), static_cast<double>(x_lo), static_cast<double>(x_hi));
    return ml + (lv - x_lo) / (x_hi - x_lo) * (w - ml - mr);
  };
  auto sy = [&](double v) {
    const double lv = std::clamp(std::log10(v), static_cast<double>(y_lo), static_cast<double>(y_hi));
    return mt + (y_hi - lv) / (y_hi - y_lo) * (h - mt - mb);
  };
  auto g = [](double v) { return general(v, 6); };
  auto line = [&f](double xa, double ya, double xb, double yb, const std::string& style) {
    svg_line(f, xa, ya, xb, yb, style);
  };
  auto text = [&f](double x, double y, const std::string& attrs, const std::string& body) {
    svg_text(f, x, y, attrs, body);
  };
  svg_open(f, w, h, ml, title, subtitle);
  for (int e = x_lo; e <= x_hi; ++e) {
    const double x = sx(std::pow(10.0, e));
    line(x, mt, x, h - mb, "stroke='#ddd'");
    text(x, h - mb + 18, "text-anchor='middle'", x_tick(std::pow(10.0, e)));
  }
  for (int e = y_lo; e <= y_hi; e += y_tick_every) {
    const double y = sy(std::pow(10.0, e));
    line(ml, y, w - mr, y, "stroke='#ddd'");
    text(ml - 6, y + 4, "text-anchor='end'", y_tick(std::pow(10.0, e)));
  }
  f << "<rect x='" << g(ml) << "' y='" << g(mt) << "' width='" << g(w - ml - mr) << "' height='"
    << g(h - mt - mb) << "' fill='none' stroke='black'/>\n";
  text((ml + w - mr) / 2, h - 18, "text-anchor='middle'", x_label);
  const double ymid = (mt + h - mb) / 2;
  text(18, ymid, "transform='rotate(-90 18 " + g(ymid) + ")' text-anchor='middle'", y_label);
  for (const RefLine& r : refs) {
    const std::string style = "stroke='" + r.colour + "' stroke-dasharray='6,4'";
    if (r.vertical) {
      const double x = sx(r.at);
      line(x, mt, x, h - mb, style);
      text(x + 4, mt + 14, "fill='" + r.colour + "'", r.label);
    } else {
      const double y = sy(r.at);
      line(ml, y, w - mr, y, style);
      text(w - mr - 4, y - 5, "fill='" + r.colour + "' text-anchor='end'", r.label);
    }
  }
  double legend_y = mt + 10;
  for (const PlotSeries& s : series) {
    if (s.line && s.points.size() > 1) {
      svg_polyline(f, s, sx, sy);
    }
    for (const PlotPoint& p : s.points) {
      f << "<circle cx='" << g(sx(p.x)) << "' cy='" << g(sy(p.y)) << "' r='4' fill='" << s.colour << "'/>\n";
      if (!p.label.empty()) {
        text(sx(p.x) + 7, sy(p.y) - 5, "font-size='10' fill='" + s.colour + "'", p.label);
      }
    }
    if (legend) {
      line(w - mr + 8, legend_y - 4, w - mr + 28, legend_y - 4,
           "stroke='" + s.colour + "' stroke-width='2'" +
               (s.dash.empty() ? "" : " stroke-dasharray='" + s.dash + "'"));
      text(w - mr + 34, legend_y, "", s.name);
      legend_y += 18;
    }
  }
  f << "</svg>\n";
  return static_cast<bool>(f);
}

}  // namespace mrskin::bench
