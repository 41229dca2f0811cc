// Tests of the usb:// transport: its logic on a fake libusb (LibusbApi), and a session over
// it to an in-process mock device. The real kernel path is the kernel integration tests' job.
#include <gtest/gtest.h>
#include <libusb-1.0/libusb.h>
#include <poll.h>
#include <sys/eventfd.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdlib>
#include <deque>
#include <functional>
#include <mutex>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "mrskin/driver/session.hpp"
#include "mrskin/protocol/packet.hpp"
#include "mrskin/sim/mock_device.hpp"
#include "transports/libusb_api.hpp"

namespace mrskin {
namespace {

using namespace std::chrono_literals;
namespace proto = protocol;

struct FakeDevice {
  std::uint16_t vendor_id = proto::kUsbVendorId;
  std::uint16_t product_id = proto::kUsbProductId;
  std::string serial = "4D520001";
  std::uint8_t bus = 1;
  std::uint8_t address = 4;
  std::vector<std::uint8_t> ports{2, 3};
  bool present = true;
  bool kernel_driver = true;  // usbhid bound to interface 0
  int open_error = 0;         // open() returns it while open_failures > 0 (-1: always)
  int open_failures = 0;
  int claim_error = 0;
  bool claimed = false;
  int opened = 0;  // handles open now
};

struct OutReport {
  unsigned char endpoint = 0;
  std::vector<std::uint8_t> bytes;
};

// libusb in memory: devices, transfers that complete when the test says so, hotplug events.
// Callbacks run inside handle_events() on the caller's thread, as libusb runs them.
class FakeLibusb final : public LibusbApi {
 public:
  explicit FakeLibusb(bool hotplug = false)
      : hotplug_capable_(hotplug), event_fd_(::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC)) {}
  FakeLibusb(const FakeLibusb&) = delete;
  FakeLibusb& operator=(const FakeLibusb&) = delete;
  FakeLibusb(FakeLibusb&&) = delete;
  FakeLibusb& operator=(FakeLibusb&&) = delete;
  ~FakeLibusb() override { ::close(event_fd_); }

  // --- test side --------------------------------------------------------------------------
  FakeDevice& add(FakeDevice d) {
    const std::lock_guard lock(m_);
    devices_.push_back(std::make_unique<FakeDevice>(std::move(d)));
    return *devices_.back();
  }
  template <class F>
  void with_device(std::size_t i, F f) {
    const std::lock_guard lock(m_);
    f(*devices_.at(i));
  }
  void inject_in(std::vector<std::uint8_t> bytes, libusb_transfer_status status = LIBUSB_TRANSFER_COMPLETED) {
    const std::lock_guard lock(m_);
    in_data_.emplace_back(std::move(bytes), status);
    signal();
  }
  void set_out_status(libusb_transfer_status s) {
    const std::lock_guard lock(m_);
    out_status_ = s;
  }
  void set_out_hold(bool hold) {
    const std::lock_guard lock(m_);
    out_hold_ = hold;
  }
  // The cable is pulled: in-flight transfers fail with NO_DEVICE (fail_transfers) and/or a
  // departure event comes (hotplug).
  void unplug(std::size_t i, bool fail_transfers) {
    const std::lock_guard lock(m_);
    FakeDevice& d = *devices_.at(i);
    d.present = false;
    if (fail_transfers) {
      for (auto* q : {&pending_in_, &held_out_}) {
        for (libusb_transfer* t : *q) {
          complete(t, LIBUSB_TRANSFER_NO_DEVICE);
        }
        q->clear();
      }
    }
    if (hotplug_capable_) {
      events_.emplace_back(as_device(d), false);
    }
    signal();
  }
  void replug(std::size_t i) {
    const std::lock_guard lock(m_);
    FakeDevice& d = *devices_.at(i);
    d.present = true;
    d.kernel_driver = true;  // usbhid binds again on enumeration
    ++d.address;
    if (hotplug_capable_) {
      events_.emplace_back(as_device(d), true);
    }
    signal();
  }
  void attach_link(std::unique_ptr<Transport> link) {
    const std::lock_guard lock(m_);
    link_ = std::move(link);
  }
  std::vector<std::string> calls() {
    const std::lock_guard lock(m_);
    return calls_;
  }
  std::size_t count(const std::string& call) {
    const std::lock_guard lock(m_);
    return static_cast<std::size_t>(std::count(calls_.begin(), calls_.end(), call));
  }
  std::vector<OutReport> written() {
    const std::lock_guard lock(m_);
    return written_;
  }
  std::size_t pending_in() {
    const std::lock_guard lock(m_);
    return pending_in_.size();
  }
  std::size_t allocs() {
    const std::lock_guard lock(m_);
    return allocs_;
  }
  std::size_t frees() {
    const std::lock_guard lock(m_);
    return frees_;
  }
  std::size_t open_handles() {
    const std::lock_guard lock(m_);
    std::size_t n = 0;
    for (const auto& d : devices_) {
      n += static_cast<std::size_t>(d->opened);
    }
    return n;
  }
  int init_result = LIBUSB_SUCCESS;

