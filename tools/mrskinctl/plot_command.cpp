// mrskinctl plot: a recording's per-cell picture (version 2 "cells" lines, written by
// `mrskinctl record --bridge`) as an SVG: per cell, the envelope band, the target, the tissue law
// and the rendered force over time, with the stretches where the law lay outside the envelope
// (clamped) marked. docs/cli.md, "plot".
#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <memory>
#include <string>
#include <vector>

#include "command.hpp"
#include "exit_codes.hpp"
#include "json_text.hpp"
#include "mrskin/driver/errors.hpp"
#include "recording.hpp"

namespace mrskin::ctl {
namespace {

struct PlotOptions {
  std::string file;
  std::string out;
  std::vector<std::size_t> cells;  // empty: the loaded ones
  std::size_t max_cells = 12;
};

// A law this far outside the envelope counts as clamped (the statistics' own test is the solve's;
// this one sees only the recorded numbers, at 10 ms).
constexpr double kClampTolerance_N = 1e-3;

struct Samples {
  std::vector<double> t_s;
  std::vector<const CellsSample*> cells;
};

Samples cells_of(const Recording& r) {
  Samples s;
  for (const RecordedEvent& e : r.events) {
    if (e.kind == "cells") {
      s.t_s.push_back(e.t_s);
      s.cells.push_back(&e.cells);
    }
  }
  return s;
}

bool clamped(const CellsSample& c, std::size_t i) {
  return c.loaded[i] != 0.0 &&
         (c.law_n[i] < c.floor_n[i] - kClampTolerance_N || c.law_n[i] > c.ceiling_n[i] + kClampTolerance_N);
}

// The cells to draw: those asked for, else the most often loaded (at most max_cells, in grid order).
std::vector<std::size_t> cells_to_draw(const PlotOptions& o, const Recording& r, const Samples& s) {
  for (const std::size_t c : o.cells) {
    if (c >= r.fluid_cells) {
      throw InvalidArgument(
          fmt::format("plot: cell {} is not in the recording (fluid cells 0..{})", c, r.fluid_cells - 1));
    }
  }
  if (!o.cells.empty()) {
    return o.cells;
  }
  std::vector<std::size_t> loaded_samples(r.fluid_cells, 0);
  for (const CellsSample* c : s.cells) {
    for (std::size_t i = 0; i < r.fluid_cells; ++i) {
      loaded_samples[i] += c->loaded[i] != 0.0 ? 1U : 0U;
    }
  }
  std::vector<std::size_t> order;
  for (std::size_t i = 0; i < r.fluid_cells; ++i) {
    if (loaded_samples[i] > 0) {
      order.push_back(i);
    }
  }
  std::stable_sort(order.begin(), order.end(),
                   [&](std::size_t a, std::size_t b) { return loaded_samples[a] > loaded_samples[b]; });
  order.resize(std::min(order.size(), o.max_cells));
  std::sort(order.begin(), order.end());
  return order;
}

std::string svg_num(double v) { return fmt::format("{:.1f}", v); }

class Panel {
 public:
  Panel(double x, double y, double w, double h, double t0_s, double t1_s, double f_max_N)
      : x_(x), y_(y), w_(w), h_(h), t0_s_(t0_s), t1_s_(t1_s), f_max_N_(f_max_N) {}
  [[nodiscard]] double px(double t_s) const { return x_ + (t_s - t0_s_) / (t1_s_ - t0_s_) * w_; }
  [[nodiscard]] double py(double f_N) const { return y_ + h_ - std::clamp(f_N / f_max_N_, 0.0, 1.0) * h_; }
  [[nodiscard]] double bottom() const { return y_ + h_; }

