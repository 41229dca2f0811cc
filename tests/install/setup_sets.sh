#!/bin/bash
# scripts/setup-deps.sh's sets:
#  1. the run set (the README's first command) holds no QEMU, clang, valgrind, linter or test
#     framework;
#  2. every external command the scripts, the VM harness and the tests call on the host is
#     provided by a package of the set that needs it, or by a package a bare Debian 12 root
#     (debootstrap minbase: Priority required) already has. The commands are listed below; the
#     test also fails if one of them is no longer called anywhere (a stale list), so the list
#     follows the scripts.
# usage: setup_sets.sh SOURCE_DIR
set -euo pipefail
src=$1
deps=$src/scripts/setup-deps.sh
status=0

run=$("$deps" --print run)
for forbidden in qemu-system-x86 clang clang-14 libclang-rt-14-dev valgrind clang-format clang-tidy \
  libgtest-dev librapidcheck-dev libbenchmark-dev busybox-static lintian; do
  if [[ " $run " == *" $forbidden "* ]]; then
    echo "FAIL: the run set holds $forbidden"
    status=1
  fi
done
[[ $status -eq 0 ]] && echo "ok: the run set ($(wc -w <<<"$run") packages) holds no QEMU, clang, valgrind, linter or test framework"

# set:command, for the commands each set's users call (scripts/, tests/system, tests/install, .ci/run).
commands=(
  run:cmake run:ninja run:g++ run:pkg-config
  test:ctest test:valgrind test:candump test:cansend test:qemu-system-x86_64 test:busybox test:cpio
  test:ip test:python3 test:apt-get test:dpkg-deb test:flock test:mountpoint test:timeout test:sha256sum
  test:gzip test:setarch
  build:clang++-14 build:help2man
  lint:clang-format-14 lint:clang-tidy-14 lint:python3
  package:dpkg-buildpackage package:lintian package:mmdebstrap package:fakeroot
)
callers=("$src/scripts" "$src/tests/system" "$src/tests/install" "$src/tests/tools" "$src/tests/python"
  "$src/tests/CMakeLists.txt" "$src/CMakePresets.json" "$src/.ci/run" "$src/tests/interop"
  "$src/tests/package" "$src/docs/man" "$src/debian")
for entry in "${commands[@]}"; do
  set_name=${entry%%:*} cmd=${entry#*:}
  if ! grep -rqwF -- "$cmd" "${callers[@]}" 2>/dev/null; then
    echo "FAIL: $cmd is listed here but no script calls it any more: update this list"
    status=1
    continue
  fi
  # Debian's own first: a PATH may put pyenv or a virtualenv ahead of /usr/bin.
  path=""
  for d in /usr/bin /bin /usr/sbin /sbin; do
    [[ -x $d/$cmd ]] && path=$d/$cmd && break
  done
  [[ -n $path ]] || path=$(command -v "$cmd" || true)
  if [[ -z $path ]]; then
    echo "FAIL: $cmd is not installed: scripts/setup-deps.sh $set_name does not provide it"
    status=1
    continue
  fi
  real=$(readlink -f "$path")
  pkg=""
  for p in "$real" "$path" "/usr$real" "${real#/usr}"; do
    pkg=$(dpkg -S "$p" 2>/dev/null | head -n 1 | cut -d: -f1) && [[ -n $pkg ]] && break
  done
  if [[ -z $pkg ]]; then
    echo "FAIL: $cmd ($real) belongs to no Debian package"
    status=1
    continue
  fi
  pkg=${pkg%%,*}
  priority=$(dpkg-query -W -f='${Priority}' "$pkg" 2>/dev/null || true)
  set_pkgs=$("$deps" --print "$set_name")
  # A package the set names, or one of their dependencies that apt pulls in with them.
  if [[ " $set_pkgs " == *" $pkg "* || $priority == required ]]; then
    continue
  fi
  closure=$(apt-cache depends --recurse --no-recommends --no-suggests --no-conflicts --no-breaks --no-replaces \
    --no-enhances $set_pkgs 2>/dev/null || true)
  if grep -qxF -e "  Depends: $pkg" -e "$pkg" <<<"$closure"; then
    continue
  fi
  echo "FAIL: $cmd comes from $pkg (priority ${priority:-unknown}), which scripts/setup-deps.sh $set_name does not install"
  status=1
done
[[ $status -eq 0 ]] && echo "ok: every listed command comes from its set or from a minbase root (${#commands[@]} commands)"
exit "$status"
