#!/bin/bash
# vm-run.sh [--work DIR] [--timeout SECONDS] [--modules "MOD..."] -- COMMAND [ARGS...]
#
# Boots Debian's own kernel under QEMU (TCG, no network) with the host's root filesystem
# read-only over 9p and DIR read-write at the same path, runs COMMAND ARGS inside (a chroot
# into the host root, where /tmp, /var/tmp and /run are fresh tmpfs; the checkout and the
# folders of COMMAND and its arguments are bound back into them when they lie there),
# and exits with COMMAND's exit code. DIR defaults to CACHE/work.
#
# The kernel comes from the Debian archive: `apt-get download` of linux-image-amd64 and of
# the image package it depends on, unpacked with `dpkg-deb -x` into the cache (never into
# /boot), busybox's `depmod -b` run there. The initramfs (busybox-static + the 9p modules +
# guest-init.sh) is built once per kernel and init script and kept in the cache. The guest's
# init loads the --modules (with their dependencies, busybox modprobe on the cached tree)
# before it runs COMMAND: the host needs no kmod and has no /lib/modules of that kernel.
#
# Environment: MRSKIN_VM_QEMU (the qemu-system-x86_64 to run), MRSKIN_VM_CACHE (default
# ${XDG_CACHE_HOME:-$HOME/.cache}/mrskin-vm; not under /tmp, /var/tmp, /run or /dev, which
# the guest covers with tmpfs), MRSKIN_VM_MEM (MB, 1024), MRSKIN_VM_SMP (2),
# MRSKIN_VM_TIMEOUT (seconds, 420). Inside, the command sees MRSKIN_VM=1 and
# MRSKIN_VM_MODULES (the unpacked kernel's root).
#
# Exit codes: COMMAND's; 77 when the VM cannot be run here (qemu-system-x86, busybox-static
# or cpio missing, or the kernel package cannot be fetched), with the reason on stderr;
# 125 when the VM crashed or timed out before COMMAND finished.
set -euo pipefail

here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
work=""
modules=""
timeout_s=${MRSKIN_VM_TIMEOUT:-420}
while [ $# -gt 0 ]; do
  case $1 in
    --work) work=$2; shift 2 ;;
    --timeout) timeout_s=$2; shift 2 ;;
    --modules) modules=$2; shift 2 ;;
    --) shift; break ;;
    *) echo "vm-run: unknown option $1" >&2; exit 2 ;;
  esac