  // --- LibusbApi ----------------------------------------------------------------------------
  int init() override {
    log("init");
    return init_result;
  }
  void exit() noexcept override { log("exit"); }
  bool has_hotplug() override { return hotplug_capable_; }
  std::ptrdiff_t get_device_list(libusb_device*** list) override {
    const std::lock_guard lock(m_);
    auto* out = new libusb_device*[devices_.size() + 1];
    std::size_t n = 0;
    for (const auto& d : devices_) {
      if (d->present) {
        out[n++] = as_device(*d);
      }
    }
    out[n] = nullptr;
    *list = out;
    return static_cast<std::ptrdiff_t>(n);
  }
  void free_device_list(libusb_device** list) override { delete[] list; }
  int get_device_ids(libusb_device* device, UsbDeviceIds& out) override {
    const std::lock_guard lock(m_);
    const FakeDevice& d = of(device);
    out = UsbDeviceIds{d.vendor_id, d.product_id, static_cast<std::uint8_t>(d.serial.empty() ? 0 : 3)};
    return LIBUSB_SUCCESS;
  }
  std::uint8_t get_bus_number(libusb_device* device) override {
    const std::lock_guard lock(m_);
    return of(device).bus;
  }
  std::uint8_t get_device_address(libusb_device* device) override {
    const std::lock_guard lock(m_);
    return of(device).address;
  }
  int get_port_numbers(libusb_device* device, std::span<std::uint8_t> out) override {
    const std::lock_guard lock(m_);
    const FakeDevice& d = of(device);
    std::copy(d.ports.begin(), d.ports.end(), out.begin());
    return static_cast<int>(d.ports.size());
  }
  int open(libusb_device* device, libusb_device_handle** handle) override {
    const std::lock_guard lock(m_);
    FakeDevice& d = of(device);
    calls_.push_back("open " + d.serial);
    if (!d.present) {
      return LIBUSB_ERROR_NO_DEVICE;
    }
    if (d.open_failures != 0) {
      d.open_failures -= d.open_failures > 0 ? 1 : 0;
      return d.open_error;
    }
    ++d.opened;
    *handle = reinterpret_cast<libusb_device_handle*>(&d);
    return LIBUSB_SUCCESS;
  }
  void close(libusb_device_handle* handle) override {
    const std::lock_guard lock(m_);
    calls_.emplace_back("close");
    --of(handle).opened;
  }
  libusb_device* get_device(libusb_device_handle* handle) override {
    return reinterpret_cast<libusb_device*>(handle);
  }
  int get_string_descriptor_ascii(libusb_device_handle* handle, std::uint8_t /*index*/,
                                  std::span<unsigned char> out) override {
    const std::lock_guard lock(m_);
    const std::string& s = of(handle).serial;
    std::copy(s.begin(), s.end(), out.begin());
    return static_cast<int>(s.size());
  }
  int kernel_driver_active(libusb_device_handle* handle, int interface) override {
    const std::lock_guard lock(m_);
    EXPECT_EQ(interface, 0);
    return of(handle).kernel_driver ? 1 : 0;
  }
  int detach_kernel_driver(libusb_device_handle* handle, int /*interface*/) override {
    const std::lock_guard lock(m_);
    calls_.emplace_back("detach");
    of(handle).kernel_driver = false;
    return LIBUSB_SUCCESS;
  }
  int attach_kernel_driver(libusb_device_handle* handle, int /*interface*/) override {
    const std::lock_guard lock(m_);
    calls_.emplace_back("attach");
    FakeDevice& d = of(handle);
    if (!d.present) {
      return LIBUSB_ERROR_NO_DEVICE;
    }
    d.kernel_driver = true;
    return LIBUSB_SUCCESS;
  }
  int claim_interface(libusb_device_handle* handle, int interface) override {
    const std::lock_guard lock(m_);
    EXPECT_EQ(interface, 0);
    calls_.emplace_back("claim");
    FakeDevice& d = of(handle);
    if (d.claim_error != 0) {
      return d.claim_error;
    }
    d.claimed = true;
    return LIBUSB_SUCCESS;
  }
  int release_interface(libusb_device_handle* handle, int /*interface*/) override {
    const std::lock_guard lock(m_);
    calls_.emplace_back("release");
    of(handle).claimed = false;
    return LIBUSB_SUCCESS;
  }
  int clear_halt(libusb_device_handle* /*handle*/, std::uint8_t endpoint) override {
    const std::lock_guard lock(m_);
    calls_.push_back("clear_halt " + std::to_string(endpoint));
    return LIBUSB_SUCCESS;
  }
  libusb_transfer* alloc_transfer() override {
    const std::lock_guard lock(m_);
    ++allocs_;
    return static_cast<libusb_transfer*>(std::calloc(1, sizeof(libusb_transfer)));
  }
  void free_transfer(libusb_transfer* transfer) override {
    const std::lock_guard lock(m_);
    ++frees_;
    std::free(transfer);
  }
  int submit_transfer(libusb_transfer* t) override {
    const std::lock_guard lock(m_);
    EXPECT_EQ(t->type, LIBUSB_TRANSFER_TYPE_INTERRUPT);
    FakeDevice& d = of(t->dev_handle);
    if (!d.present) {
      return LIBUSB_ERROR_NO_DEVICE;
    }
    if ((t->endpoint & LIBUSB_ENDPOINT_IN) != 0) {
      pending_in_.push_back(t);
      signal();  // data may be waiting for it
      return LIBUSB_SUCCESS;
    }
    written_.push_back(OutReport{t->endpoint, std::vector<std::uint8_t>(t->buffer, t->buffer + t->length)});
    if (link_) {
      (void)link_->send(std::span<const std::uint8_t>(t->buffer, static_cast<std::size_t>(t->length)));
    }
    if (out_hold_) {
      held_out_.push_back(t);
    } else {
      t->actual_length = out_status_ == LIBUSB_TRANSFER_COMPLETED ? t->length : 0;
      complete(t, out_status_);
    }
    signal();
    return LIBUSB_SUCCESS;
  }
  int cancel_transfer(libusb_transfer* t) override {
    const std::lock_guard lock(m_);
    for (auto* q : {&pending_in_, &held_out_}) {
      if (const auto it = std::find(q->begin(), q->end(), t); it != q->end()) {
        q->erase(it);
        calls_.emplace_back("cancel");
        complete(t, LIBUSB_TRANSFER_CANCELLED);
        signal();
        return LIBUSB_SUCCESS;
      }
    }
    return LIBUSB_ERROR_NOT_FOUND;
  }
  void get_pollfds(std::vector<pollfd>& out) override { out.assign(1, pollfd{event_fd_, POLLIN, 0}); }
  int get_next_timeout(Duration& timeout) override {
    const std::lock_guard lock(m_);
    timeout = 1ms;  // the mock link has no descriptor: poll it every ms, as libusb without timerfd
    return link_ ? 1 : 0;
  }
  int handle_events(Duration timeout) override {
    pollfd p{event_fd_, POLLIN, 0};
    (void)::poll(&p, 1, static_cast<int>(std::chrono::ceil<std::chrono::milliseconds>(timeout).count()));
    std::uint64_t value = 0;
    (void)!::read(event_fd_, &value, sizeof value);
    std::deque<libusb_transfer*> done;
    std::deque<std::pair<libusb_device*, bool>> events;
    UsbHotplugFn fn = nullptr;
    void* user = nullptr;
    {
      const std::lock_guard lock(m_);
      while (!pending_in_.empty() && !in_data_.empty()) {
        libusb_transfer* t = pending_in_.front();
        pending_in_.pop_front();
        auto& [bytes, status] = in_data_.front();
        std::copy(bytes.begin(), bytes.end(), t->buffer);
        t->actual_length = static_cast<int>(bytes.size());
        complete(t, status);
        in_data_.pop_front();
      }
      Datagram d;
      while (link_ && !pending_in_.empty() && of(pending_in_.front()->dev_handle).present &&
             link_->receive(d) == ResultCode::ok) {
        libusb_transfer* t = pending_in_.front();
        pending_in_.pop_front();
        std::copy_n(d.bytes.begin(), d.length, t->buffer);
        t->actual_length = d.length;
        complete(t, LIBUSB_TRANSFER_COMPLETED);
      }
      done.swap(completions_);
      events.swap(events_);
      fn = hotplug_fn_;
      user = hotplug_user_;
    }
    for (const auto& [device, arrived] : events) {
      if (fn != nullptr) {
        fn(user, device, arrived);
      }
    }
    for (libusb_transfer* t : done) {
      t->callback(t);
    }
    return LIBUSB_SUCCESS;
  }
  int hotplug_register(std::uint16_t vendor_id, std::uint16_t product_id, UsbHotplugFn fn, void* user,
                       int& handle) override {
    const std::lock_guard lock(m_);
    calls_.push_back("hotplug_register " + std::to_string(vendor_id) + ":" + std::to_string(product_id));
    hotplug_fn_ = fn;
    hotplug_user_ = user;
    handle = 7;
    return LIBUSB_SUCCESS;
  }
  void hotplug_deregister(int handle) noexcept override {
    const std::lock_guard lock(m_);
    calls_.push_back("hotplug_deregister " + std::to_string(handle));
    hotplug_fn_ = nullptr;
  }

