// The hid:// transport's own logic over a fake hidapi: URI parsing, report-ID framing,
// timeout vs error vs disconnect, EACCES at open and after a hotplug, unplug and replug, no
// allocation per datagram, and a device session end to end over the mock device's firmware.
// Waits are bounded by a generous deadline that only catches hangs; nothing asserts timing.
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <deque>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "counting_new.hpp"
#include "mrskin/driver/session.hpp"
#include "mrskin/driver/transports/hid.hpp"
#include "mrskin/protocol/packet.hpp"
#include "mrskin/sim/mock_device.hpp"

namespace mrskin {
namespace {

using namespace std::chrono_literals;
using Bytes = std::vector<std::uint8_t>;

template <class Pred>
bool eventually(Pred pred) {
  const auto deadline = std::chrono::steady_clock::now() + 20s;
  while (!pred()) {
    if (std::chrono::steady_clock::now() > deadline) {
      return false;
    }
    std::this_thread::sleep_for(1ms);
  }
  return true;
}

bool contains(const std::string& text, std::string_view part) { return text.find(part) != std::string::npos; }

// The unit's end of the fake link, when something richer than the fake's own queue answers.
class Peer {
 public:
  Peer() = default;
  Peer(const Peer&) = delete;
  Peer& operator=(const Peer&) = delete;
  Peer(Peer&&) = delete;
  Peer& operator=(Peer&&) = delete;
  virtual ~Peer() = default;
  virtual void host_wrote(std::span<const std::uint8_t> report) noexcept = 0;  // 64 bytes
  virtual bool device_report(std::span<std::uint8_t> out) noexcept = 0;        // non-blocking
};

// One hidraw node of the fake.
struct FakeUnit {
  std::string path;
  std::string serial;
  bool present = true;
  int deny_opens = 0;  // the next opens fail with EACCES
  bool deny_always = false;
  int generation = 0;  // bumped by an unplug: handles opened before it are dead
};

// hidapi for tests: hidraw units that can be unplugged, replugged and refuse opens (EACCES),
// read and write faults injected in order, every write recorded. Reads and writes allocate
// nothing unless record_writes is on.
class FakeHid final : public HidApi {
 public:
  using Unit = FakeUnit;

  explicit FakeHid(std::vector<Unit> units = {{"/dev/hidraw7", "0000BEEF"}}) : units_(std::move(units)) {}

  // --- the test's side -------------------------------------------------------------------
  void unplug(std::size_t unit = 0) {
    const std::lock_guard lock(mutex_);
    units_[unit].present = false;
    ++units_[unit].generation;
    count_ = 0;
    cv_.notify_all();
  }
  void replug(std::size_t unit = 0, int deny_opens = 0, bool deny_always = false) {
    const std::lock_guard lock(mutex_);
    units_[unit].present = true;
    units_[unit].deny_opens = deny_opens;
    units_[unit].deny_always = deny_always;
  }
  void allow(std::size_t unit = 0) {
    const std::lock_guard lock(mutex_);
    units_[unit].deny_always = false;
  }
  void push_input(const Bytes& report) {
    const std::lock_guard lock(mutex_);
    push_locked(report);
  }
  void fail_reads(std::initializer_list<HidIoResult> results) {
    const std::lock_guard lock(mutex_);
    read_faults_.insert(read_faults_.end(), results);
  }
  void fail_writes(std::initializer_list<HidIoResult> results) {
    const std::lock_guard lock(mutex_);
    write_faults_.insert(write_faults_.end(), results);
  }
  void hold_writes(bool hold) {
    const std::lock_guard lock(mutex_);
    hold_ = hold;
    cv_.notify_all();
  }
  // An unplugged node's reads fail with this errno (0: hidapi 0.13's poll hang-up).
  void set_hangup_errno(int error) {
    const std::lock_guard lock(mutex_);
    hangup_errno_ = error;
  }
  void set_echo(bool echo) {
    const std::lock_guard lock(mutex_);
    echo_ = echo;
  }
  void set_record_writes(bool record) {
    const std::lock_guard lock(mutex_);
    record_ = record;
  }
  void set_peer(Peer* peer) {
    const std::lock_guard lock(mutex_);
    peer_ = peer;
  }
  std::vector<Bytes> writes() const {
    const std::lock_guard lock(mutex_);
    return writes_;
  }
  std::vector<std::string> opened_paths() const {
    const std::lock_guard lock(mutex_);
    return opened_paths_;
  }
  template <class F>
  auto stat(F f) const {
    const std::lock_guard lock(mutex_);
    return f(stats_);
  }
  struct Stats {
    int inits = 0;
    int exits = 0;
    int enumerations = 0;
    int denied = 0;
    int reads = 0;
    int write_calls = 0;
    int blocked_writes = 0;
    std::size_t last_read_size = 0;
  };

