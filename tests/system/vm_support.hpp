// Support for the tests that run inside the QEMU VM (tests/system): the mock firmware put
// behind a real kernel bus by a device-side adapter, a bounded wait that keeps a session
// polled, and child processes (candump, mrskinctl). Nothing here measures or asserts time:
// every wait is a hang guard scaled by MRSKIN_TIME_SCALE.
#pragma once

#include <sys/types.h>

#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/driver/session.hpp"
#include "mrskin/driver/transport.hpp"
#include "mrskin/sim/mock_device.hpp"

namespace mrskin::vmtest {

// MRSKIN_TIME_SCALE, or 1 when unset.
double time_scale();

// The serial number every simulated unit of these tests reports.
inline constexpr std::uint32_t kSerial = 0x4D52C0DE;

// A mock unit (default profile) running on its own thread against clock, with its timeouts
// scaled like the session's.
std::shared_ptr<sim::MockDevice> start_mock(Clock& clock);

// Moves datagrams between the mock firmware's end of its in-process link and a bus, on its
// own thread: what the firmware sends goes out with write_bus(), what read_bus() delivers
// goes to the firmware. Subclasses provide the bus.
class FirmwareAdapter {
 public:
  explicit FirmwareAdapter(std::shared_ptr<sim::MockDevice> mock);
  FirmwareAdapter(const FirmwareAdapter&) = delete;
  FirmwareAdapter& operator=(const FirmwareAdapter&) = delete;
  FirmwareAdapter(FirmwareAdapter&&) = delete;
  FirmwareAdapter& operator=(FirmwareAdapter&&) = delete;
  virtual ~FirmwareAdapter();

  [[nodiscard]] std::uint64_t to_bus() const noexcept { return to_bus_.load(); }
  [[nodiscard]] std::uint64_t from_bus() const noexcept { return from_bus_.load(); }
  [[nodiscard]] std::uint64_t dropped() const noexcept { return dropped_.load(); }
  [[nodiscard]] sim::MockDevice& mock() noexcept { return *mock_; }

 protected:
  // Starts the thread; call at the end of the subclass's constructor.
  void start();
  // Stops the thread; call first in the subclass's destructor.
  void stop() noexcept;
  // Waits up to timeout_ms for bus input and hands each datagram to deliver(). Returns false
  // when the bus failed for good.
  virtual bool read_bus(int timeout_ms, const std::function<void(const Datagram&)>& deliver) = 0;
  // Sends one datagram; false when it could not go out (dropped).
  virtual bool write_bus(const Datagram& d) = 0;

 private:
  void run() noexcept;
  std::shared_ptr<sim::MockDevice> mock_;
  std::unique_ptr<Transport> firmware_;
  std::atomic<bool> running_{false};
  std::atomic<std::uint64_t> to_bus_{0};
  std::atomic<std::uint64_t> from_bus_{0};
  std::atomic<std::uint64_t> dropped_{0};
  std::thread thread_;
};

// A simulated CAN node: the firmware behind open_can_transport() in the device role.
class CanNode final : public FirmwareAdapter {
 public:
  CanNode(std::shared_ptr<sim::MockDevice> mock, const std::string& uri);
  ~CanNode() override;

 private:
  bool read_bus(int timeout_ms, const std::function<void(const Datagram&)>& deliver) override;
  bool write_bus(const Datagram& d) override;
  std::unique_ptr<Transport> bus_;
};

// A virtual HID device on /dev/uhid with the unit's VID:PID, report descriptor and serial
// (HID_UNIQ): IN reports are the firmware's packets, OUT reports go to the firmware.
// unplug() destroys the kernel device (the hidraw node goes away) and pulls the firmware's
// cable; plug() creates it again.
class UhidUnit final : public FirmwareAdapter {
 public:
  explicit UhidUnit(std::shared_ptr<sim::MockDevice> mock);
  ~UhidUnit() override;
  void unplug();
  void plug();
  [[nodiscard]] bool opened() const noexcept { return opened_.load(); }  // hidraw open

 private:
  bool read_bus(int timeout_ms, const std::function<void(const Datagram&)>& deliver) override;
  bool write_bus(const Datagram& d) override;
  void create();
  void destroy();
  int fd_ = -1;
  std::atomic<bool> present_{false};
  std::atomic<bool> opened_{false};
};

// The device side of a configfs HID gadget: reads OUT reports from /dev/hidgN and writes the
// firmware's packets as IN reports. The gadget itself is made by gadget.sh; the node exists
// only while the gadget is bound to a UDC, so the adapter opens it when it appears, and
// set_open(false) closes it (before an unbind) until set_open(true).
class GadgetUnit final : public FirmwareAdapter {
 public:
  GadgetUnit(std::shared_ptr<sim::MockDevice> mock, std::string node);
  ~GadgetUnit() override;
  void set_open(bool open) noexcept { want_open_ = open; }
  [[nodiscard]] bool is_open() const noexcept { return is_open_.load(); }

 private:
  bool read_bus(int timeout_ms, const std::function<void(const Datagram&)>& deliver) override;
  bool write_bus(const Datagram& d) override;
  void close_node() noexcept;
  std::string node_;
  int fd_ = -1;
  std::atomic<bool> want_open_{true};
  std::atomic<bool> is_open_{false};
};

// Polls session (every millisecond of clock) until done() or the guard runs out
// (guard_s * time_scale() of wall time). Returns done()'s last value.
bool poll_until(DeviceSession& session, Clock& clock, const std::function<bool()>& done, double guard_s);
// A device node appears a moment after the unit does (hid_generic binding a uhid device, a
// gadget enumerating): opens again on DeviceNotFound, at most 100 times 100 ms.
OpenedDevice open_with_retry(const std::string& uri, Clock& clock);
// One line of the session's counters, prefixed ("vm-hid", "vm-usb", ...).
void print_counters(const char* prefix, const char* when, const DeviceSession& session);
// The checks every bus shares (GoogleTest assertions): the unit's identity and profile came over
// the bus, it enables, the plant's coils follow the currents sent, and telemetry flows.
void expect_session_runs(DeviceSession& session, sim::MockDevice& mock, Clock& clock);
// Unplug mid-stream is noticed and plugging back in reconnects the session with telemetry
// flowing again.
void expect_unplug_noticed_and_replug_reconnects(const char* prefix, DeviceSession& session, Clock& clock,
                                                 const std::function<void()>& unplug,
                                                 const std::function<void()>& plug, double reconnect_guard_s);

// A child process with stdout and stderr to a file; stop() sends SIGINT and reaps it.
class Child {
 public:
  Child(const std::vector<std::string>& argv, const std::string& output_path);
  Child(const Child&) = delete;
  Child& operator=(const Child&) = delete;
  Child(Child&&) = delete;
  Child& operator=(Child&&) = delete;
  ~Child();
  // The exit status (as waitpid gives it).
  int stop();

 private:
  pid_t pid_ = -1;
};

// Runs a command through /bin/sh -c; returns its exit code and appends its output to *output.
int run_command(const std::string& command, std::string* output = nullptr);

// Where the tests keep what they record: $MRSKIN_VM_OUT, else the current directory.
std::string output_dir();

}  // namespace mrskin::vmtest
