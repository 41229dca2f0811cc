#!/bin/sh
# The install is relocatable and carries no build or source path:
#  1. cmake --install into WORK/a, then the whole prefix is moved to WORK/moved/b;
#  2. from there, with no MRSKIN_PROFILE_PATH, the installed mrskinctl opens mock:// (its
#     profile found relative to the installed driver library) and loads a second built-in
#     profile by name;
#  3. no installed file (binaries included) names the source tree, the build tree or the
#     prefix it was installed to.
#     Only for a build without debug information or sanitizers (what the packages are made
#     from): DWARF and the sanitizers' reports name the source files by design.
# usage: relocated.sh CMAKE BUILD_DIR SOURCE_DIR WORK_DIR BINDIR check-paths|no-path-check
set -eu
cmake=$1 build=$2 source=$3 work=$4 bindir=$5 paths=$6
rm -rf "$work"
mkdir -p "$work/moved"
"$cmake" --install "$build" --prefix "$work/a" >"$work/install.log" 2>&1 || {
  cat "$work/install.log"
  exit 1
}
mv "$work/a" "$work/moved/b"
prefix=$work/moved/b
status=0

if out=$(env -u MRSKIN_PROFILE_PATH "$prefix/$bindir/mrskinctl" info --device mock:// 2>&1) &&
  echo "$out" | grep -q '^profile *mr-skin-5x5'; then
  echo "ok: the moved mrskinctl opens mock:// with its default profile"
else
  echo "FAIL: the moved mrskinctl could not open mock://:"
  echo "$out"
  status=1
fi
if out=$(env -u MRSKIN_PROFILE_PATH "$prefix/$bindir/mrskinctl" info --device mock://fingertip-16x16 2>&1) &&
  echo "$out" | grep -q '^profile *fingertip-16x16'; then
  echo "ok: the moved mrskinctl finds fingertip-16x16 by name"
else
  echo "FAIL: the moved mrskinctl could not find fingertip-16x16:"
  echo "$out"
  status=1
fi

if [ "$paths" != check-paths ]; then
  echo "ok: relocated (no path check in this build: debug information or a sanitizer names the sources)"
  exit "$status"
fi

# grep -a: binaries too. The build tree may sit inside the source tree: both are looked for. The
# systemd unit alone names the install prefix (systemd wants absolute paths; it is generated for
# the prefix at install time): it may name that one, and must.
unit=$(find "$prefix" -name mrskin-bridged.service)
if [ -z "$unit" ] || ! grep -q "^ExecStart=$work/a/$bindir/mrskin-bridged " "$unit"; then
  echo "FAIL: the installed unit's ExecStart does not name the prefix it was installed to:"
  grep -s '^ExecStart' "$unit" || echo "  (no mrskin-bridged.service installed)"
  status=1
fi
for path in "$source" "$build" "$work/a"; do
  real=$(cd "$path" 2>/dev/null && pwd -P || echo "$path")
  for p in "$path" "$real"; do
    if hits=$(grep -rlaF --exclude=mrskin-bridged.service -- "$p" "$prefix") ||
      { [ "$p" != "$work/a" ] && sed "s|$work/a||g" "$unit" | grep -qF -- "$p" && hits=$unit; }; then
      echo "FAIL: installed files name $p:"
      echo "$hits" | sed "s|^$prefix/|  |"
      status=1
    fi
  done
done
[ "$status" -eq 0 ] && echo "ok: no installed file names the source, build or install path"
exit "$status"