  // --- HidApi ------------------------------------------------------------------------------
  bool init() noexcept override {
    const std::lock_guard lock(mutex_);
    ++stats_.inits;
    return true;
  }
  void exit() noexcept override {
    const std::lock_guard lock(mutex_);
    ++stats_.exits;
  }
  std::vector<HidDeviceInfo> enumerate(std::uint16_t vendor_id, std::uint16_t product_id) override {
    const std::lock_guard lock(mutex_);
    ++stats_.enumerations;
    std::vector<HidDeviceInfo> out;
    for (const Unit& u : units_) {
      if (u.present && vendor_id == protocol::kUsbVendorId && product_id == protocol::kUsbProductId) {
        out.push_back({u.path, protocol::kUsbVendorId, protocol::kUsbProductId, u.serial});
      }
    }
    return out;
  }
  Opened open_path(const std::string& path) override {
    const std::lock_guard lock(mutex_);
    for (std::size_t i = 0; i < units_.size(); ++i) {
      Unit& u = units_[i];
      if (u.path != path || !u.present) {
        continue;
      }
      if (u.deny_always || u.deny_opens > 0) {
        u.deny_opens = std::max(0, u.deny_opens - 1);
        ++stats_.denied;
        return {nullptr, EACCES};
      }
      opened_paths_.push_back(path);
      return {std::make_unique<Device>(*this, i, u.generation), 0};
    }
    return {nullptr, ENOENT};
  }
  int access(const std::string& path) noexcept override {
    const std::lock_guard lock(mutex_);
    for (const Unit& u : units_) {
      if (u.path == path && u.present) {
        return u.deny_always || u.deny_opens > 0 ? EACCES : 0;
      }
    }
    return ENOENT;
  }

 private:
  class Device final : public HidDevice {
   public:
    Device(FakeHid& hid, std::size_t unit, int generation)
        : hid_(hid), unit_(unit), generation_(generation) {}
    HidIoResult write(std::span<const std::uint8_t> data) noexcept override {
      return hid_.write(*this, data);
    }
    HidIoResult read_timeout(std::span<std::uint8_t> data, int timeout_ms) noexcept override {
      return hid_.read(*this, data, timeout_ms);
    }
    std::size_t unit() const noexcept { return unit_; }
    int generation() const noexcept { return generation_; }

   private:
    FakeHid& hid_;
    std::size_t unit_;
    int generation_;
  };

  bool alive(const Device& d) const noexcept {
    return units_[d.unit()].present && units_[d.unit()].generation == d.generation();
  }
  void push_locked(std::span<const std::uint8_t> report) noexcept {
    if (count_ == ring_.size()) {
      return;
    }
    Report& slot = ring_[(head_ + count_) % ring_.size()];
    slot.fill(0);
    std::copy_n(report.begin(), std::min(report.size(), slot.size()), slot.begin());
    ++count_;
    cv_.notify_all();
  }

  HidIoResult read(const Device& d, std::span<std::uint8_t> out, int timeout_ms) noexcept {
    std::unique_lock lock(mutex_);
    ++stats_.reads;
    stats_.last_read_size = out.size();
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
    for (;;) {
      if (!alive(d)) {
        return {-1, hangup_errno_};
      }
      if (!read_faults_.empty()) {
        const HidIoResult r = read_faults_.front();
        read_faults_.pop_front();
        return r;
      }
      if (count_ > 0) {
        const Report& r = ring_[head_];
        const std::size_t n = std::min(out.size(), r.size());
        std::copy_n(r.begin(), n, out.begin());
        head_ = (head_ + 1) % ring_.size();
        --count_;
        return {static_cast<int>(n), 0};
      }
      if (peer_ != nullptr && peer_->device_report(out)) {
        return {static_cast<int>(out.size()), 0};
      }
      const auto now = std::chrono::steady_clock::now();
      if (now >= deadline) {
        return {0, 0};
      }
      // A peer is polled every millisecond; the own queue wakes the wait.
      cv_.wait_until(lock, peer_ != nullptr ? std::min(deadline, now + 1ms) : deadline);
    }
  }

