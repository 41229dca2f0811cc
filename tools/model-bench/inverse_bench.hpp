// Inverse suite: CellInverse (the loop's allocation) against the slow exact solve of the same
// objective, timed and measured in one run. Writes
//   <out>/inverse_cases.csv   every case: kind, loaded cells, fast and slow time per solve, the
//                             exact rendered force error of each (max and RMS over the loaded
//                             cells, N), the fast model's own residual
//   <out>/inverse_methods.csv per method and kind: median time per solve, median / p95 / max error
//   <out>/inverse_time_vs_error.svg
// Cases (fixed seed): single cells with targets inside their envelope; targets made by the exact
// model from random currents on 1-3 cells (a solution exists); independent targets on two or three
// neighbouring cells (they may conflict through shared valves); and one press tracked at 1 kHz
// (the warm path, every target changing every tick). Wall clock on a shared machine: medians.
#pragma once

#include <string>

#include "bench_common.hpp"
#include "mrskin/driver/model/device_model.hpp"
#include "suites.hpp"  // run_inverse_suite, the same as a model-bench suite

namespace mrskin::bench {

// The suite proper; `progress` draws a progress bar on stderr (when it is a terminal). Returns
// the process exit code (0; 1 when a file cannot be written or a solve fails).
int run_inverse_bench(const std::string& out_dir, const model::DeviceModel& model, bool progress);

}  // namespace mrskin::bench
