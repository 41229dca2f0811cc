#!/bin/bash
# scripts/tidy_unity.py (the lint's clang-tidy, files with the same flags in one unit):
#  1. a finding in a grouped .cpp file is reported at that file's own path and fails the run;
#  2. two files of one group that define the same name in an anonymous namespace (they do not
#     compile as one unit) are both still tidied, the one the error names on its own;
#  3. files with different flags are in different units;
#  4. a clean tree passes.
# Skipped (77) without clang-tidy-14 (scripts/setup-deps.sh lint).
# usage: tidy_unity.sh SOURCE_DIR WORK_DIR
set -euo pipefail
src=$1
work=$2
command -v clang-tidy-14 >/dev/null || {
  echo "skip: clang-tidy-14 is not installed (scripts/setup-deps.sh lint)"
  exit 77
}
rm -rf "$work"
# The script's header filter takes the project's folders only: the files live under bridge/.
mkdir -p "$work/bridge"
cd "$work"
cat >.clang-tidy <<'EOF'
Checks: '-*,readability-else-after-return'
WarningsAsErrors: '*'
EOF
cat >bridge/a.cpp <<'EOF'
namespace {
int helper() { return 1; }
}  // namespace
int a_fn() { return helper(); }
EOF
cat >bridge/b.cpp <<'EOF'
namespace {
int helper() { return 2; }
}  // namespace
int b_fn(int x) {
  if (x > 0) {
    return helper();
  } else {
    return 0;
  }
}
EOF
cat >bridge/c.cpp <<'EOF'
int c_fn(int x) {
  if (x > 0) {
    return X;
  } else {
    return 0;
  }
}
EOF
mkdir -p build
cat >build/compile_commands.json <<EOF
[
 {"directory": "$work/build", "file": "$work/bridge/a.cpp", "command": "g++ -std=c++20 -o a.o -c $work/bridge/a.cpp"},
 {"directory": "$work/build", "file": "$work/bridge/b.cpp", "command": "g++ -std=c++20 -o b.o -c $work/bridge/b.cpp"},
 {"directory": "$work/build", "file": "$work/bridge/c.cpp", "command": "g++ -std=c++20 -DX=7 -o c.o -c $work/bridge/c.cpp"}
]
EOF
run() {
  rc=0
  python3 "$src/scripts/tidy_unity.py" --build-dir build --out-dir build/unity --config-file "$work/.clang-tidy" \
    --jobs 2 --regex "^$work/bridge/" >out.log 2>&1 || rc=$?
}
status=0
expect() { # description, grep pattern
  if grep -qE -- "$2" out.log; then
    echo "ok: $1"
  else
    echo "FAIL: $1 (no line matching '$2' in the output below)"
    status=1
  fi
}

run
expect "b.cpp's finding reported at its own path" "^$work/bridge/b.cpp:7:5: (warning|error): do not use 'else' after 'return' \[readability-else-after-return"
expect "c.cpp's finding reported at its own path" "^$work/bridge/c.cpp:4:5: (warning|error): do not use 'else' after 'return'"
expect "the colliding file tidied on its own" "does not compile as one unit; tidying these on their own: .*bridge/b.cpp"
expect "three compile commands, c.cpp in a unit of its own flags" "^tidy_unity: 3 compile commands in 4 units over 2 rounds, 1 of them taken out"
if ((rc != 1)); then
  echo "FAIL: the run with findings exited $rc, not 1"
  status=1
fi

# The same tree without the findings passes.
sed -i 's/  } else {/  }\n  {/' bridge/b.cpp bridge/c.cpp
run
expect "a clean tree reports nothing" "^tidy_unity: 3 compile commands"
if ((rc != 0)) || grep -qE ': (warning|error): ' out.log; then
  echo "FAIL: the clean tree exited $rc or reported a finding"
  status=1
fi
((status == 0)) || cat out.log
exit "$status"