  HidIoResult write(const Device& d, std::span<const std::uint8_t> data) noexcept {
    std::unique_lock lock(mutex_);
    ++stats_.write_calls;
    if (hold_ && alive(d)) {
      ++stats_.blocked_writes;
      cv_.wait(lock, [&] { return !hold_ || !alive(d); });
    }
    if (!alive(d)) {
      return {-1, ENODEV};  // what hidraw's write gives on a gone device
    }
    if (!write_faults_.empty()) {
      const HidIoResult r = write_faults_.front();
      write_faults_.pop_front();
      return r;
    }
    if (record_) {
      writes_.emplace_back(data.begin(), data.end());
    }
    // The unit sees the report only when it came with the report-ID byte in front.
    if (data.size() == protocol::kHidReportBytes + 1 && data[0] == 0x00) {
      if (echo_) {
        push_locked(data.subspan(1));
      }
      if (peer_ != nullptr) {
        peer_->host_wrote(data.subspan(1));
      }
    }
    cv_.notify_all();
    return {static_cast<int>(data.size()), 0};
  }

  using Report = std::array<std::uint8_t, protocol::kHidReportBytes>;
  mutable std::mutex mutex_;
  std::condition_variable cv_;
  std::vector<Unit> units_;
  std::array<Report, 512> ring_{};
  std::size_t head_ = 0;
  std::size_t count_ = 0;
  std::deque<HidIoResult> read_faults_;
  std::deque<HidIoResult> write_faults_;
  std::vector<Bytes> writes_;
  std::vector<std::string> opened_paths_;
  bool record_ = true;
  bool echo_ = false;
  bool hold_ = false;
  int hangup_errno_ = 0;
  Peer* peer_ = nullptr;
  Stats stats_;
};

HidTransportOptions fast_options() {
  HidTransportOptions o;
  o.read_timeout = 5ms;
  o.reopen_backoff_min = 1ms;
  o.reopen_backoff_max = 5ms;
  o.permission_retry = 30s;  // generous: the EACCES retry must not run out under sanitizers
  return o;
}

struct Link {
  explicit Link(std::string_view uri = "hid://1209:4d52", HidTransportOptions options = fast_options(),
                std::vector<FakeHid::Unit> units = {{"/dev/hidraw7", "0000BEEF"}})
      : hid(std::make_shared<FakeHid>(std::move(units))), transport(open_hid_transport(uri, options, hid)) {}
  std::shared_ptr<FakeHid> hid;
  std::unique_ptr<Transport> transport;
  [[nodiscard]] TransportCounters counters() const { return transport->counters(); }
};

Bytes packet_like(std::size_t n, std::uint8_t first = 0x01) {
  Bytes b(n);
  for (std::size_t i = 0; i < n; ++i) {
    b[i] = static_cast<std::uint8_t>(first + 7 * i);
  }
  return b;
}

// --- URI ---------------------------------------------------------------------------------

TEST(HidUri, ParsesVidPidAndSerial) {
  const HidUri bare = parse_hid_uri("hid://");
  EXPECT_EQ(bare.vendor_id, 0x1209);
  EXPECT_EQ(bare.product_id, 0x4d52);
  EXPECT_EQ(bare.serial, "");
  const HidUri ids = parse_hid_uri("hid://abcd:12");
  EXPECT_EQ(ids.vendor_id, 0xabcd);
  EXPECT_EQ(ids.product_id, 0x0012);
  const HidUri with_serial = parse_hid_uri("hid://1209:4D52?serial=0000beef");
  EXPECT_EQ(with_serial.product_id, 0x4d52);
  EXPECT_EQ(with_serial.serial, "0000BEEF");
  EXPECT_EQ(parse_hid_uri("hid://?serial=4D520001").serial, "4D520001");
  EXPECT_EQ(format_hid_uri(with_serial), "hid://1209:4d52?serial=0000BEEF");
  EXPECT_EQ(format_hid_uri(bare), "hid://1209:4d52");
}

TEST(HidUri, RejectsBadPartsNamingThem) {
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"usb://1209:4d52", "not a hid:// URI"},  {"hid://1209", "'1209' is not VID:PID"},
      {"hid://12g9:4d52", "vendor ID '12g9'"},  {"hid://0000:4d52", "vendor ID '0000'"},
      {"hid://1209:", "product ID ''"},         {"hid://1209:4d520", "product ID '4d520'"},
      {"hid://1209:-4d5", "product ID '-4d5'"}, {"hid://1209:4d52?serial=BEEF", "serial 'BEEF'"},
      {"hid://1209:4d52?serial", "serial ''"},  {"hid://1209:4d52?seriall=0000BEEF", "parameter 'seriall'"},
  };
  for (const auto& [uri, part] : cases) {
    try {
      (void)parse_hid_uri(uri);
      ADD_FAILURE() << uri << " was accepted";
    } catch (const InvalidArgument& e) {
      EXPECT_TRUE(contains(e.what(), part)) << uri << ": " << e.what();
    }
  }
}

