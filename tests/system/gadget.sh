#!/bin/sh
# gadget.sh up|down -- inside the VM: a configfs HID gadget with the MR skin's descriptors
# (protocol/include/mrskin/protocol/usb.hpp: VID 1209, PID 4d52, vendor report descriptor,
# 64-byte reports without report ID, serial 4D52C0DE as vm_support.hpp's kSerial) bound to
# dummy_hcd's UDC. The device side is /dev/hidg0. `up` leaves the gadget unbound (it would
# otherwise stand in for the uhid unit, with the same VID:PID, during the HID part): the USB
# part binds it by writing the UDC's name (`bind` prints it) to $g/UDC, and unbinds it.
set -eu
g=/sys/kernel/config/usb_gadget/mrskin
case ${1:-up} in
  up)
    mountpoint -q /sys/kernel/config || mount -t configfs none /sys/kernel/config
    mkdir -p "$g"
    cd "$g"
    echo 0x1209 >idVendor
    echo 0x4d52 >idProduct
    echo 0x0100 >bcdDevice
    echo 0x0200 >bcdUSB
    mkdir -p strings/0x409
    echo "mrskin" >strings/0x409/manufacturer
    echo "MR skin (dummy_hcd gadget, VM test)" >strings/0x409/product
    echo "4D52C0DE" >strings/0x409/serialnumber
    mkdir -p functions/hid.usb0
    echo 0 >functions/hid.usb0/protocol
    echo 0 >functions/hid.usb0/subclass
    echo 64 >functions/hid.usb0/report_length
    # kHidReportDescriptor
    printf '\006\000\377\011\001\241\001\025\000\046\377\000\165\010\225\100\011\002\201\002\225\100\011\003\221\002\300' \
      >functions/hid.usb0/report_desc
    mkdir -p configs/c.1/strings/0x409
    echo "MR skin" >configs/c.1/strings/0x409/configuration
    echo 100 >configs/c.1/MaxPower
    [ -e configs/c.1/hid.usb0 ] || ln -s functions/hid.usb0 configs/c.1/
    echo "gadget: made $g; UDCs: $(find /sys/class/udc -mindepth 1 -maxdepth 1 -printf "%f ")"
    ;;
  down)
    [ -d "$g" ] || exit 0
    echo "" >"$g/UDC" || true
    rm -f "$g/configs/c.1/hid.usb0"
    rmdir "$g/configs/c.1/strings/0x409" "$g/configs/c.1" "$g/functions/hid.usb0" "$g/strings/0x409" "$g" || true
    ;;
esac
