// mrskin-model-bench: run time against error of the device model, published as CSV and SVG.
//
//   mrskin-model-bench [--suite valve|network|inverse|design|plant|all] [--out DIR] [--reps N] [--profile
//   FILE]
//                      [--check] [--quick]
//
// --out (default: ./model-bench-out) is created when missing; the committed results in
// tools/model-bench/results change only when it is named explicitly (docs/model.md).
//
// Suites (one function each in suites.hpp; add a new one there and to kSuites below):
//   valve    every valve law timed per call and its error over the stated range (valve_bench.cpp)
//   network  every network stepper and step size against a fine reference, and the step's
//            cost from 5x5 to 64x64 with 1-100 % of cells in contact (network_bench.cpp)
//   inverse  the fast CellInverse against the slow exact solve: force error and time per solve
//            (inverse_bench.cpp)
//   design   the design study: searches the profile's design parameters for the largest coverage
//            of the organ scenes under stated constraints, writes designed.toml and a plot per
//            parameter (design_bench.cpp; about a minute; docs/model.md, "The design study")
//   plant    the mock device's plant: time per substep on every built-in grid, idle and pressed,
//            with its settled-field reuse on and off (plant_bench.cpp; about a minute)
//   all      valve, network and inverse, in that order (default; design and plant only when named)
// --reps applies to the valve suite; --profile to the valve suite and to design (its base);
// --quick makes design short (one scene cycle, a coarse search: the test's mode); --check exits 1
// unless the fast valve law is within 0.5 % and at least 10x faster than the exact one. A progress
// bar is drawn on stderr when it is a terminal. Exit codes: 0, 1 (a suite failed, --check unmet;
// design: no design meets the constraints, or the written one covers less than its base), 2 (bad
// argument).
#include <array>
#include <exception>
#include <filesystem>
#include <iostream>
#include <string>
#include <system_error>

#include "exit_codes.hpp"
#include "logging.hpp"
#include "mrskin/driver/version.hpp"
#include "suites.hpp"

namespace {

using mrskin::bench::BenchOptions;

struct Suite {
  const char* name;
  int (*run)(const BenchOptions&);
};
struct SuiteEntry {
  Suite suite;
  bool in_all;  // run by --suite all
};
constexpr std::array<SuiteEntry, 5> kSuites = {{
    {{"valve", &mrskin::bench::run_valve_suite}, true},
    {{"network", &mrskin::bench::run_network_suite}, true},
    {{"inverse", &mrskin::bench::run_inverse_suite}, true},
    {{"design", &mrskin::bench::run_design_suite}, false},
    {{"plant", &mrskin::bench::run_plant_suite}, false},
}};

int run(int argc, char** argv) {
  mrskin::tools::CliApp cli{
      "mrskin-model-bench: run time against error of the device model, and the design study, written as CSV "
      "and SVG"};
  mrskin::tools::CliCommand app = cli.root();
  app.version_flag("--version", std::string(mrskin::library_version()));
  std::string log_level;
  mrskin::tools::add_log_level_option(app, log_level);
  BenchOptions o;
  o.out = "model-bench-out";
  std::string suite = "all";
  app.option("--suite", suite, "The suite to run")
      .one_of({"valve", "network", "inverse", "design", "plant", "all"})
      .show_default();
  app.option("--out", o.out, "Directory for the CSV and SVG files (created when missing)").show_default();
  app.option("--reps", o.reps, "Timing repetitions of the valve suite").range(3, 1000000).show_default();
  app.option("--profile", o.profile,
             "Device profile file for the valve suite, and the design suite's base (default: mr-skin-5x5)")
      .existing_file();
  app.flag("--quick", o.quick, "design suite: one scene cycle and a coarse search (about 10 s)");
  app.footer(
      "Suites: valve, network and inverse time the model's laws against their error (all runs these "
      "three); design searches the profile's design parameters for the organ scenes' envelope coverage "
      "under stated constraints and writes designed.toml, design_coverage.csv, design_search.csv and a "
      "design_<parameter>.svg each (about 1.5 min; docs/model.md, section 11a); plant times the mock "
      "device's plant per substep on every built-in grid and writes plant_substep.csv (about a minute; "
      "docs/bridge.md, \"Every grid in real time\").\n"
      "Exit codes: 0 done; 1 a suite failed (--check unmet; design: no candidate meets the constraints, "
      "or the written profile fails one or covers the organs less than its base); 2 bad argument.");
  app.flag("--check", o.check,
           "Exit 1 unless the fast valve law is within 0.5 % and at least 10x faster than the exact one");
  if (const mrskin::tools::CliParse parsed = cli.parse(argc, argv); !parsed.run) {
    // --help and --version exit 0; every bad argument is a usage error (2).
    return parsed.exit_code == 0 ? mrskin::tools::kOk : mrskin::tools::kUsage;
  }
  mrskin::tools::set_log_level(log_level);
  std::error_code ec;
  std::filesystem::create_directories(o.out, ec);
  if (ec || !std::filesystem::is_directory(o.out)) {
    std::cerr << "mrskin-model-bench: cannot create --out " << o.out << ": "
              << (ec ? ec.message() : std::string("not a directory")) << "\n";
    return mrskin::tools::kUsage;
  }
  int rc = mrskin::tools::kOk;
  for (const auto& [s, in_all] : kSuites) {
    if ((suite == "all" && in_all) || suite == s.name) {
      std::cout << "== " << s.name << "\n";
      const int r = s.run(o);
      rc = rc != mrskin::tools::kOk ? rc : r;
    }
  }
  return rc;
}

}  // namespace

int main(int argc, char** argv) {
  mrskin::tools::init_logging("mrskin-model-bench");
  try {
    return run(argc, argv);
  } catch (...) {
    return mrskin::tools::exit_code_for_current_exception();
  }
}