// --- framing -----------------------------------------------------------------------------

TEST(HidFraming, WritesTheReportIdByteThenThe64ByteReport) {
  Link link;
  const Bytes small = packet_like(6);
  const Bytes full = packet_like(64, 0x40);
  ASSERT_EQ(link.transport->send(small), ResultCode::ok);
  ASSERT_EQ(link.transport->send(full), ResultCode::ok);
  ASSERT_TRUE(eventually([&] { return link.hid->writes().size() == 2; }));
  const std::vector<Bytes> writes = link.hid->writes();
  for (const Bytes& w : writes) {
    ASSERT_EQ(w.size(), 65U) << "a 64-byte hid_write would send the version byte as the report ID";
    EXPECT_EQ(w[0], 0x00);
  }
  EXPECT_TRUE(std::equal(small.begin(), small.end(), writes[0].begin() + 1));
  EXPECT_TRUE(std::all_of(writes[0].begin() + 7, writes[0].end(), [](std::uint8_t b) { return b == 0; }));
  EXPECT_TRUE(std::equal(full.begin(), full.end(), writes[1].begin() + 1));
  // The writer thread counts a write after hid_write returns, so the count may trail the fake's
  // record (seen under ThreadSanitizer, 2026-12-03).
  EXPECT_TRUE(eventually([&] { return link.counters().sent == 2U; })) << link.counters().sent;
}

TEST(HidFraming, ReadsThe64ReportBytesAsTheyAre) {
  Link link;
  const Bytes report = packet_like(64);  // byte 0 is the protocol version, not a report ID
  link.hid->push_input(report);
  Datagram d;
  ASSERT_EQ(link.transport->receive_for(d, 20s), ResultCode::ok);
  // The read offers room for the largest report a unit may declare (UsbSlots); hidraw returns the
  // report's own length.
  EXPECT_EQ(link.hid->stat([](const FakeHid::Stats& s) { return s.last_read_size; }), kMaxDatagramBytes);
  ASSERT_EQ(d.length, 64U);
  EXPECT_TRUE(std::equal(report.begin(), report.end(), d.bytes.begin()));
}

TEST(HidFraming, RefusesDatagramsThatDoNotFitAReport) {
  Link link;
  EXPECT_EQ(link.transport->send(Bytes(kMaxDatagramBytes + 1, 1)), ResultCode::invalid_value);
  EXPECT_EQ(link.transport->send(Bytes{}), ResultCode::invalid_value);
}

// --- timeout, error, disconnect ------------------------------------------------------------

TEST(HidErrors, ReadTimeoutsAreIdleNotErrors) {
  Link link;
  ASSERT_TRUE(
      eventually([&] { return link.hid->stat([](const FakeHid::Stats& s) { return s.reads; }) >= 20; }));
  EXPECT_EQ(link.transport->state(), TransportState::open);
  EXPECT_EQ(link.counters().io_errors, 0U);
  EXPECT_EQ(link.counters().disconnects, 0U);
}

