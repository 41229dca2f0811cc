#!/bin/sh
# The 5 x 5 tick's instructions per tick over the demo on the perturbed mock (issue 19's
# reference): maximum and percentiles of demo_callgrind_probe's per-tick dumps.
#   demo_callgrind_max.sh PROBE OUT_DIR [TICKS [GOLDEN_FILE]]
# Prints "max N (first tick N) p50 N p99 N ticks N": max over every tick but the first (it sends
# the first frames), the first apart. With GOLDEN_FILE, fails when the max is above the file's
# (tests/bridge/golden/demo_instructions.txt: a refactoring must not raise it). Exits 77
# (ctest: skipped) when valgrind is missing.
probe=$1 out=$2 ticks=${3:-3000} golden=$4
if ! command -v valgrind >/dev/null 2>&1; then
  echo "SKIPPED: valgrind not found (apt-get install valgrind)"
  exit 77
fi
rm -rf "$out" && mkdir -p "$out" || exit 1
if ! valgrind --tool=callgrind --instr-atstart=no --collect-atstart=no --dump-instr=no \
    --callgrind-out-file="$out/tick.%p" "$probe" "$ticks" >"$out/probe.log" 2>&1; then
  echo "probe failed:"; tail -20 "$out/probe.log"
  exit 1
fi
# One dump per tick (tick.PID.N); the last file (no suffix) holds what ran after the loop.
first=$(ls "$out"/tick.*.1 2>/dev/null | head -n 1)
[ -n "$first" ] || { echo "no per-tick dumps in $out"; exit 1; }
for f in "$out"/tick.*.*; do
  [ "$f" = "$first" ] || sed -n 's/^totals: \([0-9]*\).*/\1/p' "$f"
done | sort -n >"$out/per_tick.txt"
n=$(wc -l <"$out/per_tick.txt")
pick() { sed -n "$(( ($1 * n + 99) / 100 ))p" "$out/per_tick.txt"; }
max=$(tail -n 1 "$out/per_tick.txt")
echo "max $max (first tick $(sed -n 's/^totals: \([0-9]*\).*/\1/p' "$first")) p50 $(pick 50) p99 $(pick 99) ticks $((n + 1))"
if [ -n "$golden" ]; then
  limit=$(sed -n 's/^max \([0-9]*\).*/\1/p' "$golden")
  [ -n "$limit" ] || { echo "no 'max N' line in $golden"; exit 1; }
  if [ "$max" -gt "$limit" ]; then
    echo "FAILED: the tick's maximum rose above the reference $limit ($golden)"
    exit 1
  fi
  echo "at most the reference $limit"
fi
