#!/usr/bin/env bash
# Lint: clang-format (dry run, any difference fails) on the project's C++ sources, no file over
# 1,000 lines outside tests/, then clang-tidy
# (.clang-tidy, warnings are errors) over protocol/, driver/, bridge/, tools/ and python/ using the release
# build's compile_commands.json (configured first if missing), files with the same flags several to a
# clang-tidy unit (scripts/tidy_unity.py). Prints a count of findings per check.
# Usage: scripts/lint.sh [--format-only | --tidy-only]
# Env: LINT_BUILD_DIR (default build/release), LINT_JOBS (default nproc), LINT_PER_FILE=1 (one
# file per clang-tidy unit, as run-clang-tidy does: 3.4 times slower here, README.md).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
root=$PWD

mode=${1:-all}
build_dir=${LINT_BUILD_DIR:-build/release}
jobs=${LINT_JOBS:-$(nproc 2>/dev/null || echo 2)}
logs=$build_dir/lint
rc=0

pick() { # first existing command
  local c
  for c in "$@"; do
    if command -v "$c" >/dev/null 2>&1; then
      echo "$c"
      return 0
    fi
  done
  echo "lint: none of $* found; run scripts/setup-deps.sh" >&2
  return 1
}

# Tracked and new (not ignored) C++ files of the project.
mapfile -t sources < <(git ls-files -co --exclude-standard -- \
  'protocol/*' 'driver/*' 'bridge/*' 'tools/*' 'python/*' 'tests/*' |
  grep -E '\.(cpp|cc|hpp|h)$' | sort -u | while read -r f; do [[ -f $f ]] && echo "$f"; done)

summarize() { # log: findings per check, each finding (file:line:col + check) counted once
  grep -E '^[^ ].*:[0-9]+:[0-9]+: (warning|error): .*\[[A-Za-z0-9.,_-]+\]$' "$1" | sort -u |
    sed -E 's/.*\[([A-Za-z0-9.,_-]+)\]$/\1/' | tr ',' '\n' |
    grep -v -E '^-warnings-as-errors$' | sort | uniq -c | sort -rn || true
}

if [[ $mode != --tidy-only ]]; then
  echo "== lint: clang-format on ${#sources[@]} files"
  fmt=$(pick clang-format-14 clang-format)
  mkdir -p "$logs"
  if ((${#sources[@]})) && ! "$fmt" --dry-run --Werror "${sources[@]}" >"$logs/format.log" 2>&1; then
    rc=1
    mapfile -t bad < <(grep -oE '^[^:]+\.(cpp|cc|hpp|h):' "$logs/format.log" | sort -u | tr -d ':')
    echo "clang-format: ${#bad[@]} files need formatting (clang-format-14 -i FILE to fix):"
    printf '  %s\n' "${bad[@]}"
    echo "  $(grep -c 'error: code should be clang-formatted' "$logs/format.log") places; details in $logs/format.log"
  else
    echo "clang-format: clean"
  fi
fi

if [[ $mode != --tidy-only ]]; then
  # No source file over 1,000 lines outside tests/ (a file a newcomer can hold in mind).
  echo "== lint: file size (at most 1000 lines outside tests/)"
  long=()
  for f in "${sources[@]}"; do
    if [[ $f != tests/* ]] && (($(wc -l <"$f") > 1000)); then
      long+=("$f ($(wc -l <"$f") lines)")
    fi
  done
  if ((${#long[@]})); then
    rc=1
    echo "files over 1000 lines (split them by responsibility):"
    printf '  %s\n' "${long[@]}"
  else
    echo "file size: clean"
  fi
fi

if [[ $mode != --format-only ]]; then
  if [[ ! -f $build_dir/compile_commands.json ]]; then
    echo "== lint: configuring (preset release) for compile_commands.json"
    ./scripts/setup-deps.sh
    cmake --preset release >/dev/null
  fi
  tidy=$(pick clang-tidy-14 clang-tidy)
  mkdir -p "$logs"
  # Files with the same flags are tidied several to a unit (scripts/tidy_unity.py: the standard
  # library's headers are most of clang-tidy's time on a file); LINT_PER_FILE=1 tidies one by one.
  unity_args=()
  [[ ${LINT_PER_FILE:-0} == 1 ]] && unity_args+=(--per-file)
  echo "== lint: clang-tidy (${jobs} jobs) over protocol/ driver/ bridge/ tools/ python/"
  if ! python3 scripts/tidy_unity.py --build-dir "$build_dir" --out-dir "$logs/unity" \
    --config-file "$root/.clang-tidy" --tidy "$(command -v "$tidy")" --jobs "$jobs" \
    "${unity_args[@]}" --regex "^${root}/(protocol|driver|bridge|tools|python)/" \
    >"$logs/tidy.raw.log" 2>&1; then
    rc=1
  fi
  # Strip colours, should a clang-tidy print them.
  sed -E 's/\x1b\[[0-9;]*m//g' "$logs/tidy.raw.log" >"$logs/tidy.log"
  rm -f "$logs/tidy.raw.log"
  grep -E '^tidy_unity: ' "$logs/tidy.log" || true
  counts=$(summarize "$logs/tidy.log")
  if [[ -n $counts ]]; then
    rc=1
    echo "clang-tidy findings per check (details in $logs/tidy.log):"
    echo "$counts"
    echo "  total: $(awk '{s += $1} END {print s}' <<<"$counts")"
  elif ((rc)); then
    echo "clang-tidy failed without findings; see $logs/tidy.log"
    tail -n 20 "$logs/tidy.log"
  else
    echo "clang-tidy: clean"
  fi
fi

exit "$rc"