TEST(HidErrors, ATransientReadErrorIsCountedAndReadingGoesOn) {
  Link link;
  link.hid->fail_reads({{-1, EIO}, {-1, EINTR}});
  ASSERT_TRUE(eventually([&] { return link.counters().io_errors == 2; }));
  link.hid->push_input(packet_like(64));
  Datagram d;
  EXPECT_EQ(link.transport->receive_for(d, 20s), ResultCode::ok);
  EXPECT_EQ(link.transport->state(), TransportState::open);
  EXPECT_EQ(link.counters().disconnects, 0U);
}

TEST(HidErrors, WriteTimeoutsAndErrorsAreCountedAndTheLinkStays) {
  Link link;
  link.hid->fail_writes({{-1, ETIMEDOUT}, {-1, EPIPE}, {12, 0}});  // the last one short
  for (int i = 0; i < 4; ++i) {
    ASSERT_EQ(link.transport->send(packet_like(10)), ResultCode::ok);
  }
  ASSERT_TRUE(eventually([&] { return link.counters().sent == 1; }));
  const TransportCounters c = link.counters();
  EXPECT_EQ(c.timeouts, 1U);
  EXPECT_EQ(c.io_errors, 2U);
  EXPECT_EQ(c.disconnects, 0U);
  EXPECT_EQ(link.transport->state(), TransportState::open);
}

TEST(HidErrors, ErrorsInARowOnAPresentNodeReopenIt) {
  HidTransportOptions options = fast_options();
  options.errors_before_reopen = 3;
  Link link("hid://", options);
  link.hid->fail_reads({{-1, EIO}, {-1, EIO}, {-1, EIO}});
  ASSERT_TRUE(eventually([&] { return link.counters().reopens == 1; }));
  EXPECT_EQ(link.counters().io_errors, 2U);
  EXPECT_EQ(link.counters().disconnects, 1U);
  EXPECT_EQ(link.transport->state(), TransportState::open);
  EXPECT_EQ(link.hid->opened_paths().size(), 4U);  // reader and writer handles, twice
}

// Unplug while a write is stuck and more are queued: disconnected at once, nothing stale
// reaches the unit after the replug, and the link carries new datagrams.
void unplug_and_replug(int hangup_errno) {
  Link link;
  link.hid->set_hangup_errno(hangup_errno);
  link.hid->hold_writes(true);
  for (std::uint8_t i = 0; i < 5; ++i) {
    ASSERT_EQ(link.transport->send(packet_like(8, i)), ResultCode::ok);
  }
  ASSERT_TRUE(eventually(
      [&] { return link.hid->stat([](const FakeHid::Stats& s) { return s.blocked_writes; }) == 1; }));
  link.hid->unplug();
  ASSERT_TRUE(eventually([&] { return link.transport->state() == TransportState::disconnected; }));
  EXPECT_EQ(link.transport->send(packet_like(8)), ResultCode::disconnected);
  Datagram d;
  EXPECT_EQ(link.transport->receive(d), ResultCode::disconnected);
  link.hid->hold_writes(false);
  link.hid->replug();
  ASSERT_TRUE(eventually([&] { return link.transport->state() == TransportState::open; }));
  const Bytes fresh = packet_like(8, 0xA0);
  ASSERT_EQ(link.transport->send(fresh), ResultCode::ok);
  ASSERT_TRUE(eventually([&] { return !link.hid->writes().empty(); }));
  const std::vector<Bytes> writes = link.hid->writes();
  ASSERT_EQ(writes.size(), 1U) << "a command queued before the unplug was written after it";
  EXPECT_TRUE(std::equal(fresh.begin(), fresh.end(), writes[0].begin() + 1));
  link.hid->push_input(packet_like(64));
  EXPECT_EQ(link.transport->receive_for(d, 20s), ResultCode::ok);
  EXPECT_EQ(link.counters().disconnects, 1U);
  EXPECT_EQ(link.counters().reopens, 1U);
  EXPECT_EQ(link.counters().io_errors, 0U);
  EXPECT_EQ(hid_transport_problem(*link.transport), "");
}

TEST(HidUnplug, PollHangupWithoutErrnoIsADisconnect) { unplug_and_replug(0); }

