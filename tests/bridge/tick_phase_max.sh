#!/bin/sh
# Issue 21's gates as it states them: the maximum instructions of one Bridge::step in each phase
# of a run on the perturbed mock (its network plant and sensor noise), not a mean and not a
# synthetic plant. demo_callgrind_probe dumps each tick's count and writes each tick's phase
# (from the finger's true depths); this pairs them and prints, per phase, the ticks, the maximum,
# p50 and p99 (the first tick, which sends the first frames, left out).
#   tick_phase_max.sh PROBE OUT_DIR TICKS URI FINGER [PHASE:LIMIT ...]   (FINGER: scene, all or rest)
# With PHASE:LIMIT arguments (a ratchet), fails when a phase's maximum is above its limit or the
# phase has no tick. Exits 77 (ctest: skipped) when valgrind is missing.
# With MRSKIN_PHASE_WITHOUT_MOCK=1 the simulated unit's own work inside the tick is left out
# (MockDevice's transport: the synchronous mock parses the host's frames and runs its bus model
# inside the session's send and poll), so the counts are the driver's and the bridge's alone.
probe=$1 out=$2 ticks=$3 uri=$4 finger=$5
if [ -z "$finger" ]; then
  echo "usage: tick_phase_max.sh PROBE OUT_DIR TICKS URI scene|all|rest [PHASE:LIMIT ...]" >&2
  exit 2
fi
shift 5
if ! command -v valgrind >/dev/null 2>&1; then
  echo "SKIPPED: valgrind not found (apt-get install valgrind)"
  exit 77
fi
rm -rf "$out" && mkdir -p "$out" || exit 1
transport=mrskin::sim::MockDevice::Impl::HostTransport
toggle_receive=--toggle-collect=none toggle_send=--toggle-collect=none
if [ "${MRSKIN_PHASE_WITHOUT_MOCK:-0}" = 1 ]; then
  toggle_receive="--toggle-collect=$transport::receive*" toggle_send="--toggle-collect=$transport::send*"
fi
if ! MRSKIN_PROBE_PHASES="$out/phases.txt" valgrind --tool=callgrind --instr-atstart=no \
    --collect-atstart=no --dump-instr=no --callgrind-out-file="$out/tick.%p" \
    "$toggle_receive" "$toggle_send" "$probe" "$ticks" "$uri" "$finger" >"$out/probe.log" 2>&1; then
  echo "probe failed:"; tail -20 "$out/probe.log"
  exit 1
fi
# Dump N (tick.PID.N, N from 1) is tick N - 1, whose phase is line N of phases.txt.
for f in "$out"/tick.*.*; do
  n=${f##*.}
  printf '%s %s\n' "$n" "$(sed -n 's/^totals: \([0-9]*\).*/\1/p' "$f")"
done | sort -n >"$out/per_tick.txt"
awk 'NR == FNR { phase[FNR] = $1; next } $1 > 1 { print phase[$1], $2 }' \
  "$out/phases.txt" "$out/per_tick.txt" | sort -k1,1 -k2,2n >"$out/by_phase.txt"
awk '{ v[$1, ++n[$1]] = $2 }
     END {
       for (p in n) {
         c = n[p]
         i50 = int((50 * c + 99) / 100); i99 = int((99 * c + 99) / 100)
         printf "%-12s ticks %5d  max %8d  p50 %8d  p99 %8d\n", p, c, v[p, c], v[p, i50], v[p, i99]
       }
     }' "$out/by_phase.txt" | sort | tee "$out/summary.txt"
status=0
for pair in "$@"; do
  phase=${pair%%:*} limit=${pair#*:}
  max=$(awk -v p="$phase" '$1 == p { print $5 }' "$out/summary.txt")
  if [ -z "$max" ]; then
    echo "FAILED: no tick in phase $phase"; status=1
  elif [ "$max" -gt "$limit" ]; then
    echo "FAILED: $phase's maximum $max is above its ratchet $limit"; status=1
  else
    echo "$phase: $max, at most $limit"
  fi
done
exit $status
