#!/usr/bin/env bash
# Command 2: installs missing Debian packages, builds the release preset and runs the whole test
# suite through ctest, one test per core (nproc). Exits with ctest's status. Extra arguments go to ctest (e.g. -R protocol).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

jobs=$(nproc 2>/dev/null || echo 2)

echo "== mrskin tests: dependencies"
./scripts/setup-deps.sh
echo "== mrskin tests: configure (preset release)"
cmake --preset release
echo "== mrskin tests: build (${jobs} jobs)"
cmake --build --preset release -j "$jobs"
echo "== mrskin tests: ctest (preset release)"
rc=0
ctest --preset release --parallel "$jobs" "$@" || rc=$?
exit "$rc"
