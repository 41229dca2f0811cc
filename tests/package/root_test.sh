#!/usr/bin/env bash
# ctest package.root: installs the Debian packages with apt into a minimal Debian 12 root and runs
# them there, from /usr/bin, with no checkout in sight (docs/install.md, "The Debian packages"):
#   - the mrskin group and user made by the postinst with adduser (systemd-sysusers hidden), then
#     again by systemd-sysusers from the package's sysusers.d entry;
#   - mrskinctl info --device mock://, and the daemon's demo (mock://, scene demo) for 2 s;
#   - the Python module;
#   - the example console built against libmrskin-dev with find_package(mrskin), and the install
#     test's consumer built with pkg-config (mrskin.pc);
#   - systemd-analyze verify on the packaged unit.
# The root (mmdebstrap --variant=minbase, Debian's mirror, with the packages' dependencies, a
# compiler, cmake, pkgconf and systemd) is cached as a tarball in ~/.cache/mrskin-pkgroot, keyed
# on a hash of its package list and mirrors. The tests in the root run without network (their own
# network namespace, loopback only): apt installs the .deb files from the root's contents.
#
#   root_test.sh SOURCE_DIR DEB_DIR WORK_DIR
# Exit 77 (skipped) when not root or mmdebstrap, unshare or chroot is missing.
set -euo pipefail

if (($# != 3)); then
  echo "usage: root_test.sh SOURCE_DIR DEB_DIR WORK_DIR" >&2
  exit 2
fi
src=$(realpath "$1")
debs=$(realpath "$2")
work=$(realpath -m "$3")

skip() { echo "package.root: SKIPPED: $*"; exit 77; }
fail() { echo "package.root: FAILED: $*" >&2; exit 1; }

[[ $(id -u) -eq 0 ]] || skip "needs root (chroot, mount): run ctest -L package as root"
for tool in mmdebstrap unshare chroot; do
  command -v "$tool" >/dev/null 2>&1 ||
    skip "$tool is missing: run ./scripts/setup-deps.sh (group 'packaging')"
done
shopt -s nullglob
deb_files=("$debs"/*.deb)
((${#deb_files[@]} > 0)) || fail "no .deb in $debs: run scripts/package.sh first"

# --- the root's package list: our packages' dependencies (first of each alternative), a
# toolchain for the consoles, systemd for systemd-analyze and its sysusers, procps for the unit's
# /bin/kill, man-db for the unit's Documentation=man:mrskin-bridged(8) (systemd-analyze verify
# runs man on it). Our own packages are installed by the test itself.
ours=$(for d in "${deb_files[@]}"; do dpkg-deb -f "$d" Package; done | sort -u)
deps=$(for d in "${deb_files[@]}"; do dpkg-deb -f "$d" Depends Pre-Depends; done |
  sed -E 's/^[A-Za-z-]+: //' | tr ',' '\n' | sed -E 's/\|.*//; s/\(.*\)//; s/:any//; s/[[:space:]]//g' |
  grep -v '^$' | sort -u | grep -vxF -f <(echo "$ours") || true)
packages=$(printf '%s\n' $deps g++ cmake make pkgconf systemd procps man-db | sort -u)
suite=bookworm
mirrors=(
  "deb http://deb.debian.org/debian bookworm main"
  "deb http://deb.debian.org/debian bookworm-updates main"
  "deb http://deb.debian.org/debian-security bookworm-security main"
)
key=$(printf '%s\n' "v1 minbase $suite" "${mirrors[@]}" $packages | sha256sum | cut -c1-16)
cache=${XDG_CACHE_HOME:-$HOME/.cache}/mrskin-pkgroot
tarball=$cache/root-$key.tar
echo "package.root: root packages (key $key): $(echo $packages | tr '\n' ' ')"

t0=$SECONDS
if [[ ! -f $tarball ]]; then
  echo "package.root: making the root with mmdebstrap (first run for this package list; cached as $tarball)"
  mkdir -p "$cache"
  if ! mmdebstrap --variant=minbase --mode=root --quiet --include="$(echo $packages | tr ' ' ',')" \
    "$suite" "$cache/root-$key.part$$.tar" "${mirrors[@]}" >"$cache/root-$key.log" 2>&1; then
    tail -n 30 "$cache/root-$key.log" >&2
    rm -rf "$cache/root-$key.part$$.tar"
    fail "mmdebstrap failed (log: $cache/root-$key.log); is deb.debian.org reachable?"
  fi
  mv "$cache/root-$key.part$$.tar" "$tarball"
  echo "package.root: root made in $((SECONDS - t0)) s"
else
  echo "package.root: cached root $tarball"
fi

# --- the root, fresh for each run, with the packages and the consoles' sources and nothing else.
rm -rf "$work"
root=$work/root
mkdir -p "$root"
tar -xf "$tarball" -C "$root"
echo "package.root: root unpacked in $((SECONDS - t0)) s"
mkdir -p "$root/tmp/mrskin/debs" "$root/tmp/mrskin/src"
cp "${deb_files[@]}" "$root/tmp/mrskin/debs/"
cp -r "$src/tools/example-console" "$root/tmp/mrskin/src/example-console"
cp -r "$src/tests/install/consumer" "$root/tmp/mrskin/src/consumer"
cp "$src/tests/package/in_root.sh" "$root/tmp/mrskin/in_root.sh"
[[ ! -e $root$src ]] || fail "the checkout's path $src exists in the root"

# A private mount and network namespace: /proc for the tools, loopback only, and every mount gone
# when the test ends, whatever happens.
unshare --mount --net --propagation private -- bash -euo pipefail -c '
  root=$1 src=$2
  if command -v ip >/dev/null 2>&1; then ip link set lo up; fi
  mount -t proc proc "$root/proc"
  mount -t tmpfs tmpfs "$root/dev/shm" 2>/dev/null || true
  exec chroot "$root" /usr/bin/env -i PATH=/usr/sbin:/usr/bin:/sbin:/bin HOME=/root LANG=C.UTF-8 \
    MRSKIN_CHECKOUT="$src" /bin/bash /tmp/mrskin/in_root.sh
' in-root "$root" "$src"
echo "package.root: passed in $((SECONDS - t0)) s"
rm -rf "$work"