done
[ $# -ge 1 ] || { echo "usage: vm-run.sh [--work DIR] [--timeout S] [--modules \"M...\"] -- COMMAND [ARGS...]" >&2; exit 2; }

skip() {
  echo "vm-run: SKIP: $*" >&2
  exit 77
}

# --- tools ------------------------------------------------------------------------------------
missing=()
qemu=${MRSKIN_VM_QEMU:-qemu-system-x86_64}
command -v "$qemu" >/dev/null || missing+=(qemu-system-x86)
busybox=""
for b in /bin/busybox /usr/bin/busybox; do
  # A static busybox: ldd refuses it.
  if [ -x "$b" ] && ! ldd "$b" >/dev/null 2>&1; then busybox=$b; break; fi
done
[ -n "$busybox" ] || missing+=(busybox-static)
command -v cpio >/dev/null || missing+=(cpio)
if [ ${#missing[@]} -gt 0 ]; then
  skip "missing ${missing[*]}; install with: apt-get install -y --no-install-recommends ${missing[*]}"
fi

# --- the kernel, cached -------------------------------------------------------------------------
cache=${MRSKIN_VM_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/mrskin-vm}
mkdir -p "$cache"
cache=$(realpath "$cache")
# The guest mounts fresh tmpfs on these: a kernel cached there would be invisible inside.
case $cache/ in
  /tmp/* | /var/tmp/* | /run/* | /dev/*)
    echo "vm-run: the cache $cache must not be under /tmp, /var/tmp, /run or /dev (set MRSKIN_VM_CACHE)" >&2
    exit 2
    ;;
esac
root=$cache/kernel
lock=$cache/.lock
exec 9>"$lock"
flock 9
kv=""
if [ -d "$root/lib/modules" ]; then
  kv=$(find "$root/lib/modules" -mindepth 1 -maxdepth 1 -printf '%f\n' | sort -V | tail -n 1)
fi
if [ -z "$kv" ] || [ ! -f "$root/boot/vmlinuz-$kv" ] || [ ! -f "$root/lib/modules/$kv/modules.dep" ]; then
  command -v apt-get >/dev/null || skip "no apt-get to fetch the kernel package"
  dl=$cache/download
  rm -rf "$dl" "$root"
  mkdir -p "$dl"
  echo "vm-run: fetching the kernel package into $cache" >&2
  (cd "$dl" && apt-get download linux-image-amd64 >/dev/null 2>"$dl/apt.log") ||
    skip "apt-get download linux-image-amd64 failed: $(tail -n 1 "$dl/apt.log")"
  meta=$(find "$dl" -name 'linux-image-amd64_*.deb' | head -n 1)
  image=$(dpkg-deb -f "$meta" Depends | tr ',' '\n' | grep -o 'linux-image-[0-9][^ ]*' | head -n 1)
  [ -n "$image" ] || skip "cannot read the image package from $meta"
  (cd "$dl" && apt-get download "$image" >/dev/null 2>"$dl/apt.log") ||
    skip "apt-get download $image failed: $(tail -n 1 "$dl/apt.log")"
  deb=$(find "$dl" -name "${image}_*.deb" | head -n 1)
  mkdir -p "$root"
  dpkg-deb -x "$deb" "$root"
  kv=$(find "$root/lib/modules" -mindepth 1 -maxdepth 1 -printf '%f\n' | sort -V | tail -n 1)
  "$busybox" depmod -b "$root" "$kv"
  rm -rf "$dl"
fi
kernel=$root/boot/vmlinuz-$kv
[ -r "$kernel" ] || skip "no readable kernel image $kernel"

# --- the initramfs, cached per kernel and init script -----------------------------------------------
key=$(cat "$here/guest-init.sh" "$busybox" | sha256sum | cut -c1-12)
initrd=$cache/initramfs-$kv-$key.cpio.gz
if [ ! -f "$initrd" ]; then
  stage=$(mktemp -d "$cache/initramfs.XXXXXX")
  mkdir -p "$stage"/{bin,dev,proc,sys,newroot,lib/modules}
  cp "$busybox" "$stage/bin/busybox"
  # modules.dep lists every module a module needs, transitively; load those first.
  declare -A dep_of=() loaded=()
  while IFS=: read -r mod deps; do
    name=${mod##*/}
    dep_of[${name%.ko*}]=$deps
  done <"$root/lib/modules/$kv/modules.dep"
  order=()
  load() {
    local m=$1 d
    [ -z "${loaded[$m]:-}" ] || return 0
    loaded[$m]=1
    for d in ${dep_of[$m]}; do
      d=${d##*/}
      load "${d%.ko*}"
    done
    order+=("$m")
  }
  for m in virtio_pci 9pnet_virtio 9p; do load "$m"; done
  for m in "${order[@]}"; do
    f=$(grep -m 1 "/$m\.ko[^:]*:" "$root/lib/modules/$kv/modules.dep" | cut -d: -f1)
    cp "$root/lib/modules/$kv/$f" "$stage/lib/modules/"
    basename "$f"
  done >"$stage/modorder"
  cp "$here/guest-init.sh" "$stage/init"
  chmod 755 "$stage/init"
  (cd "$stage" && find . | cpio -o -H newc 2>/dev/null | gzip -1 >"$initrd.part")
  mv "$initrd.part" "$initrd"
  rm -rf "$stage"
  find "$cache" -maxdepth 1 -name 'initramfs-*.cpio.gz' ! -name "${initrd##*/}" -delete
fi
flock -u 9

# --- the run ----------------------------------------------------------------------------------------
[ -n "$work" ] || work=$cache/work
mkdir -p "$work"
work=$(realpath "$work")
case $work in *' '*) echo "vm-run: the work folder must not contain spaces: $work" >&2; exit 2 ;; esac
rm -f "$work/.vm-exit-code"
echo "$modules" >"$work/.vm-modules"
{
  echo "export MRSKIN_VM=1 MRSKIN_VM_MODULES='$root' PATH=/usr/sbin:/usr/bin:/sbin:/bin HOME=/tmp"
  echo "cd '$work'"
  printf 'exec'
  printf " '%s'" "$@"
  printf '\n'
} >"$work/.vm-command"

# The guest covers /tmp, /var/tmp and /run with fresh tmpfs: a checkout there (its scripts, the
# command's binaries) would vanish. The guest binds these paths back from the host's root.
keep=()
for p in "$here/../.." "$@"; do
  [ -e "$p" ] || continue
  p=$(realpath "$p")
  [ -d "$p" ] || p=$(dirname "$p")
  case $p/ in
    /tmp/* | /var/tmp/* | /run/*)
      case $p in *' '* | *:*) echo "vm-run: a path the guest needs has a space or a colon: $p" >&2; exit 2 ;; esac
      keep+=("$p")
      ;;
  esac
done
keep_arg=$(IFS=:; echo "${keep[*]:-none}")

echo "vm-run: kernel $kv, work $work, timeout ${timeout_s}s" >&2
start=$(date +%s%N)
set +e
timeout --kill-after=10 "$timeout_s" "$qemu" -accel tcg -m "${MRSKIN_VM_MEM:-1024}" \
  -smp "${MRSKIN_VM_SMP:-2}" -nographic -no-reboot -nic none \
  -kernel "$kernel" -initrd "$initrd" \
  -append "console=ttyS0 quiet panic=-1 mrskin.work=$work mrskin.modroot=$root mrskin.keep=$keep_arg" \
  -virtfs local,path=/,mount_tag=hostroot,security_model=none,readonly=on,multidevs=remap \
  -virtfs "local,path=$work,mount_tag=work,security_model=none" </dev/null |
  sed -u -e 's/\x1bc//g; s/\x1b\[[0-9;?]*[a-zA-Z]//g; s/\r//g; /SeaBIOS/d; /^Booting from ROM/d; /^$/d'
qemu_rc=${PIPESTATUS[0]}
set -e
elapsed_ms=$((($(date +%s%N) - start) / 1000000))
echo "vm-run: VM ran $((elapsed_ms / 1000)).$(printf %03d $((elapsed_ms % 1000)))s (qemu exit $qemu_rc)" >&2
if [ ! -f "$work/.vm-exit-code" ]; then
  echo "vm-run: the command did not finish (VM crashed or timed out after ${timeout_s}s)" >&2
  exit 125
fi
exit "$(cat "$work/.vm-exit-code")"