TEST(HidUnplug, AnErrorOnAVanishedNodeIsADisconnect) { unplug_and_replug(EIO); }

TEST(HidUnplug, ReopensOnlyTheUnitWithTheGivenSerial) {
  Link link("hid://1209:4d52?serial=0000cafe", fast_options(),
            {{"/dev/hidraw7", "0000BEEF"}, {"/dev/hidraw8", "0000CAFE"}});
  link.hid->unplug(1);
  ASSERT_TRUE(eventually([&] { return link.transport->state() == TransportState::disconnected; }));
  const int before = link.hid->stat([](const FakeHid::Stats& s) { return s.enumerations; });
  ASSERT_TRUE(eventually(
      [&] { return link.hid->stat([](const FakeHid::Stats& s) { return s.enumerations; }) >= before + 5; }));
  EXPECT_EQ(link.transport->state(), TransportState::disconnected) << "opened another unit";
  link.hid->replug(1);
  ASSERT_TRUE(eventually([&] { return link.transport->state() == TransportState::open; }));
  for (const std::string& path : link.hid->opened_paths()) {
    EXPECT_EQ(path, "/dev/hidraw8");
  }
}

// --- permissions and absent units ------------------------------------------------------------

TEST(HidPermissions, EaccesAtOpenNamesTheNodeTheRuleAndTheGroup) {
  auto hid = std::make_shared<FakeHid>();
  hid->replug(0, 0, /*deny_always=*/true);
  try {
    (void)open_hid_transport("hid://", fast_options(), hid);
    FAIL() << "opened a node we may not write";
  } catch (const PermissionDenied& e) {
    const std::string m = e.what();
    EXPECT_TRUE(contains(m, "/dev/hidraw7")) << m;
    EXPECT_TRUE(contains(m, "udev/70-mrskin.rules")) << m;
    EXPECT_TRUE(contains(m, "udevadm control --reload")) << m;
    EXPECT_TRUE(contains(m, "usermod -aG mrskin")) << m;
  }
  EXPECT_EQ(hid->stat([](const FakeHid::Stats& s) { return s.inits - s.exits; }), 0);
}

TEST(HidPermissions, NoUnitSaysWhatWasSearchedAndWhatToCheck) {
  auto none = std::make_shared<FakeHid>(std::vector<FakeHid::Unit>{});
  try {
    (void)open_hid_transport("hid://", fast_options(), none);
    FAIL() << "opened nothing";
  } catch (const DeviceNotFound& e) {
    EXPECT_TRUE(contains(e.what(), "1209:4d52")) << e.what();
    EXPECT_TRUE(contains(e.what(), "mrskinctl list")) << e.what();
    EXPECT_TRUE(contains(e.what(), "cable")) << e.what();
  }
  auto other = std::make_shared<FakeHid>();
  try {
    (void)open_hid_transport("hid://1209:4d52?serial=0000CAFE", fast_options(), other);
    FAIL() << "opened a unit with another serial";
  } catch (const DeviceNotFound& e) {
    EXPECT_TRUE(contains(e.what(), "serial 0000CAFE")) << e.what();
    EXPECT_TRUE(contains(e.what(), "found only /dev/hidraw7 (serial 0000BEEF)")) << e.what();
  }
}

TEST(HidPermissions, EaccesAfterAHotplugIsRetriedUntilUdevAppliesTheRule) {
  Link link;
  link.hid->unplug();
  ASSERT_TRUE(eventually([&] { return link.transport->state() == TransportState::disconnected; }));
  link.hid->replug(0, /*deny_opens=*/3);
  ASSERT_TRUE(eventually([&] { return link.transport->state() == TransportState::open; }));
  EXPECT_EQ(link.hid->stat([](const FakeHid::Stats& s) { return s.denied; }), 3);
  EXPECT_EQ(link.counters().reopens, 1U);
  EXPECT_EQ(hid_transport_problem(*link.transport), "");
}

