#!/bin/bash
# vm-suite.sh WORK CAN_TEST HID_TEST USB_TEST MRSKINCTL UDEV_RELAY
# (MRSKIN_VM_PARTS: the parts to run, default all; MRSKIN_VM_TIME_SCALE: the guest's
# MRSKIN_TIME_SCALE, default 50.)
# The ctest fixture Vm.boot: one VM run that executes every part (guest-tests.sh) and leaves
# WORK/results/PART.{rc,log} for vm-result.sh. Exits 77 (and leaves WORK/results/SKIP with the
# reason) when the VM cannot run here, 0 when the guest ran whatever the parts' results,
# else the harness's failure code.
set -euo pipefail
here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
[ $# -eq 6 ] || { echo "usage: vm-suite.sh WORK CAN_TEST HID_TEST USB_TEST MRSKINCTL UDEV_RELAY" >&2; exit 2; }
work=$1
shift
mkdir -p "$work"
rm -rf "$work/results"
mkdir -p "$work/results"
rc=0
"$here/vm-run.sh" --work "$work" --timeout "${MRSKIN_VM_TIMEOUT:-270}" \
  --modules "vcan can_raw uhid hid_generic usbhid dummy_hcd libcomposite usb_f_hid" \
  -- "$here/guest-tests.sh" "$work/results" "$@" "${MRSKIN_VM_PARTS:-all}" "${MRSKIN_VM_TIME_SCALE:-50}" 2> >(tee "$work/results/harness.log" >&2) || rc=$?
wait
if [ "$rc" -eq 77 ]; then
  grep 'SKIP' "$work/results/harness.log" >"$work/results/SKIP" || echo "vm-run: SKIP" >"$work/results/SKIP"
  exit 77
fi
if [ ! -f "$work/results/guest.done" ]; then
  echo "vm-suite: the guest did not finish its parts (harness exit $rc)" >&2
  exit "$([ "$rc" -ne 0 ] && echo "$rc" || echo 1)"
fi
exit 0
