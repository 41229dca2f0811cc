#!/bin/sh
# The bridge tick's cost gate (docs/requirements.md): runs tick_callgrind_probe under
# callgrind for each case and fails if
#   - a 5 x 5 case (idle5, load5, hold5) costs more than LIMIT_5X5 instructions per tick, or
#   - the 64 x 64 with 5 % of its cells in contact costs more than RATIO_PERCENT % of the 64 x 64
#     in full contact (grid5 against grid100).
# grid0 (64 x 64, no contact) is reported. A case written CASE:N, any case, has a limit of its own
# (the ratchets: what the tick costs today, so that no change raises it). Exits 77 (ctest: skipped)
# when valgrind is missing.
#   tick_callgrind_gate.sh PROBE PROFILE_DIR OUT_DIR LIMIT_5X5 RATIO_PERCENT [CASE[:N]...]
probe=$1 profiles=$2 out=$3 limit=$4 ratio=$5
shift 5
cases=${*:-"idle5 load5 hold5 grid0 grid5 grid100"}
if ! command -v valgrind >/dev/null 2>&1; then
  echo "SKIPPED: valgrind not found; install it (apt-get install valgrind) to run the instruction-count gate"
  exit 77
fi
mkdir -p "$out" || exit 1
failed=""
grid5="" grid100=""
for spec in $cases; do
  c=${spec%%:*}
  case_limit=$limit
  [ "$spec" != "$c" ] && case_limit=${spec#*:}
  file=$out/callgrind.$c.out
  if ! log=$(valgrind --tool=callgrind --instr-atstart=no --collect-atstart=no --callgrind-out-file="$file" \
      "$probe" "$c" "$profiles" 2>"$file.log"); then
    echo "probe $c failed:"; echo "$log"; cat "$file.log"
    exit 1
  fi
  ticks=$(echo "$log" | sed -n 's/^ticks \([0-9]*\)$/\1/p')
  total=$(sed -n 's/^totals: \([0-9]*\).*/\1/p' "$file")
  if [ -z "$ticks" ] || [ -z "$total" ]; then
    echo "could not read the tick count or the totals for $c"; echo "$log"
    exit 1
  fi
  per=$((total / ticks))
  echo "$c: $per instructions per tick ($total over $ticks ticks); $(echo "$log" | sed -n 's/^cells //p')"
  if [ "$spec" != "$c" ]; then  # a limit of its own, on any case
    if [ "$per" -gt "$case_limit" ]; then failed="$failed $c($per > $case_limit)"; fi
  else
    case $c in
      idle5 | load5 | hold5) if [ "$per" -gt "$limit" ]; then failed="$failed $c($per > $limit)"; fi ;;
    esac
  fi
  [ "$c" = grid5 ] && grid5=$per
  [ "$c" = grid100 ] && grid100=$per
done
if [ -n "$grid5" ] && [ -n "$grid100" ]; then
  # grid5 * 100 <= ratio * grid100, in integers
  echo "grid5 / grid100 = $grid5 / $grid100 (limit $ratio %)"
  if [ $((grid5 * 100)) -gt $((ratio * grid100)) ]; then
    failed="$failed grid5/grid100($grid5/$grid100 > $ratio %)"
  fi
fi
if [ -n "$failed" ]; then
  echo "over budget:$failed"
  exit 1
fi
ratio_note=""
[ -n "$grid5" ] && [ -n "$grid100" ] && ratio_note=", grid5 <= $ratio % of grid100"
echo "within budget: every case at or below its limit ($cases; default $limit)$ratio_note"
