// The model-bench suites, selected by `--suite`. Each writes its CSV and SVG files into
// options.out, prints a summary and returns the process exit code.
#pragma once

#include "bench_common.hpp"

namespace mrskin::bench {

int run_valve_suite(const BenchOptions& o);    // valve laws: exact, Wereley-Pang, fast
int run_network_suite(const BenchOptions& o);  // network steppers and scaling
int run_inverse_suite(const BenchOptions& o);  // the inverse against the slow exact solve
int run_design_suite(const BenchOptions& o);   // the design study: coverage of the organ scenes
int run_plant_suite(const BenchOptions& o);    // the mock's plant: time per substep on every grid

}  // namespace mrskin::bench
