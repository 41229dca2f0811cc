#!/bin/bash
# Runs inside the Debian 12 root made by root_test.sh (as /tmp/mrskin/in_root.sh), as root, with
# no network and no checkout: installs the packages with apt and checks what they hold.
set -euo pipefail
cd /
step() { printf -- '--- %s\n' "$*"; }
fail() { echo "package.root (in the root): FAILED: $*" >&2; exit 1; }

[[ ! -e $MRSKIN_CHECKOUT ]] || fail "the checkout $MRSKIN_CHECKOUT is visible in the root"

step "apt install the packages, systemd-sysusers hidden: the postinst falls back to adduser"
dpkg-divert --quiet --local --rename --divert /usr/bin/systemd-sysusers.hidden --add /usr/bin/systemd-sysusers
! command -v systemd-sysusers >/dev/null || fail "systemd-sysusers still on PATH"
DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends -o Dpkg::Use-Pty=0 \
  /tmp/mrskin/debs/*.deb
getent group mrskin >/dev/null || fail "the postinst made no group mrskin (adduser fallback)"
[[ $(id -gn mrskin) == mrskin ]] || fail "user mrskin's group is $(id -gn mrskin), not mrskin"
echo "adduser fallback: $(getent group mrskin), $(getent passwd mrskin)"

step "the same with systemd-sysusers (sysusers.d/mrskin.conf)"
dpkg-divert --quiet --local --rename --remove /usr/bin/systemd-sysusers
userdel mrskin 2>/dev/null || true
groupdel mrskin 2>/dev/null || true
! getent group mrskin >/dev/null || fail "could not remove the group mrskin to try again"
DPKG_MAINTSCRIPT_PACKAGE=mrskin DPKG_MAINTSCRIPT_NAME=postinst /var/lib/dpkg/info/mrskin.postinst configure
getent group mrskin >/dev/null || fail "systemd-sysusers made no group mrskin"
[[ $(id -gn mrskin) == mrskin ]] || fail "user mrskin's group is $(id -gn mrskin), not mrskin"
echo "systemd-sysusers: $(getent group mrskin), $(getent passwd mrskin)"

step "the tools are in /usr/bin and answer --help"
for tool in mrskinctl mrskin-bridged mrskin-model-bench mrskin-follower; do
  [[ $(command -v "$tool") == /usr/bin/$tool ]] || fail "$tool is not /usr/bin/$tool"
  "$tool" --help >/dev/null || fail "$tool --help failed"
done
for page in man1/mrskinctl.1 man8/mrskin-bridged.8 man1/mrskin-model-bench.1 man1/mrskin-follower.1; do
  [[ -f /usr/share/man/$page.gz ]] || fail "no man page /usr/share/man/$page.gz"
done

step "mrskinctl info --device mock://"
cd /tmp
out=$(mrskinctl info --device mock:// 2>&1) || { echo "$out" >&2; fail "mrskinctl info --device mock:// failed (above)"; }
echo "$out" | head -n 6
grep -q '^profile *mr-skin-5x5' <<<"$out" || fail "mrskinctl info did not find the profile mr-skin-5x5"

step "the daemon's demo for 2 s: mrskin-bridged --device mock:// --scene demo --duration 2"
mrskin-bridged --device mock:// --scene demo --duration 2 --quiet --stats-json /tmp/demo-stats.json \
  --socket /tmp/bridged.sock || fail "mrskin-bridged's demo exited with $?"
python3 - <<'PY' || fail "the demo's statistics are not those of a run"
import json
s = json.load(open("/tmp/demo-stats.json"))
print(f"demo: {s['ticks']} ticks, {s['overruns']} overruns, force error rms {s['force_rms_error_n']:.4f} N")
assert s["ticks"] > 0 and s["force_samples"] > 0, s
PY

step "the Python module"
python3 -c 'import mrskin, sys; print("python3-mrskin:", mrskin.__file__)' ||
  fail "import mrskin failed"

step "the example console, built against libmrskin-dev with find_package(mrskin)"
cmake -S /tmp/mrskin/src/example-console -B /tmp/mrskin/console-build -DCMAKE_BUILD_TYPE=Release >/dev/null ||
  fail "configuring tools/example-console with find_package(mrskin) failed"
cmake --build /tmp/mrskin/console-build -j 2 >/dev/null || fail "building tools/example-console failed"
grep -q '^mrskin_DIR:PATH=/usr/lib/.*/cmake/mrskin$' /tmp/mrskin/console-build/CMakeCache.txt ||
  fail "find_package found mrskin elsewhere: $(grep ^mrskin_DIR /tmp/mrskin/console-build/CMakeCache.txt)"
out=$(/tmp/mrskin/console-build/example-console 2>&1) || { echo "$out" >&2; fail "example-console failed (above)"; }
echo "$out" | tail -n 1
grep -q 'example-console: 3500 ticks' <<<"$out" || fail "example-console did not complete its loop"

step "the install test's consumer, built with pkg-config (mrskin.pc)"
flags=$(pkg-config --cflags --libs mrskin) || fail "pkg-config --cflags --libs mrskin failed"
echo "pkg-config mrskin: $flags (version $(pkg-config --modversion mrskin))"
g++ -std=c++20 -o /tmp/mrskin/pc-consumer /tmp/mrskin/src/consumer/main.cpp $flags ||
  fail "building the consumer with pkg-config's flags failed"
out=$(/tmp/mrskin/pc-consumer 2>&1) || { echo "$out" >&2; fail "the pkg-config consumer failed (above)"; }
echo "$out"
grep -q "^mrskin library $(pkg-config --modversion mrskin)," <<<"$out" ||
  fail "the pkg-config consumer does not report version $(pkg-config --modversion mrskin)"

step "systemd-analyze verify on the packaged unit"
unit=$(dpkg -L mrskin | grep '/systemd/system/mrskin-bridged.service$')
systemd-analyze verify "$unit" || fail "systemd-analyze verify $unit reported problems (above)"
echo "systemd-analyze verify $unit: clean"