TEST(HidPermissions, EaccesThatOutlastsTheRetryIsReportedWithTheFix) {
  HidTransportOptions options = fast_options();
  options.permission_retry = 1ms;
  Link link("hid://", options);
  link.hid->unplug();
  ASSERT_TRUE(eventually([&] { return link.transport->state() == TransportState::disconnected; }));
  link.hid->replug(0, 0, /*deny_always=*/true);
  ASSERT_TRUE(eventually([&] { return !hid_transport_problem(*link.transport).empty(); }));
  const std::string problem = hid_transport_problem(*link.transport);
  EXPECT_TRUE(contains(problem, "permission denied on /dev/hidraw7")) << problem;
  EXPECT_TRUE(contains(problem, "70-mrskin.rules")) << problem;
  EXPECT_EQ(link.transport->state(), TransportState::disconnected);
  link.hid->allow();  // the user fixed it: the transport keeps trying
  ASSERT_TRUE(eventually([&] { return link.transport->state() == TransportState::open; }));
  EXPECT_EQ(hid_transport_problem(*link.transport), "");
}

TEST(HidPermissions, ListingShowsEachUnitWithItsUriAndAnyPermissionProblem) {
  FakeHid hid({{"/dev/hidraw7", "0000BEEF"}, {"/dev/hidraw9", "0000CAFE"}, {"/dev/hidraw4", "no-serial"}});
  hid.replug(1, 0, /*deny_always=*/true);
  const std::vector<DeviceListing> list = list_hid_devices(hid);
  ASSERT_EQ(list.size(), 3U);
  EXPECT_EQ(list[0].bus, "hid");
  EXPECT_EQ(list[0].path, "/dev/hidraw7");
  EXPECT_EQ(list[0].uri, "hid://1209:4d52?serial=0000BEEF");
  EXPECT_EQ(list[0].problem, "");
  EXPECT_EQ(list[1].problem, "permission denied");
  EXPECT_TRUE(contains(list[1].fix, "udev/70-mrskin.rules")) << list[1].fix;
  EXPECT_TRUE(contains(list[1].fix, "usermod -aG mrskin")) << list[1].fix;
  EXPECT_EQ(list[2].uri, "hid://1209:4d52");
  EXPECT_EQ(hid.stat([](const FakeHid::Stats& s) { return s.inits - s.exits; }), 0);
}

TEST(HidOptions, NonsenseIsRefused) {
  HidTransportOptions options;
  options.errors_before_reopen = 0;
  EXPECT_THROW((void)open_hid_transport("hid://", options, std::make_shared<FakeHid>()), InvalidArgument);
  options = {};
  options.time_scale = 0.0;
  EXPECT_THROW((void)open_hid_transport("hid://", options, std::make_shared<FakeHid>()), InvalidArgument);
}

TEST(HidShutdown, ClosesAndBalancesHidInit) {
  auto hid = std::make_shared<FakeHid>();
  {
    auto t = open_hid_transport("hid://", fast_options(), hid);
    ASSERT_EQ(t->send(packet_like(8)), ResultCode::ok);
  }
  EXPECT_EQ(hid->stat([](const FakeHid::Stats& s) { return s.inits; }), 1);
  EXPECT_EQ(hid->stat([](const FakeHid::Stats& s) { return s.exits; }), 1);
}

// The real hidapi (hidraw backend) on this machine: whatever is plugged in, listing answers.
TEST(HidSystem, ListingTheRealHidrawNodesNeverThrows) {
  std::vector<DeviceListing> list;
  ASSERT_NO_THROW(list = list_hid_devices());
  for (const DeviceListing& l : list) {
    EXPECT_EQ(l.bus, "hid");
    EXPECT_TRUE(l.uri.starts_with("hid://1209:4d52")) << l.uri;
    EXPECT_EQ(l.problem.empty(), l.fix.empty()) << l.problem;
  }
}

// --- allocation ------------------------------------------------------------------------------

TEST(HidAllocation, DatagramsAllocateNothing) {
  Link link;
  link.hid->set_record_writes(false);
  link.hid->set_echo(true);
  const Bytes p = packet_like(40);
  Datagram d;
  auto round_trip = [&] {
    if (link.transport->send(p) != ResultCode::ok) {
      return false;
    }
    return link.transport->receive_for(d, 20s) == ResultCode::ok;
  };
  for (int i = 0; i < 50; ++i) {
    ASSERT_TRUE(round_trip());
  }
  const std::uint64_t before = test::allocation_count();
  int ok = 0;
  for (int i = 0; i < 2000; ++i) {
    ok += round_trip() ? 1 : 0;
  }
  const std::uint64_t allocations = test::allocation_count() - before;
  EXPECT_EQ(ok, 2000);
  EXPECT_EQ(allocations, 0U);
  EXPECT_EQ(d.length, 64U);
  EXPECT_TRUE(std::equal(p.begin(), p.end(), d.bytes.begin()));
}

