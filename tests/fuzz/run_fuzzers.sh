#!/usr/bin/env bash
# Runs every fuzzer for SECONDS (default 60) from a copy of its committed seed corpus (which it
# replays first; the committed corpora stay small), JOBS at a time (default 2), and prints one
# line per fuzzer. Exits non-zero on any finding; crash inputs and grown corpora are then kept in
# the work folder, which is removed after a clean run (MRSKIN_FUZZ_KEEP=1 keeps it). .ci/run runs
# it for 15 s (docs/reliability.md).
#   cmake --preset clang && cmake --build build/clang
#   tests/fuzz/run_fuzzers.sh [SECONDS] [BUILD_DIR] [JOBS]
set -euo pipefail
secs=${1:-60}
build=${2:-build/clang}
jobs=${3:-2}
here=$(cd "$(dirname "$0")" && pwd)
work=$(mktemp -d "${TMPDIR:-/tmp}/mrskin-fuzz.XXXXXX")
declare -A max_len=([packet]=1100 [can_classic]=1024 [can_fd]=1024 [quantize]=64 [control_line]=8192
                    [config]=8192 [profile]=8192 [calibration]=4096 [replay]=8192 [igtl]=8192 [udp]=128
                    [recording]=16384)
fuzzers=(packet can_classic can_fd quantize control_line config profile calibration replay recording igtl udp)
for d in "${fuzzers[@]}"; do
  [ -x "$build/tests/fuzz/mrskin_fuzz_$d" ] || { echo "run_fuzzers: $build/tests/fuzz/mrskin_fuzz_$d is not built (clang preset)" >&2; exit 2; }
done

one() { # fuzzer: runs it, writes WORK/NAME.result
  local d=$1 log="$work/$1.log" result=ok
  mkdir -p "$work/$d"
  cp "$here/corpus/$d"/* "$work/$d"/
  if ! "$build/tests/fuzz/mrskin_fuzz_$d" -max_total_time="$secs" -max_len="${max_len[$d]}" -rss_limit_mb=1024 \
       -print_final_stats=1 -artifact_prefix="$work/$d-" "$work/$d" >"$log" 2>&1; then
    result=FINDING
  fi
  echo "$result" >"$work/$d.result"
}

running=0
for d in "${fuzzers[@]}"; do
  one "$d" &
  running=$((running + 1))
  if [ "$running" -ge "$jobs" ]; then
    wait -n
    running=$((running - 1))
  fi
done
wait

status=0
printf '%-13s %-8s %12s %10s %8s %8s\n' fuzzer result runs execs/s cov corpus
for d in "${fuzzers[@]}"; do
  log="$work/$d.log"
  result=$(cat "$work/$d.result" 2>/dev/null || echo FINDING)
  [ "$result" = ok ] || status=1
  runs=$(awk '/^stat::number_of_executed_units/ {print $2}' "$log")
  eps=$(awk '/^stat::average_exec_per_sec/ {print $2}' "$log")
  cov=$(grep -oE 'cov: [0-9]+' "$log" | tail -1 | awk '{print $2}')
  printf '%-13s %-8s %12s %10s %8s %8s\n' "$d" "$result" "${runs:-?}" "${eps:-?}" "${cov:-?}" "$(ls "$work/$d" | wc -l)"
  if [ "$result" != ok ]; then
    grep -E 'ERROR|invariant|unexpected|SUMMARY' "$log" | head -n 5 | sed "s/^/  $d: /"
  fi
done
if [ "$status" -eq 0 ] && [ "${MRSKIN_FUZZ_KEEP:-0}" != 1 ]; then
  rm -rf "$work"
  echo "no finding; work folder removed (MRSKIN_FUZZ_KEEP=1 keeps its logs and grown corpora)"
else
  echo "logs, grown corpora and any crash inputs: $work"
fi
exit $status
