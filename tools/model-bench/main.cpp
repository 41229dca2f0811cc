// mrskin-model-bench: run time against error of the device model, published as CSV and SVG.
//
//   mrskin-model-bench [--suite valve|network|inverse|all] [--out DIR] [--reps N] [--profile FILE] [--check]
//
// Suites (one function each in suites.hpp; add a new one there and to kSuites below):
//   valve    every valve law timed per call and its error over the stated range (valve_bench.cpp)
//   network  every network stepper and step size against a fine reference, and the step's
//            cost from 5x5 to 64x64 with 1-100 % of cells in contact (network_bench.cpp)
//   inverse  the fast CellInverse against the slow exact solve: force error and time per solve
//            (inverse_bench.cpp)
//   all      every suite, in that order (default)
// --reps and --profile apply to the valve suite; --check exits 1 unless the fast valve law is
// within 0.5 % and at least 10x faster than the exact one. A progress bar is drawn on stderr
// when it is a terminal.
#include <algorithm>
#include <array>
#include <cstdlib>
#include <iostream>
#include <string>
#include <vector>

#include "suites.hpp"

namespace {

using mrskin::bench::BenchOptions;

struct Suite {
  const char* name;
  int (*run)(const BenchOptions&);
};
constexpr std::array<Suite, 3> kSuites = {{
    {"valve", &mrskin::bench::run_valve_suite},
    {"network", &mrskin::bench::run_network_suite},
    {"inverse", &mrskin::bench::run_inverse_suite},
}};

int usage() {
  std::cerr << "usage: mrskin-model-bench [--suite valve|network|inverse|all] [--out DIR] [--reps N] "
               "[--profile FILE] [--check]\n";
  return 2;
}

}  // namespace

int main(int argc, char** argv) {
  const std::vector<std::string> args(argv + 1, argv + argc);
  BenchOptions o;
  std::string suite = "all";
  for (std::size_t i = 0; i < args.size(); ++i) {
    const std::string& a = args[i];
    if (a == "--out" && i + 1 < args.size()) {
      o.out = args[++i];
    } else if (a == "--reps" && i + 1 < args.size()) {
      o.reps = std::max(3, std::atoi(args[++i].c_str()));
    } else if (a == "--profile" && i + 1 < args.size()) {
      o.profile = args[++i];
    } else if (a == "--check") {
      o.check = true;
    } else if (a == "--suite" && i + 1 < args.size()) {
      suite = args[++i];
    } else {
      return usage();
    }
  }
  bool known = suite == "all";
  int rc = 0;
  for (const Suite& s : kSuites) {
    if (suite == "all" || suite == s.name) {
      known = true;
      std::cout << "== " << s.name << "\n";
      const int r = s.run(o);
      rc = rc != 0 ? rc : r;
    }
  }
  return known ? rc : usage();
}
