#!/bin/sh
# The inverse's cost gate: runs inverse_callgrind_probe under callgrind for each scenario and
# fails if any scenario's instructions per solve exceed LIMIT. Exits 77 (ctest: skipped) when
# valgrind is missing.
#   callgrind_gate.sh PROBE PROFILE_DIR OUT_DIR LIMIT
probe=$1 profiles=$2 out=$3 limit=$4
if ! command -v valgrind >/dev/null 2>&1; then
  echo "SKIPPED: valgrind not found; install it (apt-get install valgrind) to run the instruction-count gate"
  exit 77
fi
mkdir -p "$out" || exit 1
failed=""
for scenario in press1 press2 press3 hold3 idle; do
  file=$out/callgrind.$scenario.out
  if ! log=$(valgrind --tool=callgrind --instr-atstart=no --callgrind-out-file="$file" \
      "$probe" "$scenario" "$profiles" 2>"$file.log"); then
    echo "probe $scenario failed:"; echo "$log"; cat "$file.log"
    exit 1
  fi
  solves=$(echo "$log" | sed -n 's/^solves \([0-9]*\)$/\1/p')
  total=$(sed -n 's/^totals: \([0-9]*\).*/\1/p' "$file")
  if [ -z "$solves" ] || [ -z "$total" ]; then
    echo "could not read the solve count or the totals for $scenario"; echo "$log"
    exit 1
  fi
  per=$((total / solves))
  echo "$scenario: $per instructions per solve ($total over $solves solves)"
  if [ "$per" -gt "$limit" ]; then
    failed="$failed $scenario($per)"
  fi
done
if [ -n "$failed" ]; then
  echo "above $limit instructions per solve:$failed"
  exit 1
fi
echo "every scenario within $limit instructions per solve"
