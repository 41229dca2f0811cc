#!/bin/sh
# The bridge tick's per-cell Rendering record as struct-of-arrays (the code) against
# array-of-structs (aos-rendering.patch: one RenderedCell per cell, gathered into the spans the
# inverse and the watchers take), measured with callgrind's cache simulation on the 64 x 64
# (tick_callgrind_probe's grid0, grid5, grid100). Prints instructions, L1 and last-level data
# misses per tick for each. Both variants are built from HEAD in a temporary worktree (a full
# build, then the patch and an incremental one: about 12 minutes on 2 cores) and each runs
# under valgrind three times (about 11 minutes in all). docs/bridge.md, "The per-cell record".
#   scripts/measure/record-layout.sh [OUT_DIR]
set -eu
here=$(cd "$(dirname "$0")/../.." && pwd)
out=${1:-/tmp/mrskin-record-layout}
command -v valgrind >/dev/null || { echo "valgrind not found: apt-get install valgrind"; exit 1; }
mkdir -p "$out"
wt=$out/worktree
rm -rf "$wt"
git -C "$here" worktree prune
git -C "$here" worktree add --detach "$wt" HEAD >/dev/null
trap 'git -C "$here" worktree remove --force "$wt"' EXIT
probe=$wt/build/release/tests/bridge/tick_callgrind_probe
build() { (cd "$wt" && cmake --preset release >/dev/null && cmake --build --preset release -j2 --target tick_callgrind_probe >/dev/null); }
run() {  # LABEL CASE
  f=$out/cg.$1.$2.out
  valgrind --tool=callgrind --cache-sim=yes --instr-atstart=no --collect-atstart=no \
    --callgrind-out-file="$f" "$probe" "$2" "$here/driver/profiles" >"$f.log" 2>"$f.vg.log"
  ticks=$(sed -n 's/^ticks //p' "$f.log")
  # totals: Ir Dr Dw I1mr D1mr D1mw ILmr DLmr DLmw
  sed -n 's/^totals: //p' "$f" | awk -v l="$1" -v c="$2" -v t="$ticks" \
    '{ printf "%-5s %-8s %12.0f instr/tick %10.0f L1d misses/tick %8.0f LL data misses/tick\n", l, c, $1 / t, ($5 + $6) / t, ($8 + $9) / t }'
}
build
for c in grid0 grid5 grid100; do run soa "$c"; done
git -C "$wt" apply "$here/scripts/measure/aos-rendering.patch"
build
for c in grid0 grid5 grid100; do run aos "$c"; done
