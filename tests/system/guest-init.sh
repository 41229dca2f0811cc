#!/bin/busybox sh
# shellcheck shell=dash
# /init of the VM's initramfs (busybox only). Mounts the host's root filesystem read-only
# over 9p (tag hostroot) and the work folder read-write (tag work) at the path the kernel
# command line names (mrskin.work=PATH), puts fresh tmpfs on /tmp, /var/tmp and /run and binds
# back from the host the paths mrskin.keep=A:B names, chroots into the host root and runs
# PATH/.vm-command with /bin/sh. Its exit code goes to PATH/.vm-exit-code; then power off.
# Before that it loads the modules PATH/.vm-modules names, from the unpacked kernel under
# mrskin.modroot=DIR (busybox modprobe; the host root has no modules for this kernel).
B=/bin/busybox
R=/newroot
$B mount -t proc proc /proc
$B mount -t sysfs sys /sys
$B mount -t devtmpfs dev /dev
for m in $($B cat /modorder); do $B insmod "/lib/modules/$m" 2>/dev/null; done
say() { echo "vm-init: $* at $($B cut -d' ' -f1 /proc/uptime)s"; }
off() { $B sync; $B poweroff -f; }
if ! $B mount -t 9p -o trans=virtio,version=9p2000.L,ro,msize=262144,cache=loose hostroot $R; then
  say "cannot mount the host root"
  off
fi
# A second view of the host root, for the paths bound back below once tmpfs covers their folder.
$B mkdir -p /hostro
$B mount -o bind $R /hostro
$B mount -t proc proc $R/proc
$B mount -t sysfs sys $R/sys
$B mount -t devtmpfs dev $R/dev
$B mkdir -p $R/dev/pts $R/dev/shm
$B mount -t devpts devpts $R/dev/pts
$B mount -t tmpfs shm $R/dev/shm
$B mount -t tmpfs tmp $R/tmp
$B mount -t tmpfs run $R/run
$B mount -t tmpfs vartmp $R/var/tmp
$B mount -t configfs none $R/sys/kernel/config 2>/dev/null
# The checkout and the command's folders, when they lie under one of the tmpfs (mrskin.keep=A:B).
KEEP=$($B sed -n 's/.*mrskin\.keep=\([^ ]*\).*/\1/p' /proc/cmdline)
OLDIFS=$IFS
IFS=:
for k in $KEEP; do
  [ "$k" = none ] && continue
  $B mkdir -p "$R$k" && $B mount -o bind "/hostro$k" "$R$k" || say "cannot bind $k back"
done
IFS=$OLDIFS
WORK=$($B sed -n 's/.*mrskin\.work=\([^ ]*\).*/\1/p' /proc/cmdline)
$B mkdir -p "$R$WORK" 2>/dev/null # under one of the tmpfs above
if ! $B mount -t 9p -o trans=virtio,version=9p2000.L,msize=262144 work "$R$WORK"; then
  say "cannot mount the work folder $WORK"
  off
fi
# The unpacked kernel's modules, for busybox modprobe: the host root has none for it.
MODROOT=$($B sed -n 's/.*mrskin\.modroot=\([^ ]*\).*/\1/p' /proc/cmdline)
KV=$($B uname -r)
$B mkdir -p /lib/modules
$B ln -s "$R$MODROOT/lib/modules/$KV" "/lib/modules/$KV"
for m in $($B cat "$R$WORK/.vm-modules" 2>/dev/null); do
  $B modprobe "$m" || say "modprobe $m failed"
done
say "up"
$B chroot $R /bin/sh "$WORK/.vm-command"
RC=$?
echo "$RC" >"$R$WORK/.vm-exit-code"
say "command exited with $RC"
$B sync
$B umount "$R$WORK" 2>/dev/null
off
