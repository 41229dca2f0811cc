#!/bin/bash
# vm-result.sh WORK PART: one part's result from the VM run of Vm.boot (vm-suite.sh): prints
# its log and exits with its exit code; 77 when the VM run was skipped.
set -euo pipefail
work=$1
part=$2
results=$work/results
if [ -f "$results/SKIP" ]; then
  cat "$results/SKIP"
  exit 77
fi
if [ ! -f "$results/$part.rc" ]; then
  echo "vm-result: no result for $part (did Vm.boot run? see $results/harness.log)"
  exit 1
fi
cat "$results/$part.log"
exit "$(cat "$results/$part.rc")"