// --- end to end ----------------------------------------------------------------------------

// The mock device's firmware as the unit behind the fake hidraw node.
class MockPeer final : public Peer {
 public:
  explicit MockPeer(std::unique_ptr<Transport> link) : link_(std::move(link)) {}
  void host_wrote(std::span<const std::uint8_t> report) noexcept override { (void)link_->send(report); }
  bool device_report(std::span<std::uint8_t> out) noexcept override {
    Datagram d;
    if (link_->receive(d) != ResultCode::ok) {
      return false;
    }
    std::fill(out.begin(), out.end(), 0);
    std::copy_n(d.bytes.begin(), std::min<std::size_t>(d.length, out.size()), out.begin());
    return true;
  }

 private:
  std::unique_ptr<Transport> link_;
};

TEST(HidSession, HandshakeEnableTelemetryAndReconnectOverTheMockDevice) {
  MonotonicClock clock;
  sim::MockOptions mock_options;
  mock_options.seed = 11;
  mock_options.time_scale = 10.0;  // sanitizer builds run slowly: no heartbeat loss from that
  const std::shared_ptr<sim::MockDevice> mock = sim::MockDevice::make(mock_options);
  mock->start(clock);
  MockPeer peer(mock->connect(false));
  auto hid = std::make_shared<FakeHid>(std::vector<FakeHid::Unit>{{"/dev/hidraw3", "4D520001"}});
  hid->set_record_writes(false);
  hid->set_peer(&peer);
  SessionOptions session_options;
  session_options.time_scale = 10.0;
  auto session = std::make_unique<DeviceSession>(
      open_hid_transport("hid://1209:4d52?serial=4d520001", fast_options(), hid), clock, session_options);
  EXPECT_EQ(session->info().serial, 0x4D520001U);
  EXPECT_EQ(session->info().valves, 12U);
  ASSERT_NE(session->profile(), nullptr);

  const std::vector<double> currents(session->info().valves, 0.02);
  auto run_until = [&](auto done) {
    return eventually([&] {
      if (session->poll(clock.now()) == ResultCode::ok) {
        (void)session->send_valve_currents(currents);
      }
      return done();
    });
  };
  ASSERT_EQ(session->request_enable(), ResultCode::ok);
  const std::uint64_t t0 = session->counters().telemetry;
  ASSERT_TRUE(run_until(
      [&] { return session->state() == DeviceState::enabled && session->counters().telemetry > t0 + 100; }));
  EXPECT_EQ(session->counters().crc_errors, 0U);
  std::vector<double> applied(session->info().valves);
  ASSERT_TRUE(run_until([&] {
    mock->applied_currents(applied);
    return std::abs(applied[0] - 0.02) < 1e-3;
  }));

  // Unplug: the unit loses power with its link; the session sees the transport go down.
  mock->set_link_up(false);
  hid->unplug();
  ASSERT_TRUE(run_until([&] { return !session->connected(); }));
  EXPECT_EQ(session->poll(clock.now()), ResultCode::disconnected);
  mock->set_link_up(true);
  hid->replug();
  // Back: the transport reopens the node, the session re-identifies the unit and enables it
  // again, as the host had asked.
  ASSERT_TRUE(run_until([&] { return session->connected() && session->state() == DeviceState::enabled; }));
  const std::uint64_t t1 = session->counters().telemetry;
  ASSERT_TRUE(run_until([&] { return session->counters().telemetry > t1 + 100; }));
  EXPECT_EQ(session->counters().reconnects, 1U);
  EXPECT_EQ(session->counters().identity_changes, 0U);
  EXPECT_EQ(session->transport_state(), TransportState::open);
  session.reset();  // joins the transport's threads before the peer and the mock go
  mock->stop();
}

}  // namespace
}  // namespace mrskin
