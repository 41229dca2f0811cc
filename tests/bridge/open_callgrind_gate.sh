#!/bin/sh
# Issue 21's gate on opening a unit: open_callgrind_probe (open_device on the mock, a Bridge
# built, enabled and ticked 10 times) under callgrind must cost at most LIMIT instructions.
#   open_callgrind_gate.sh PROBE OUT_DIR LIMIT [URI]
# Exits 77 (ctest: skipped) when valgrind is missing.
probe=$1 out=$2 limit=$3 uri=${4:-mock://palm-64x64}
if ! command -v valgrind >/dev/null 2>&1; then
  echo "SKIPPED: valgrind not found (apt-get install valgrind)"
  exit 77
fi
mkdir -p "$out" || exit 1
file=$out/callgrind.open.out
if ! log=$(valgrind --tool=callgrind --instr-atstart=no --collect-atstart=no --callgrind-out-file="$file" \
    "$probe" "$uri" 2>"$file.log"); then
  echo "probe failed:"; echo "$log"; tail -20 "$file.log"
  exit 1
fi
total=$(sed -n 's/^totals: \([0-9]*\).*/\1/p' "$file")
[ -n "$total" ] || { echo "no totals in $file"; exit 1; }
echo "$log"
echo "opening $uri: $total instructions (limit $limit)"
if [ "$total" -gt "$limit" ]; then
  echo "FAILED: opening costs more than $limit instructions"
  exit 1
fi
