#!/bin/sh
# guest-tests.sh RESULTS CAN_TEST HID_TEST USB_TEST MRSKINCTL UDEV_RELAY [PARTS [TIME_SCALE]]
# Runs inside the VM (vm-run.sh). PARTS: "all" (default) or some of can_classic can_fd
# hid_uhid usb_gadget; TIME_SCALE: MRSKIN_TIME_SCALE for the parts (default 50).
# Brings up vcan0 (MTU 72, for CAN FD) and a configfs HID gadget with the unit's descriptors
# on dummy_hcd, then runs each part with the time scale raised, writing RESULTS/PART.log and
# RESULTS/PART.rc. UDEV_RELAY stands in for udevd during the USB part (libusb learns of
# arriving devices only from udev's broadcast). Exits 0 once every part has run (their
# results are in the files).
set -eu
results=$1
can_test=$2
hid_test=$3
usb_test=$4
export MRSKINCTL="$5"
udev_relay=$6
parts=${7:-all}
export MRSKIN_TIME_SCALE="${8:-50}"
export MRSKIN_VM_OUT="$results"
export XDG_RUNTIME_DIR=/run
here=$(dirname "$0")
uptime_s() { cut -d' ' -f1 /proc/uptime; }
echo "guest: kernel $(uname -r), $(nproc) CPUs, MRSKIN_TIME_SCALE=$MRSKIN_TIME_SCALE"

ip link add dev vcan0 type vcan
ip link set vcan0 mtu 72
ip link set up vcan0
MRSKIN_VM_UDC=$(find /sys/class/udc -mindepth 1 -maxdepth 1 -printf "%f\n" | head -n 1)
export MRSKIN_VM_UDC
if ! "$here/gadget.sh" up >"$results/gadget.log" 2>&1; then
  echo "guest: gadget setup failed:"
  cat "$results/gadget.log"
fi

# run_part NAME TIMEOUT COMMAND...: bounded; a part that hangs is killed and fails.
run_part() {
  name=$1
  limit=$2
  shift 2
  case " $parts " in
    *" all "* | *" $name "*) ;;
    *) return 0 ;;
  esac
  start=$(uptime_s)
  rc=0
  timeout -k 5 "$limit" "$@" >"$results/$name.log" 2>&1 || rc=$?
  echo "$rc" >"$results/$name.rc"
  echo "guest: $name exit $rc ($(awk "BEGIN { print $(uptime_s) - $start }")s)"
  grep -E '^(vm-|\[  (PASSED|FAILED|SKIPPED) )' "$results/$name.log" | sed 's/^/guest:   /' || true
}
run_part can_classic 90 "$can_test" --gtest_filter='*classic*'
run_part can_fd 90 "$can_test" --gtest_filter='*fd*'
run_part hid_uhid 90 "$hid_test"
"$udev_relay" 2>"$results/udev-relay.log" &
relay=$!
sleep 1
if kill -0 "$relay" 2>/dev/null; then
  export MRSKIN_VM_UDEV=1
fi
run_part usb_gadget 240 "$usb_test"
kill "$relay" 2>/dev/null || true
wait "$relay" 2>/dev/null || true
touch "$results/guest.done"
