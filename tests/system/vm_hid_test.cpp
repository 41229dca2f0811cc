// Inside the VM: the hid:// transport (hidapi, hidraw backend) against a uhid virtual device
// with the unit's VID:PID, report descriptor and serial, answered by the mock firmware.
// Handshake, commands and telemetry; then the device is destroyed mid-stream (unplug), the
// session sees the link go, and reconnects when the device is created again.
#include <gtest/gtest.h>

#include <cstdio>
#include <cstdlib>
#include <string>
#include <thread>
#include <vector>

#include "mrskin/driver/device.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/protocol/usb.hpp"
#include "vm_support.hpp"

namespace mrskin::vmtest {
namespace {

TEST(HidVm, UhidDeviceRunsTheSessionAndReconnectsAfterAnUnplug) {
  MonotonicClock clock;
  auto mock = start_mock(clock);
  UhidUnit unit(mock);
  auto opened = open_with_retry("hid://1209:4d52", clock);
  DeviceSession& session = *opened.session;
  EXPECT_TRUE(unit.opened());

  expect_session_runs(session, *mock, clock);
  print_counters("vm-hid", "streaming", session);
  // Unplug mid-stream (the hidraw node goes away), then plug in again: the session reconnects to
  // the same unit by itself.
  expect_unplug_noticed_and_replug_reconnects(
      "vm-hid", session, clock, [&] { unit.unplug(); }, [&] { unit.plug(); }, 20.0);
  // The unit rebooted DISABLED; it enables again.
  ASSERT_EQ(session.request_enable(), ResultCode::ok);
  EXPECT_TRUE(poll_until(
      session, clock, [&] { return session.state() == DeviceState::enabled; }, 5.0));
  print_counters("vm-hid", "replugged", session);
  std::printf("vm-hid: adapter to bus %llu, from bus %llu, dropped %llu\n",
              static_cast<unsigned long long>(unit.to_bus()),
              static_cast<unsigned long long>(unit.from_bus()),
              static_cast<unsigned long long>(unit.dropped()));
  opened.session.reset();

  // mrskinctl lists the unit (its own process, hidapi's enumeration).
  if (const char* ctl = std::getenv("MRSKINCTL"); ctl != nullptr) {
    std::string out;
    EXPECT_EQ(run_command(std::string(ctl) + " list --json", &out), 0) << out;
    std::printf("vm-hid: mrskinctl list --json: %s\n", out.c_str());
    EXPECT_NE(out.find("hid://1209:4d52"), std::string::npos) << out;
  }
}

}  // namespace
}  // namespace mrskin::vmtest
