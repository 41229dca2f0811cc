#!/usr/bin/env bash
# Runs every protocol fuzzer for SECONDS (default 60), one after the other, starting from
# a copy of the committed seed corpus (the committed corpus stays small), and prints one
# line per fuzzer. Exits non-zero on any finding; crash inputs are kept in the work folder.
#   cmake --preset clang && cmake --build build/clang
#   tests/fuzz/run_fuzzers.sh [SECONDS] [BUILD_DIR]
set -euo pipefail
secs=${1:-60}
build=${2:-build/clang}
here=$(cd "$(dirname "$0")" && pwd)
work=$(mktemp -d "${TMPDIR:-/tmp}/mrskin-fuzz.XXXXXX")
status=0
declare -A max_len=([packet]=128 [can_classic]=1024 [can_fd]=1024 [quantize]=64)
printf '%-12s %-8s %12s %10s %8s %8s\n' fuzzer result runs execs/s cov corpus
for d in packet can_classic can_fd quantize; do
  mkdir -p "$work/$d"
  cp "$here/corpus/$d"/* "$work/$d"/
  log="$work/$d.log"
  result=ok
  if ! "$build/tests/fuzz/mrskin_fuzz_$d" -max_total_time="$secs" -max_len="${max_len[$d]}" \
       -print_final_stats=1 -artifact_prefix="$work/$d-" "$work/$d" >"$log" 2>&1; then
    result=FINDING
    status=1
  fi
  runs=$(awk '/^stat::number_of_executed_units/ {print $2}' "$log")
  eps=$(awk '/^stat::average_exec_per_sec/ {print $2}' "$log")
  cov=$(grep -oE 'cov: [0-9]+' "$log" | tail -1 | awk '{print $2}')
  printf '%-12s %-8s %12s %10s %8s %8s\n' "$d" "$result" "${runs:-?}" "${eps:-?}" "${cov:-?}" "$(ls "$work/$d" | wc -l)"
done
echo "logs, grown corpora and any crash inputs: $work"
exit $status