 private:
  double x_, y_, w_, h_, t0_s_, t1_s_, f_max_N_;
};

// One polyline per run of samples where `keep` holds.
template <class Keep, class Value>
std::string polylines(const Samples& s, const Panel& p, Keep keep, Value value, const std::string& style) {
  std::string out;
  std::string points;
  const auto flush = [&] {
    if (!points.empty()) {
      out += fmt::format("<polyline fill='none' {} points='{}'/>\n", style, points);
      points.clear();
    }
  };
  for (std::size_t k = 0; k < s.cells.size(); ++k) {
    if (!keep(*s.cells[k])) {
      flush();
      continue;
    }
    points += svg_num(p.px(s.t_s[k])) + "," + svg_num(p.py(value(*s.cells[k]))) + " ";
  }
  flush();
  return out;
}

// The envelope as closed polygons, one per loaded stretch.
std::string envelope_band(const Samples& s, const Panel& p, std::size_t i) {
  std::string out;
  std::size_t k = 0;
  while (k < s.cells.size()) {
    if (s.cells[k]->loaded[i] == 0.0) {
      ++k;
      continue;
    }
    std::size_t end = k;
    while (end < s.cells.size() && s.cells[end]->loaded[i] != 0.0) {
      ++end;
    }
    std::string points;
    for (std::size_t j = k; j < end; ++j) {
      points += svg_num(p.px(s.t_s[j])) + "," + svg_num(p.py(s.cells[j]->ceiling_n[i])) + " ";
    }
    for (std::size_t j = end; j-- > k;) {
      points += svg_num(p.px(s.t_s[j])) + "," + svg_num(p.py(s.cells[j]->floor_n[i])) + " ";
    }
    out += fmt::format("<polygon fill='#cfe3f7' stroke='none' points='{}'/>\n", points);
    k = end;
  }
  return out;
}

std::string clamp_marks(const Samples& s, const Panel& p, std::size_t i, std::size_t& clamped_samples) {
  std::string out;
  for (std::size_t k = 0; k < s.cells.size(); ++k) {
    if (!clamped(*s.cells[k], i)) {
      continue;
    }
    ++clamped_samples;
    const double x0 = p.px(s.t_s[k]);
    const double x1 = k + 1 < s.cells.size() ? p.px(s.t_s[k + 1]) : x0 + 1.0;
    out += fmt::format("<rect class='clamped' x='{}' y='{}' width='{}' height='5' fill='#d62728'/>\n",
                       svg_num(x0), svg_num(p.bottom() - 5.0), svg_num(std::max(1.0, x1 - x0)));
  }
  return out;
}

struct PlotResult {
  std::string svg;
  std::size_t cells = 0;
  std::size_t loaded_samples = 0;
  std::size_t clamped_samples = 0;
  double duration_s = 0.0;
};

PlotResult plot_svg(const Recording& r, const Samples& s, const std::vector<std::size_t>& cells,
                    const std::string& title) {
  PlotResult result;
  result.cells = cells.size();
  const double t0_s = s.t_s.front();
  const double t1_s = std::max(s.t_s.back(), t0_s + 1e-3);
  result.duration_s = t1_s - t0_s;
  double f_max_N = 0.1;
  for (const CellsSample* c : s.cells) {
    for (const std::size_t i : cells) {
      f_max_N = std::max({f_max_N, c->rendered_n[i], c->target_n[i], c->law_n[i]});
    }
  }
  f_max_N *= 1.15;  // the ceiling may run far above: the band is cut at the panel's top
  const std::size_t columns = std::min<std::size_t>(3, cells.size());
  const std::size_t rows = (cells.size() + columns - 1) / columns;
  constexpr double kPanelW = 360.0;
  constexpr double kPanelH = 170.0;
  constexpr double kLeft = 50.0;
  constexpr double kGapX = 60.0;  // room for the next panel's force label
  constexpr double kGapY = 50.0;
  constexpr double kTop = 160.0;  // below the title and the legend
  const double width = std::max(520.0, kLeft + static_cast<double>(columns) * (kPanelW + kGapX));
  const double height = kTop + static_cast<double>(rows) * (kPanelH + kGapY);
  std::string& out = result.svg;
  out += fmt::format(
      "<svg xmlns='http://www.w3.org/2000/svg' width='{}' height='{}' font-family='sans-serif' "
      "font-size='12'>\n"
      "<rect width='100%' height='100%' fill='white'/>\n"
      "<text x='{}' y='24' font-size='15' font-weight='bold'>{}</text>\n",
      svg_num(width), svg_num(height), svg_num(kLeft), json_escape(title));
  const std::string rendered_name =
      r.rendered == "truth" ? "rendered (the mock's true force)" : "rendered (the observer's estimate)";
  const std::string legend[][2] = {{"#cfe3f7", "envelope (what the valves can render)"},
                                   {"#000000", "target (the law clamped into it)"},
                                   {"#888888", "tissue law (not clamped)"},
                                   {"#ff7f0e", rendered_name},
                                   {"#d62728", "clamped: the law outside the envelope"}};
  double ly = 44.0;
  for (const auto& [colour, name] : legend) {
    out += fmt::format(
        "<rect x='{}' y='{}' width='18' height='10' fill='{}'/><text x='{}' y='{}'>{}</text>\n",
        svg_num(kLeft), svg_num(ly - 9.0), colour, svg_num(kLeft + 24.0), svg_num(ly), json_escape(name));
    ly += 16.0;
  }
  out += fmt::format("<text x='{}' y='{}' fill='#555'>{}; force 0..{:.2f} N; time {:.2f}..{:.2f} s</text>\n",
                     svg_num(kLeft), svg_num(ly + 4.0), json_escape(r.uri), f_max_N, t0_s, t1_s);
  for (std::size_t n = 0; n < cells.size(); ++n) {
    const std::size_t i = cells[n];
    const std::size_t row = n / columns;  // the panels fill the rows left to right
    const double x = kLeft + static_cast<double>(n % columns) * (kPanelW + kGapX);
    const double y = kTop + static_cast<double>(row) * (kPanelH + kGapY);
    const Panel p(x, y, kPanelW, kPanelH, t0_s, t1_s, f_max_N);
    out += fmt::format("<text x='{}' y='{}' font-weight='bold'>cell {}</text>\n", svg_num(x),
                       svg_num(y - 6.0), i);
    out += envelope_band(s, p, i);
    const auto all = [](const CellsSample&) { return true; };
    const auto loaded = [i](const CellsSample& c) { return c.loaded[i] != 0.0; };
    out += polylines(
        s, p, all, [i](const CellsSample& c) { return c.law_n[i]; },
        "stroke='#888888' stroke-width='1.2' stroke-dasharray='5,3'");
    out += polylines(
        s, p, loaded, [i](const CellsSample& c) { return c.target_n[i]; },
        "stroke='#000000' stroke-width='1.2'");
    out += polylines(
        s, p, all, [i](const CellsSample& c) { return c.rendered_n[i]; },
        "stroke='#ff7f0e' stroke-width='1.5'");
    out += clamp_marks(s, p, i, result.clamped_samples);
    for (const CellsSample* c : s.cells) {
      result.loaded_samples += c->loaded[i] != 0.0 ? 1U : 0U;
    }
    out += fmt::format("<rect x='{}' y='{}' width='{}' height='{}' fill='none' stroke='#444'/>\n", svg_num(x),
                       svg_num(y), svg_num(kPanelW), svg_num(kPanelH));
    out += fmt::format("<text x='{}' y='{}' text-anchor='end' fill='#555'>{:.2f} N</text>\n",
                       svg_num(x - 4.0), svg_num(y + 10.0), f_max_N);
    out += fmt::format("<text x='{}' y='{}' text-anchor='end' fill='#555'>0</text>\n", svg_num(x - 4.0),
                       svg_num(y + kPanelH));
    out += fmt::format(
        "<text x='{}' y='{}' fill='#555'>{:.2f} s</text><text x='{}' y='{}' text-anchor='end' "
        "fill='#555'>{:.2f} s</text>\n",
        svg_num(x), svg_num(y + kPanelH + 14.0), t0_s, svg_num(x + kPanelW), svg_num(y + kPanelH + 14.0),
        t1_s);
  }
  out += "</svg>\n";
  return result;
}

int run_plot(const PlotOptions& o, const GlobalOptions& global) {
  const Recording r = read_recording(o.file);
  const Samples s = cells_of(r);
  if (s.cells.empty()) {
    throw InvalidArgument(fmt::format(
        "plot: {} has no cells lines (version {}); record a bridged run with `mrskinctl record --bridge "
        "--out FILE` (version 2) to get them",
        o.file, r.version));
  }
  const std::vector<std::size_t> cells = cells_to_draw(o, r, s);
  if (cells.empty()) {
    throw InvalidArgument(
        fmt::format("plot: no cell was loaded in {}; name cells with --cells to draw them anyway", o.file));
  }
  const PlotResult p = plot_svg(r, s, cells, std::filesystem::path(o.file).filename().string());
  std::ofstream f(o.out);
  f << p.svg;
  f.close();
  if (!f) {
    throw Error(fmt::format("plot: cannot write {}: {}", o.out, std::strerror(errno)));
  }
  const double clamped_fraction =
      p.loaded_samples == 0 ? 0.0
                            : static_cast<double>(p.clamped_samples) / static_cast<double>(p.loaded_samples);
  if (global.json) {
    fmt::print(R"({{"out": "{}", "cells": {}, "samples": {}, "duration_s": {}, "rendered": "{}", )"
               R"("loaded_samples": {}, "clamped_samples": {}, "clamped_fraction": {}}})"
               "\n",
               json_escape(o.out), p.cells, s.cells.size(), json_number(p.duration_s), r.rendered,
               p.loaded_samples, p.clamped_samples, json_number(clamped_fraction));
  } else {
    fmt::print(
        "plotted {} cells over {:.2f} s ({} samples, rendered: {}) to {}; clamped {:.1f} % of their loaded "
        "samples\n",
        p.cells, p.duration_s, s.cells.size(), r.rendered, o.out, 100.0 * clamped_fraction);
  }
  return tools::kOk;
}

}  // namespace

void add_plot_command(CliCommand app, const GlobalOptions& global, int& exit_code) {
  auto o = std::make_shared<PlotOptions>();
  CliCommand plot = app.subcommand(
      "plot",
      "draw a bridged recording (mrskinctl record --bridge) as an SVG: per cell the envelope, the target, "
      "the "
      "tissue law and the rendered force over time, clamped stretches marked. Exit 0 written, 2 a malformed "
      "file or one without cells lines, 1 the SVG could not be written");
  plot.option("file", o->file, "recording written by mrskinctl record --bridge (version 2)").required();
  plot.option("--out", o->out, "SVG file to write").required();
  plot.option("--cells", o->cells, "fluid cells to draw (comma-separated; default: the loaded ones)")
      .delimiter(',');
  plot.option("--max-cells", o->max_cells, "draw at most this many of the loaded cells, the most loaded")
      .range(1, 64)
      .show_default();
  plot.callback([o, &global, &exit_code] { exit_code = run_plot(*o, global); });
}

}  // namespace mrskin::ctl