 private:
  static libusb_device* as_device(FakeDevice& d) { return reinterpret_cast<libusb_device*>(&d); }
  static FakeDevice& of(libusb_device* d) { return *reinterpret_cast<FakeDevice*>(d); }
  static FakeDevice& of(libusb_device_handle* h) { return *reinterpret_cast<FakeDevice*>(h); }
  void complete(libusb_transfer* t, libusb_transfer_status status) {
    t->status = status;
    completions_.push_back(t);
  }
  void signal() const {
    const std::uint64_t one = 1;
    (void)!::write(event_fd_, &one, sizeof one);
  }
  void log(const char* call) {
    const std::lock_guard lock(m_);
    calls_.emplace_back(call);
  }

  std::mutex m_;
  bool hotplug_capable_;
  int event_fd_;
  std::vector<std::unique_ptr<FakeDevice>> devices_;
  std::vector<std::string> calls_;
  std::size_t allocs_ = 0;
  std::size_t frees_ = 0;
  std::deque<libusb_transfer*> pending_in_;
  std::deque<libusb_transfer*> held_out_;
  std::deque<std::pair<std::vector<std::uint8_t>, libusb_transfer_status>> in_data_;
  std::deque<libusb_transfer*> completions_;
  std::deque<std::pair<libusb_device*, bool>> events_;
  std::vector<OutReport> written_;
  libusb_transfer_status out_status_ = LIBUSB_TRANSFER_COMPLETED;
  bool out_hold_ = false;
  UsbHotplugFn hotplug_fn_ = nullptr;
  void* hotplug_user_ = nullptr;
  std::unique_ptr<Transport> link_;
};

// Waits for a condition the transport's thread brings about; the limit only stops a hang.
template <class P>
bool eventually(P done) {
  const auto until = std::chrono::steady_clock::now() + 20s;
  while (!done()) {
    if (std::chrono::steady_clock::now() > until) {
      return false;
    }
    std::this_thread::sleep_for(200us);
  }
  return true;
}

UsbTransportOptions fast() {
  UsbTransportOptions o;
  o.reopen_backoff_min = 1ms;
  o.reopen_backoff_max = 5ms;
  o.reopen_window = 60s;
  return o;
}

std::vector<std::uint8_t> heartbeat_report(std::uint16_t counter) {
  std::array<std::uint8_t, proto::kHidReportBytes> r{};
  EXPECT_EQ(proto::encode_hid_report(proto::Heartbeat{counter}, 5, r).error, proto::Error::ok);
  return {r.begin(), r.end()};
}

template <class E>
std::string thrown_message(const std::function<void()>& f) {
  try {
    f();
  } catch (const E& e) {
    return e.what();
  } catch (const std::exception& e) {
    return std::string("wrong exception type: ") + e.what();
  }
  return "nothing thrown";
}

// --- URI -------------------------------------------------------------------------------------

TEST(UsbUriTest, DefaultsAndExplicitIds) {
  const UsbUri d = parse_usb_uri("usb://");
  EXPECT_EQ(d.vendor_id, 0x1209);
  EXPECT_EQ(d.product_id, 0x4d52);
  EXPECT_EQ(d.serial, "");
  const UsbUri e = parse_usb_uri("usb://ABCD:12?serial=4d52beef");
  EXPECT_EQ(e.vendor_id, 0xabcd);
  EXPECT_EQ(e.product_id, 0x0012);
  EXPECT_EQ(e.serial, "4D52BEEF");  // as the unit's string descriptor spells it
  EXPECT_EQ(parse_usb_uri("usb://?serial=0000beef").serial, "0000BEEF");
}

TEST(UsbUriTest, BadPartsAreNamed) {
  const auto bad = [](std::string_view uri) {
    return thrown_message<InvalidArgument>([&] { (void)parse_usb_uri(uri); });
  };
  EXPECT_NE(bad("hid://1209:4d52").find("not a usb:// URI"), std::string::npos);
  EXPECT_NE(bad("usb://12g9:4d52").find("vendor id '12g9'"), std::string::npos);
  EXPECT_NE(bad("usb://1209:4d521").find("product id '4d521'"), std::string::npos);
  EXPECT_NE(bad("usb://1209").find("'1209' is not VID:PID"), std::string::npos);
  EXPECT_NE(bad("usb://1209:").find("product id ''"), std::string::npos);
  EXPECT_NE(bad("usb://1209:4d52?node=3").find("unknown parameter 'node'"), std::string::npos);
  EXPECT_NE(bad("usb://1209:4d52?serial=BEEF").find("serial 'BEEF' is not 8 hex digits"), std::string::npos);
  EXPECT_NE(bad("usb://1209:4d52?serial=").find("serial ''"), std::string::npos);
}

// --- open and close --------------------------------------------------------------------------

TEST(UsbOpenTest, DetachesKernelDriverClaimsAndReattachesOnClose) {
  auto fake = std::make_shared<FakeLibusb>(true);
  fake->add({});
  auto t = open_usb_transport("usb://1209:4d52", fake, fast());
  EXPECT_EQ(t->state(), TransportState::open);
  EXPECT_EQ(t->uri(), "usb://1209:4d52");
  EXPECT_EQ(fake->count("detach"), 1U);
  EXPECT_EQ(fake->count("claim"), 1U);
  EXPECT_EQ(fake->count("hotplug_register 4617:19794"), 1U);
  fake->with_device(0, [](FakeDevice& d) {
    EXPECT_FALSE(d.kernel_driver);
    EXPECT_TRUE(d.claimed);
  });
  EXPECT_TRUE(eventually([&] { return fake->pending_in() == 4; }));
  t.reset();
  const std::vector<std::string> calls = fake->calls();
  const auto at = [&](const std::string& c) {
    return std::find(calls.begin(), calls.end(), c) - calls.begin();
  };
  // Order of a clean shutdown: cancel, release, re-attach, close, deregister, exit.
  EXPECT_EQ(fake->count("cancel"), 4U);
  EXPECT_LT(at("cancel"), at("release"));
  EXPECT_LT(at("release"), at("attach"));
  EXPECT_LT(at("attach"), at("close"));
  EXPECT_LT(at("close"), at("hotplug_deregister 7"));
  EXPECT_LT(at("hotplug_deregister 7"), at("exit"));
  fake->with_device(0, [](FakeDevice& d) {
    EXPECT_TRUE(d.kernel_driver);
    EXPECT_FALSE(d.claimed);
  });
  EXPECT_EQ(fake->open_handles(), 0U);
  EXPECT_EQ(fake->frees(), fake->allocs());
}

TEST(UsbOpenTest, NoKernelDriverNothingToDetachOrReattach) {
  auto fake = std::make_shared<FakeLibusb>();
  FakeDevice d;
  d.kernel_driver = false;
  fake->add(d);
  open_usb_transport("usb://", fake, fast()).reset();
  EXPECT_EQ(fake->count("detach"), 0U);
  EXPECT_EQ(fake->count("attach"), 0U);
  EXPECT_EQ(fake->count("release"), 1U);
  EXPECT_EQ(fake->count("hotplug_register 4617:19794"), 0U);  // no hotplug capability
}

TEST(UsbOpenTest, AccessDeniedNamesNodeRuleAndGroup) {
  auto fake = std::make_shared<FakeLibusb>();
  FakeDevice d;
  d.bus = 3;
  d.address = 7;
  d.open_error = LIBUSB_ERROR_ACCESS;
  d.open_failures = -1;
  fake->add(d);
  const std::string m = thrown_message<PermissionDenied>([&] { (void)open_usb_transport("usb://", fake); });
  EXPECT_NE(m.find("permission denied"), std::string::npos) << m;
  EXPECT_NE(m.find("/dev/bus/usb/003/007"), std::string::npos) << m;
  EXPECT_NE(m.find("udev/70-mrskin.rules"), std::string::npos) << m;
  EXPECT_NE(m.find("mrskin group"), std::string::npos) << m;
  EXPECT_EQ(fake->count("exit"), 1U);
  EXPECT_EQ(fake->frees(), fake->allocs());
}

TEST(UsbOpenTest, ClaimedElsewhereIsBusyAndTheDriverIsReattached) {
  auto fake = std::make_shared<FakeLibusb>();
  FakeDevice d;
  d.claim_error = LIBUSB_ERROR_BUSY;
  fake->add(d);
  const std::string m = thrown_message<DeviceBusy>([&] { (void)open_usb_transport("usb://", fake); });
  EXPECT_NE(m.find("claimed by another program or kernel driver"), std::string::npos) << m;
  EXPECT_NE(m.find("/dev/bus/usb/001/004"), std::string::npos) << m;
  EXPECT_EQ(fake->count("detach"), 1U);
  EXPECT_EQ(fake->count("attach"), 1U);
  EXPECT_EQ(fake->open_handles(), 0U);
  EXPECT_EQ(fake->count("exit"), 1U);
}

TEST(UsbOpenTest, NotFoundSaysWhatWasSeen) {
  auto fake = std::make_shared<FakeLibusb>();
  std::string m = thrown_message<DeviceNotFound>([&] { (void)open_usb_transport("usb://", fake); });
  EXPECT_NE(m.find("no MR skin with USB id 1209:4d52 is attached"), std::string::npos) << m;
  EXPECT_NE(m.find("mrskinctl list"), std::string::npos) << m;
  FakeDevice other;
  other.vendor_id = 0x1234;
  fake->add(other);
  fake->add({});
  m = thrown_message<DeviceNotFound>(
      [&] { (void)open_usb_transport("usb://1209:4d52?serial=0000BEEF", fake); });
  EXPECT_NE(m.find("and serial 0000BEEF"), std::string::npos) << m;
  EXPECT_NE(m.find("units seen with serials 4D520001"), std::string::npos) << m;
  EXPECT_EQ(fake->open_handles(), 0U);
}

TEST(UsbOpenTest, SerialSelectsTheUnit) {
  auto fake = std::make_shared<FakeLibusb>();
  fake->add({});
  FakeDevice second;
  second.serial = "0000BEEF";
  second.address = 9;
  fake->add(second);
  auto t = open_usb_transport("usb://?serial=0000beef", fake, fast());
  fake->with_device(0, [](FakeDevice& d) { EXPECT_FALSE(d.claimed); });
  fake->with_device(1, [](FakeDevice& d) { EXPECT_TRUE(d.claimed); });
}

TEST(UsbOpenTest, NoUsbAtAll) {
  auto fake = std::make_shared<FakeLibusb>();
  fake->init_result = LIBUSB_ERROR_OTHER;
  const std::string m = thrown_message<DeviceNotFound>([&] { (void)open_usb_transport("usb://", fake); });
  EXPECT_NE(m.find("USB is not available"), std::string::npos) << m;
  EXPECT_NE(m.find("/dev/bus/usb"), std::string::npos) << m;
  EXPECT_EQ(fake->count("exit"), 0U);  // nothing to exit after a failed init
}

// --- framing ---------------------------------------------------------------------------------

TEST(UsbFramingTest, OutReportIs64BytesWithoutReportId) {
  auto fake = std::make_shared<FakeLibusb>();
  fake->add({});
  auto t = open_usb_transport("usb://", fake, fast());
  std::array<std::uint8_t, 64> packet{};
  const proto::EncodeResult e = proto::encode_packet(proto::Heartbeat{0x1234}, 9, packet);
  ASSERT_EQ(e.error, proto::Error::ok);
  ASSERT_EQ(t->send(std::span<const std::uint8_t>(packet.data(), e.bytes)), ResultCode::ok);
  ASSERT_TRUE(eventually([&] { return t->counters().sent == 1; }));
  const std::vector<OutReport> w = fake->written();
  ASSERT_EQ(w.size(), 1U);
  EXPECT_EQ(w[0].endpoint, 0x01);
  ASSERT_EQ(w[0].bytes.size(), 64U);
  EXPECT_EQ(w[0].bytes[0], proto::kVersionMajor);  // byte 0 is the packet, not a report ID
  EXPECT_TRUE(
      std::equal(packet.begin(), packet.begin() + static_cast<std::ptrdiff_t>(e.bytes), w[0].bytes.begin()));
  EXPECT_TRUE(std::all_of(w[0].bytes.begin() + static_cast<std::ptrdiff_t>(e.bytes), w[0].bytes.end(),
                          [](std::uint8_t b) { return b == 0; }));
  const proto::PacketDecoded p = proto::decode_packet(w[0].bytes);
  EXPECT_EQ(p.error, proto::Error::ok);
}

TEST(UsbFramingTest, InReportIsDeliveredAsItCame) {
  auto fake = std::make_shared<FakeLibusb>();
  fake->add({});
  auto t = open_usb_transport("usb://", fake, fast());
  const std::vector<std::uint8_t> report = heartbeat_report(77);
  fake->inject_in(report);
  Datagram d;
  ASSERT_EQ(t->receive_for(d, 20s), ResultCode::ok);
  ASSERT_EQ(d.length, 64);
  EXPECT_TRUE(std::equal(report.begin(), report.end(), d.bytes.begin()));
  const proto::PacketDecoded p =
      proto::decode_packet(std::span<const std::uint8_t>(d.bytes.data(), d.length));
  ASSERT_EQ(p.error, proto::Error::ok);
  EXPECT_EQ(std::get<proto::Heartbeat>(p.message).counter, 77);
  // A short transfer is delivered at its length; an empty one is no packet.
  fake->inject_in({1, 2, 3});
  ASSERT_EQ(t->receive_for(d, 20s), ResultCode::ok);
  EXPECT_EQ(d.length, 3);
  fake->inject_in({});
  EXPECT_TRUE(eventually([&] { return t->counters().malformed == 1; }));
  EXPECT_EQ(t->counters().received, 2U);
}

// --- transfer statuses -----------------------------------------------------------------------

TEST(UsbStatusTest, OutTimeoutIsCounted) {
  auto fake = std::make_shared<FakeLibusb>();
  fake->add({});
  auto t = open_usb_transport("usb://", fake, fast());
  fake->set_out_status(LIBUSB_TRANSFER_TIMED_OUT);
  const std::array<std::uint8_t, 6> bytes{1, 2, 3, 4, 5, 6};
  ASSERT_EQ(t->send(bytes), ResultCode::ok);
  ASSERT_TRUE(eventually([&] { return t->counters().timeouts == 1; }));
  EXPECT_EQ(t->counters().sent, 0U);
  EXPECT_EQ(t->counters().io_errors, 0U);
  EXPECT_EQ(t->state(), TransportState::open);
}

TEST(UsbStatusTest, OutStallClearsTheHaltAndSendingGoesOn) {
  auto fake = std::make_shared<FakeLibusb>();
  fake->add({});
  auto t = open_usb_transport("usb://", fake, fast());
  fake->set_out_status(LIBUSB_TRANSFER_STALL);
  const std::array<std::uint8_t, 6> bytes{1, 2, 3, 4, 5, 6};
  ASSERT_EQ(t->send(bytes), ResultCode::ok);
  ASSERT_TRUE(eventually([&] { return fake->count("clear_halt 1") == 1; }));
  EXPECT_EQ(t->counters().io_errors, 1U);
  fake->set_out_status(LIBUSB_TRANSFER_COMPLETED);
  ASSERT_EQ(t->send(bytes), ResultCode::ok);
  EXPECT_TRUE(eventually([&] { return t->counters().sent == 1; }));
  EXPECT_EQ(t->state(), TransportState::open);
}

TEST(UsbStatusTest, InStallClearsTheHaltAndReadingGoesOn) {
  auto fake = std::make_shared<FakeLibusb>();
  fake->add({});
  auto t = open_usb_transport("usb://", fake, fast());
  fake->inject_in({}, LIBUSB_TRANSFER_STALL);
  ASSERT_TRUE(eventually([&] { return fake->count("clear_halt 129") == 1; }));
  EXPECT_EQ(t->counters().io_errors, 1U);
  fake->inject_in(heartbeat_report(1));
  Datagram d;
  EXPECT_EQ(t->receive_for(d, 20s), ResultCode::ok);
  EXPECT_TRUE(eventually([&] { return fake->pending_in() == 4; }));  // every IN resubmitted
}

TEST(UsbStatusTest, InErrorIsCountedAndRepeatedErrorsCountAsALoss) {
  auto fake = std::make_shared<FakeLibusb>();
  fake->add({});
  UsbTransportOptions o = fast();
  o.max_consecutive_errors = 5;
  auto t = open_usb_transport("usb://", fake, o);
  fake->inject_in({}, LIBUSB_TRANSFER_ERROR);
  fake->inject_in(heartbeat_report(1));  // a success resets the run of errors
  Datagram d;
  ASSERT_EQ(t->receive_for(d, 20s), ResultCode::ok);
  EXPECT_EQ(t->counters().io_errors, 1U);
  EXPECT_EQ(t->counters().disconnects, 0U);
  for (int i = 0; i < 5; ++i) {
    fake->inject_in({}, LIBUSB_TRANSFER_ERROR);
  }
  // The unit is still there: the loss is cured by closing and reopening it.
  ASSERT_TRUE(eventually([&] { return t->counters().reopens == 1 && t->state() == TransportState::open; }));
  EXPECT_EQ(t->counters().io_errors, 6U);
  EXPECT_EQ(t->counters().disconnects, 1U);
  EXPECT_EQ(fake->count("release"), 1U);
  EXPECT_EQ(fake->count("claim"), 2U);
  fake->inject_in(heartbeat_report(2));
  EXPECT_EQ(t->receive_for(d, 20s), ResultCode::ok);
}

// --- unplug and replug -----------------------------------------------------------------------

TEST(UsbUnplugTest, NoDeviceDisconnectsDropsQueuedSendsAndPollingReopens) {
  auto fake = std::make_shared<FakeLibusb>(false);  // no hotplug: the transport polls
  fake->add({});
  UsbTransportOptions o = fast();
  o.out_transfers = 1;
  auto t = open_usb_transport("usb://", fake, o);
  fake->set_out_hold(true);  // the OUT never completes: the rest waits in the queue
  for (std::uint8_t i = 1; i <= 5; ++i) {
    const std::array<std::uint8_t, 1> b{i};
    ASSERT_EQ(t->send(b), ResultCode::ok);
  }
  ASSERT_TRUE(eventually([&] { return fake->written().size() == 1; }));
  fake->unplug(0, true);
  ASSERT_TRUE(eventually([&] { return t->state() == TransportState::disconnected; }));
  const std::array<std::uint8_t, 1> stale{9};
  EXPECT_EQ(t->send(stale), ResultCode::disconnected);
  Datagram d;
  EXPECT_EQ(t->receive(d), ResultCode::disconnected);
  fake->set_out_hold(false);
  fake->replug(0);
  ASSERT_TRUE(eventually([&] { return t->state() == TransportState::open; }));
  EXPECT_EQ(t->counters().disconnects, 1U);
  EXPECT_EQ(t->counters().reopens, 1U);
  EXPECT_EQ(fake->count("detach"), 2U);  // usbhid bound again on re-enumeration
  const std::array<std::uint8_t, 1> fresh{42};
  ASSERT_EQ(t->send(fresh), ResultCode::ok);
  ASSERT_TRUE(eventually([&] { return fake->written().size() >= 2; }));
  const std::vector<OutReport> w = fake->written();
  ASSERT_EQ(w.size(), 2U);  // datagrams 2..5, queued for the unit that left, were dropped
  EXPECT_EQ(w[1].bytes[0], 42);
  fake->inject_in(heartbeat_report(3));
  EXPECT_EQ(t->receive_for(d, 20s), ResultCode::ok);
}

TEST(UsbUnplugTest, HotplugDepartureDisconnectsAndArrivalReopens) {
  auto fake = std::make_shared<FakeLibusb>(true);
  fake->add({});
  UsbTransportOptions o = fast();
  o.reopen_window = 0ms;  // after the one attempt at the loss, only an arrival reopens
  auto t = open_usb_transport("usb://", fake, o);
  ASSERT_TRUE(eventually([&] { return fake->pending_in() == 4; }));
  fake->unplug(0, false);  // departure event only: the in-flight INs are cancelled
  ASSERT_TRUE(eventually([&] { return t->state() == TransportState::disconnected; }));
  EXPECT_EQ(fake->count("cancel"), 4U);
  EXPECT_EQ(fake->open_handles(), 0U);
  fake->replug(0);
  ASSERT_TRUE(eventually([&] { return t->state() == TransportState::open; }));
  EXPECT_EQ(t->counters().disconnects, 1U);
  EXPECT_EQ(t->counters().reopens, 1U);
  fake->inject_in(heartbeat_report(4));
  Datagram d;
  EXPECT_EQ(t->receive_for(d, 20s), ResultCode::ok);
}

TEST(UsbUnplugTest, ArrivalRetriesWhileUdevAppliesPermissions) {
  auto fake = std::make_shared<FakeLibusb>(true);
  fake->add({});
  auto t = open_usb_transport("usb://", fake, fast());
  fake->unplug(0, true);
  ASSERT_TRUE(eventually([&] { return t->state() == TransportState::disconnected; }));
  fake->with_device(0, [](FakeDevice& d) {
    d.open_error = LIBUSB_ERROR_ACCESS;
    d.open_failures = 3;
  });
  fake->replug(0);
  ASSERT_TRUE(eventually([&] { return t->state() == TransportState::open; }));
  EXPECT_GE(fake->count("open 4D520001"), 5U);  // first open, three refusals, the reopen
  EXPECT_EQ(t->counters().reopens, 1U);
}

TEST(UsbUnplugTest, AnotherUnitIsNotTakenOnReopen) {
  auto fake = std::make_shared<FakeLibusb>(false);
  fake->add({});
  auto t = open_usb_transport("usb://", fake, fast());
  fake->unplug(0, true);
  ASSERT_TRUE(eventually([&] { return t->state() == TransportState::disconnected; }));
  FakeDevice other;
  other.serial = "0000BEEF";
  other.address = 20;
  fake->add(other);
  ASSERT_TRUE(eventually([&] { return fake->count("open 0000BEEF") >= 2; }));  // looked at, twice
  EXPECT_EQ(t->state(), TransportState::disconnected);
  fake->with_device(1, [](FakeDevice& d) { EXPECT_FALSE(d.claimed); });
  fake->replug(0);
  EXPECT_TRUE(eventually([&] { return t->state() == TransportState::open; }));
}

// --- allocation and shutdown -----------------------------------------------------------------

TEST(UsbAllocationTest, TransfersAreAllocatedOnceAtOpen) {
  auto fake = std::make_shared<FakeLibusb>(true);
  fake->add({});
  UsbTransportOptions o = fast();
  auto t = open_usb_transport("usb://", fake, o);
  const std::size_t at_open = fake->allocs();
  EXPECT_EQ(at_open, o.in_transfers + o.out_transfers);
  constexpr int kDatagrams = 2000;
  int sent = 0;
  Datagram d;
  int received = 0;
  for (int i = 0; i < kDatagrams; ++i) {
    const std::array<std::uint8_t, 4> b{static_cast<std::uint8_t>(i), 1, 2, 3};
    while (t->send(b) != ResultCode::ok) {
      std::this_thread::yield();
    }
    ++sent;
    fake->inject_in(heartbeat_report(static_cast<std::uint16_t>(i)));
    while (t->receive(d) == ResultCode::ok) {
      ++received;
    }
  }
  ASSERT_TRUE(eventually([&] {
    while (t->receive(d) == ResultCode::ok) {
      ++received;
    }
    return received == kDatagrams && t->counters().sent == static_cast<std::uint64_t>(sent);
  }));
  fake->unplug(0, true);
  ASSERT_TRUE(eventually([&] { return t->state() == TransportState::disconnected; }));
  fake->replug(0);
  ASSERT_TRUE(eventually([&] { return t->state() == TransportState::open; }));
  EXPECT_EQ(fake->allocs(), at_open);
  EXPECT_EQ(fake->frees(), 0U);
  t.reset();
  EXPECT_EQ(fake->frees(), at_open);
}

TEST(UsbShutdownTest, CancelsInFlightTransfersAndWaitsForThem) {
  auto fake = std::make_shared<FakeLibusb>();
  fake->add({});
  auto t = open_usb_transport("usb://", fake, fast());
  fake->set_out_hold(true);
  const std::array<std::uint8_t, 2> b{1, 2};
  ASSERT_EQ(t->send(b), ResultCode::ok);
  ASSERT_EQ(t->send(b), ResultCode::ok);
  ASSERT_TRUE(eventually([&] { return fake->written().size() == 2 && fake->pending_in() == 4; }));
  t.reset();
  EXPECT_EQ(fake->count("cancel"), 6U);
  EXPECT_EQ(fake->frees(), fake->allocs());
  EXPECT_EQ(fake->open_handles(), 0U);
}

TEST(UsbShutdownTest, DatagramsQueuedAtShutdownAreWritten) {
  // The session's last words (a disable request) go out before the interface is released.
  auto fake = std::make_shared<FakeLibusb>();
  fake->add({});
  auto t = open_usb_transport("usb://", fake, fast());
  for (std::uint8_t i = 1; i <= 3; ++i) {
    const std::array<std::uint8_t, 1> b{i};
    ASSERT_EQ(t->send(b), ResultCode::ok);
  }
  t.reset();
  const std::vector<OutReport> w = fake->written();
  ASSERT_EQ(w.size(), 3U);
  EXPECT_EQ(w[2].bytes[0], 3);
}

// --- listing ---------------------------------------------------------------------------------

TEST(UsbListTest, ListsUnitsWithPathSerialAndPermissionProblems) {
  FakeLibusb fake;
  fake.add({});
  FakeDevice locked;
  locked.serial = "0000BEEF";
  locked.bus = 2;
  locked.address = 5;
  locked.ports = {1};
  locked.open_error = LIBUSB_ERROR_ACCESS;
  locked.open_failures = -1;
  fake.add(locked);
  FakeDevice other;
  other.product_id = 0x1111;
  fake.add(other);
  const std::vector<DeviceListing> l = list_usb_devices(fake);
  ASSERT_EQ(l.size(), 2U);
  EXPECT_EQ(l[0].bus, "usb");
  EXPECT_EQ(l[0].path, "1-2.3");
  EXPECT_EQ(l[0].serial, "4D520001");
  EXPECT_EQ(l[0].uri, "usb://1209:4d52?serial=4D520001");
  EXPECT_EQ(l[0].problem, "");
  EXPECT_EQ(l[1].path, "2-1");
  EXPECT_EQ(l[1].uri, "usb://1209:4d52");
  EXPECT_EQ(l[1].problem, "permission denied");
  EXPECT_NE(l[1].fix.find("/dev/bus/usb/002/005"), std::string::npos) << l[1].fix;
  EXPECT_NE(l[1].fix.find("70-mrskin.rules"), std::string::npos) << l[1].fix;
  EXPECT_NE(l[1].fix.find("mrskin group"), std::string::npos) << l[1].fix;
  EXPECT_EQ(fake.open_handles(), 0U);
  EXPECT_EQ(fake.count("exit"), 1U);
}

TEST(UsbListTest, NoUsbGivesOneEntryWithTheProblem) {
  FakeLibusb fake;
  fake.init_result = LIBUSB_ERROR_OTHER;
  const std::vector<DeviceListing> l = list_usb_devices(fake);
  ASSERT_EQ(l.size(), 1U);
  EXPECT_NE(l[0].problem.find("USB is not available"), std::string::npos);
  EXPECT_NE(l[0].fix.find("/dev/bus/usb"), std::string::npos);
}

TEST(UsbListTest, RealLibusbNeverThrows) {
  // Whatever this machine has (often no /dev/bus/usb in a container): entries, no exception.
  std::vector<DeviceListing> l;
  EXPECT_NO_THROW(l = list_usb_devices());
  for (const DeviceListing& e : l) {
    EXPECT_EQ(e.bus, "usb");
    EXPECT_TRUE(e.problem.empty() || !e.fix.empty());
  }
  try {
    (void)open_usb_transport("usb://ffff:fffe");  // no such unit anywhere
    ADD_FAILURE() << "opened a device that should not exist";
  } catch (const DeviceNotFound&) {
  } catch (const PermissionDenied&) {
  }
}

// --- a session over usb:// to the mock device ------------------------------------------------

TEST(UsbEndToEndTest, SessionOverUsbToMockDeviceSurvivesUnplug) {
  MonotonicClock clock;
  sim::MockOptions mo;
  mo.seed = 7;
  const std::shared_ptr<sim::MockDevice> mock = sim::MockDevice::make(mo);
  auto fake = std::make_shared<FakeLibusb>(true);
  FakeDevice unit;
  unit.serial = proto::format_usb_serial(mo.serial);
  fake->add(unit);
  fake->attach_link(mock->connect(false, &clock));
  mock->start(clock);
  {
    SessionOptions so;
    so.time_scale = 4.0;  // sanitizer builds are slow; nothing here measures time
    DeviceSession session(open_usb_transport("usb://1209:4d52", fake, fast()), clock, so);
    EXPECT_EQ(session.info().serial, mo.serial);
    ASSERT_NE(session.profile(), nullptr);
    const auto poll_until = [&](auto done) {
      return eventually([&] {
        (void)session.poll(clock.now());
        return done();
      });
    };
    ASSERT_TRUE(poll_until([&] { return session.counters().telemetry >= 50; }));
    mock->set_link_up(false);
    fake->unplug(0, true);
    ASSERT_TRUE(poll_until([&] { return session.counters().disconnects == 1; }));
    mock->set_link_up(true);
    fake->replug(0);
    ASSERT_TRUE(poll_until([&] { return session.counters().reconnects == 1; }));
    const std::uint64_t before = session.counters().telemetry;
    EXPECT_TRUE(poll_until([&] { return session.counters().telemetry >= before + 50; }));
    EXPECT_EQ(session.counters().identity_changes, 0U);
  }
  fake->attach_link(nullptr);
  mock->stop();
}

}  // namespace
}  // namespace mrskin
