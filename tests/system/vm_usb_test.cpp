// Inside the VM: the usb:// transport (libusb, interrupt transfers on the HID interface)
// against a configfs HID gadget on dummy_hcd with the unit's descriptors, its device side
// answered by the mock firmware through /dev/hidgN: enumeration and `mrskinctl list`, the
// transport's interrupt IN transfers and hotplug (the gadget unbound from and bound to its
// UDC), and the whole session through a hotplug. gadget.sh makes the gadget.
#include <gtest/gtest.h>

#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <string>
#include <thread>
#include <vector>

#include "mrskin/driver/device.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/transports/usb.hpp"
#include "mrskin/protocol/usb.hpp"
#include "vm_support.hpp"

namespace mrskin::vmtest {
namespace {

std::string env_or(const char* name, const char* fallback) {
  const char* v = std::getenv(name);
  return v != nullptr && *v != '\0' ? std::string(v) : std::string(fallback);
}

// Binds the gadget to the UDC ("" unbinds it: the device leaves the bus).
void bind_gadget(const std::string& udc) {
  std::ofstream f(env_or("MRSKIN_VM_GADGET", "/sys/kernel/config/usb_gadget/mrskin") + "/UDC");
  f << (udc.empty() ? std::string("\n") : udc + "\n");
}

// The gadget bound to the UDC for one test, with its device side answered by the mock
// firmware; unbound at the end (so the next test, or the HID part, does not see it).
class Gadget {
 public:
  explicit Gadget(Clock& clock) : udc_(env_or("MRSKIN_VM_UDC", "dummy_udc.0")), mock_(start_mock(clock)) {
    bind_gadget(udc_);
    unit_ = std::make_unique<GadgetUnit>(mock_, env_or("MRSKIN_VM_HIDG", "/dev/hidg0"));
  }
  Gadget(const Gadget&) = delete;
  Gadget& operator=(const Gadget&) = delete;
  Gadget(Gadget&&) = delete;
  Gadget& operator=(Gadget&&) = delete;
  ~Gadget() {
    unit_.reset();
    bind_gadget("");
    mock_->stop();
  }
  // Waits (bounded) until the host has enumerated it and the device side is open; returns
  // the interface's endpoints as sysfs shows them ("ep_81: 81 Interrupt" lines).
  std::string wait_enumerated() {
    std::string eps;
    for (int i = 0; i < 100 && eps.find("1-1:1.0") == std::string::npos; ++i) {
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
      eps.clear();
      (void)run_command(
          "for f in /sys/bus/usb/devices/1-1/1-1:1.0/ep_*/bEndpointAddress; do [ -r \"$f\" ] && "
          "echo \"${f%/*}: $(cat \"$f\") $(cat \"${f%/*}/type\")\"; done; true",
          &eps);
    }
    for (int i = 0; i < 100 && !unit_->is_open(); ++i) {
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    return eps;
  }
  // Hotplug: the gadget leaves the bus (unbound from its UDC) or comes back.
  void unplug() {
    mock_->set_link_up(false);
    unit_->set_open(false);
    bind_gadget("");
  }
  void plug() {
    bind_gadget(udc_);
    unit_->set_open(true);
    mock_->set_link_up(true);
  }
  [[nodiscard]] sim::MockDevice& mock() { return *mock_; }
  [[nodiscard]] GadgetUnit& unit() { return *unit_; }

 private:
  std::string udc_;
  std::shared_ptr<sim::MockDevice> mock_;
  std::unique_ptr<GadgetUnit> unit_;
};

// Datagrams the transport delivers within a bounded wait.
std::size_t receive_some(Transport& t, std::size_t want) {
  std::size_t got = 0;
  Datagram d;
  for (int i = 0; i < 2000 && got < want; ++i) {
    if (t.receive_for(d, std::chrono::milliseconds(10)) == ResultCode::ok) {
      ++got;
    }
  }
  return got;
}

TEST(UsbVm, GadgetEnumeratesWithTheUnitsDescriptorsAndMrskinctlListsIt) {
  MonotonicClock clock;
  Gadget gadget(clock);
  const std::string eps = gadget.wait_enumerated();
  std::printf("vm-usb: gadget enumerated; interface 0 endpoints:\n%s", eps.c_str());
  EXPECT_NE(eps.find("ep_81: 81 Interrupt"), std::string::npos) << eps;
  std::string ids;
  (void)run_command(
      "cat /sys/bus/usb/devices/1-1/idVendor /sys/bus/usb/devices/1-1/idProduct "
      "/sys/bus/usb/devices/1-1/serial",
      &ids);
  EXPECT_EQ(ids, "1209\n4d52\n" + protocol::format_usb_serial(kSerial) + "\n");
  ASSERT_TRUE(gadget.unit().is_open()) << "no /dev/hidg0";
  if (const char* ctl = std::getenv("MRSKINCTL"); ctl != nullptr) {
    std::string out;
    EXPECT_EQ(run_command(std::string(ctl) + " list --json", &out), 0) << out;
    std::printf("vm-usb: mrskinctl list --json: %s\n", out.c_str());
    EXPECT_NE(out.find("\"uri\": \"usb://1209:4d52?serial=" + protocol::format_usb_serial(kSerial) +
                       "\", \"path\": \"1-1\""),
              std::string::npos)
        << out;
  }
}

// The transport on its own: enumeration, interrupt IN transfers (the firmware's telemetry,
// sent whether or not a host talks to it), and hotplug (unplug noticed, reopened by itself).
TEST(UsbVm, TransportReadsInterruptInAndFollowsHotplug) {
  MonotonicClock clock;
  Gadget gadget(clock);
  (void)gadget.wait_enumerated();
  UsbTransportOptions options;
  options.time_scale = time_scale();
  std::unique_ptr<Transport> t;
  for (int i = 0; i < 100 && !t; ++i) {
    try {
      t = open_usb_transport("usb://1209:4d52", options);
    } catch (const DeviceNotFound&) {
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
  }
  ASSERT_TRUE(t) << "usb://1209:4d52 never opened";
  EXPECT_EQ(t->state(), TransportState::open);
  EXPECT_EQ(receive_some(*t, 20), 20U) << "no interrupt IN reports";

  gadget.unplug();
  for (int i = 0; i < 2000 && t->state() == TransportState::open; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  EXPECT_EQ(t->state(), TransportState::disconnected);
  // libusb (built with udev) learns of a device that arrives only from udevd's event
  // broadcast: without a udev daemon in the guest the transport cannot see the replug.
  if (std::getenv("MRSKIN_VM_UDEV") == nullptr) {
    const TransportCounters c = t->counters();
    std::printf(
        "vm-usb: transport: received %llu, disconnects %llu; replug not tried (no udev in the guest)\n",
        static_cast<unsigned long long>(c.received), static_cast<unsigned long long>(c.disconnects));
    EXPECT_GE(c.disconnects, 1U);
    GTEST_SKIP()
        << "unplug detected; the replug needs udev events (libusb's hotplug and device list come from "
           "udevd's broadcast), and the guest runs no udev daemon";
  }
  gadget.plug();
  for (int i = 0; i < 4000 && t->state() != TransportState::open; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  EXPECT_EQ(t->state(), TransportState::open);
  EXPECT_EQ(receive_some(*t, 20), 20U) << "no interrupt IN reports after the replug";
  const TransportCounters c = t->counters();
  std::printf("vm-usb: transport: received %llu, sent %llu, disconnects %llu, reopens %llu, io errors %llu\n",
              static_cast<unsigned long long>(c.received), static_cast<unsigned long long>(c.sent),
              static_cast<unsigned long long>(c.disconnects), static_cast<unsigned long long>(c.reopens),
              static_cast<unsigned long long>(c.io_errors));
  EXPECT_GE(c.disconnects, 1U);
  EXPECT_GE(c.reopens, 1U);
}

// hid:// on the same gadget: hidapi over usbhid's hidraw node, through the real USB stack (the
// kernel's HID driver uses the endpoints the descriptors name).
TEST(UsbVm, HidSessionRunsOverTheGadget) {
  MonotonicClock clock;
  Gadget gadget(clock);
  (void)gadget.wait_enumerated();
  auto opened = open_with_retry("hid://1209:4d52", clock);
  DeviceSession& session = *opened.session;
  expect_session_runs(session, gadget.mock(), clock);
  print_counters("vm-usb", "hid:// over the gadget", session);
}

// The whole session over usb://, through a hotplug.
TEST(UsbVm, SessionRunsOverTheGadgetThroughHotplug) {
  MonotonicClock clock;
  Gadget gadget(clock);
  const std::string eps = gadget.wait_enumerated();
  // dummy_hcd numbers the gadget's interrupt OUT endpoint 0x02, not the protocol's 0x01: the
  // usb:// transport takes both endpoints from the interface descriptor.
  std::printf("vm-usb: endpoints:\n%s", eps.c_str());
  auto opened = open_with_retry("usb://1209:4d52", clock);
  DeviceSession& session = *opened.session;
  expect_session_runs(session, gadget.mock(), clock);
  print_counters("vm-usb", "streaming", session);
  expect_unplug_noticed_and_replug_reconnects(
      "vm-usb", session, clock, [&] { gadget.unplug(); }, [&] { gadget.plug(); }, 30.0);
  print_counters("vm-usb", "replugged", session);
}

}  // namespace
}  // namespace mrskin::vmtest
