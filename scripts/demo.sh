#!/usr/bin/env bash
# Command 1: installs the missing Debian packages of the run set only (setup-deps.sh --print run:
# compilers and libraries; no QEMU, clang, valgrind or linters), builds the daemon alone (the demo
# preset: no tests, benchmarks or Python module) and runs the bridge on the mock device with the
# built-in demo scene for a few seconds, then prints its summary and a verdict.
# Extra arguments go to mrskin-bridged and override the defaults below
# (e.g. scripts/demo.sh --duration 10).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

jobs=$(nproc 2>/dev/null || echo 2)
bridged=build/demo/tools/mrskin-bridged/mrskin-bridged

echo "== mrskin demo: dependencies"
./scripts/setup-deps.sh run
echo "== mrskin demo: configure (preset demo)"
cmake --preset demo
echo "== mrskin demo: build mrskin-bridged (${jobs} jobs)"
cmake --build --preset demo -j "$jobs"

if [[ ! -x $bridged ]]; then
  echo "demo: $bridged was not built; the bridge daemon (tools/mrskin-bridged) is not in this tree yet" >&2
  exit 1
fi

# Defaults, each dropped when the caller passes the same option.
defaults=(--device mock:// --scene demo --duration 5 --stats-json build/demo/demo-stats.json)
args=()
for ((i = 0; i < ${#defaults[@]}; i += 2)); do
  opt=${defaults[i]}
  given=0
  for a in "$@"; do
    [[ $a == "$opt" || $a == "$opt="* ]] && given=1
  done
  ((given)) || args+=("$opt" "${defaults[i + 1]}")
done

echo "== mrskin demo: $bridged ${args[*]} $*"
exec "$bridged" "${args[@]}" "$@"
