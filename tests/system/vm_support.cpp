#include "vm_support.hpp"

#include <fcntl.h>
#include <gtest/gtest.h>
#include <linux/uhid.h>
#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <stdexcept>
#include <string_view>

#include "mrskin/driver/transports/can.hpp"
#include "mrskin/protocol/packet.hpp"
#include "mrskin/protocol/usb.hpp"

namespace mrskin::vmtest {

double time_scale() {
  const char* s = std::getenv("MRSKIN_TIME_SCALE");
  if (s == nullptr || *s == '\0') {
    return 1.0;
  }
  return std::max(1.0, std::strtod(s, nullptr));
}

std::string output_dir() {
  const char* s = std::getenv("MRSKIN_VM_OUT");
  return s != nullptr && *s != '\0' ? std::string(s) : std::string(".");
}

std::shared_ptr<sim::MockDevice> start_mock(Clock& clock) {
  sim::MockOptions options;
  options.seed = 8;
  options.serial = kSerial;
  options.time_scale = time_scale();
  auto mock = sim::MockDevice::make(options);
  mock->start(clock);
  return mock;
}

// --- FirmwareAdapter ------------------------------------------------------------------------------

FirmwareAdapter::FirmwareAdapter(std::shared_ptr<sim::MockDevice> mock)
    : mock_(std::move(mock)), firmware_(mock_->connect(false)) {}

FirmwareAdapter::~FirmwareAdapter() { stop(); }

void FirmwareAdapter::start() {
  running_ = true;
  thread_ = std::thread([this] { run(); });
}

void FirmwareAdapter::stop() noexcept {
  running_ = false;
  if (thread_.joinable()) {
    thread_.join();
  }
}

void FirmwareAdapter::run() noexcept {
  const auto deliver = [this](const Datagram& d) {
    if (firmware_->send(std::span<const std::uint8_t>(d.bytes.data(), d.length)) == ResultCode::ok) {
      from_bus_.fetch_add(1);
    } else {
      dropped_.fetch_add(1);
    }
  };
  while (running_.load()) {
    try {
      Datagram d;
      int budget = 64;
      while (budget-- > 0 && firmware_->receive(d) == ResultCode::ok) {
        if (write_bus(d)) {
          to_bus_.fetch_add(1);
        } else {
          dropped_.fetch_add(1);
        }
      }
      if (!read_bus(1, deliver)) {
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
      }
    } catch (const std::exception& e) {
      std::fprintf(stderr, "adapter: %s\n", e.what());
      std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
  }
}

// --- CanNode ----------------------------------------------------------------------------------------

namespace {
std::unique_ptr<Transport> open_node(const std::string& uri) {
  CanTransportOptions options;
  options.role = CanRole::device;
  options.time_scale = time_scale();
  return open_can_transport(uri, options);
}
}  // namespace

CanNode::CanNode(std::shared_ptr<sim::MockDevice> mock, const std::string& uri)
    : FirmwareAdapter(std::move(mock)), bus_(open_node(uri)) {
  start();
}

CanNode::~CanNode() { stop(); }

bool CanNode::read_bus(int timeout_ms, const std::function<void(const Datagram&)>& deliver) {
  Datagram d;
  if (bus_->receive_for(d, std::chrono::milliseconds(timeout_ms)) != ResultCode::ok) {
    return true;
  }
  deliver(d);
  while (bus_->receive(d) == ResultCode::ok) {
    deliver(d);
  }
  return true;
}

bool CanNode::write_bus(const Datagram& d) {
  return bus_->send(std::span<const std::uint8_t>(d.bytes.data(), d.length)) == ResultCode::ok;
}

// --- UhidUnit ---------------------------------------------------------------------------------------

namespace {
bool uhid_write(int fd, const uhid_event& ev) {
  return ::write(fd, &ev, sizeof ev) == static_cast<ssize_t>(sizeof ev);
}
}  // namespace

UhidUnit::UhidUnit(std::shared_ptr<sim::MockDevice> mock) : FirmwareAdapter(std::move(mock)) {
  fd_ = ::open("/dev/uhid", O_RDWR | O_CLOEXEC | O_NONBLOCK);
  if (fd_ < 0) {
    throw std::runtime_error(std::string("open /dev/uhid: ") + std::strerror(errno));
  }
  create();
  start();
}

UhidUnit::~UhidUnit() {
  stop();
  destroy();
  ::close(fd_);
}

void UhidUnit::create() {
  uhid_event ev{};
  ev.type = UHID_CREATE2;
  std::snprintf(reinterpret_cast<char*>(ev.u.create2.name), sizeof ev.u.create2.name, "%s",
                "mrskin MR skin (uhid, VM test)");
  std::snprintf(reinterpret_cast<char*>(ev.u.create2.phys), sizeof ev.u.create2.phys, "%s",
                "mrskin-vm/uhid0");
  const std::string serial = protocol::format_usb_serial(kSerial);
  std::snprintf(reinterpret_cast<char*>(ev.u.create2.uniq), sizeof ev.u.create2.uniq, "%s", serial.c_str());
  std::copy(protocol::kHidReportDescriptor.begin(), protocol::kHidReportDescriptor.end(),
            ev.u.create2.rd_data);
  ev.u.create2.rd_size = static_cast<std::uint16_t>(protocol::kHidReportDescriptor.size());
  ev.u.create2.bus = 0x03;  // BUS_USB
  ev.u.create2.vendor = protocol::kUsbVendorId;
  ev.u.create2.product = protocol::kUsbProductId;
  ev.u.create2.version = 0x0100;
  if (!uhid_write(fd_, ev)) {
    throw std::runtime_error(std::string("UHID_CREATE2: ") + std::strerror(errno));
  }
  present_ = true;
}

void UhidUnit::destroy() {
  if (!present_.exchange(false)) {
    return;
  }
  uhid_event ev{};
  ev.type = UHID_DESTROY;
  (void)uhid_write(fd_, ev);
  opened_ = false;
}

void UhidUnit::unplug() {
  mock().set_link_up(false);
  destroy();
}

void UhidUnit::plug() {
  create();
  mock().set_link_up(true);
}

bool UhidUnit::read_bus(int timeout_ms, const std::function<void(const Datagram&)>& deliver) {
  pollfd p{fd_, POLLIN, 0};
  if (::poll(&p, 1, timeout_ms) <= 0) {
    return true;
  }
  for (int i = 0; i < 64; ++i) {
    uhid_event ev{};
    const ssize_t n = ::read(fd_, &ev, sizeof ev);
    if (n <= 0) {
      break;
    }
    switch (ev.type) {
      case UHID_OPEN:
        opened_ = true;
        break;
      case UHID_CLOSE:
        opened_ = false;
        break;
      case UHID_OUTPUT: {
        // No report IDs: hidraw hands on 0x00 + the 64-byte report; drop the ID byte.
        const std::uint8_t* data = ev.u.output.data;
        std::size_t size = ev.u.output.size;
        if (size == protocol::kHidReportBytes + 1 && data[0] == 0) {
          ++data;
          --size;
        }
        Datagram d;
        d.length = static_cast<std::uint16_t>(std::min<std::size_t>(size, kMaxDatagramBytes));
        std::copy_n(data, d.length, d.bytes.begin());
        deliver(d);
        break;
      }
      case UHID_GET_REPORT: {
        uhid_event reply{};
        reply.type = UHID_GET_REPORT_REPLY;
        reply.u.get_report_reply.id = ev.u.get_report.id;
        reply.u.get_report_reply.err = EIO;
        (void)uhid_write(fd_, reply);
        break;
      }
      case UHID_SET_REPORT: {
        uhid_event reply{};
        reply.type = UHID_SET_REPORT_REPLY;
        reply.u.set_report_reply.id = ev.u.set_report.id;
        reply.u.set_report_reply.err = EIO;
        (void)uhid_write(fd_, reply);
        break;
      }
      default:
        break;
    }
  }
  return true;
}

bool UhidUnit::write_bus(const Datagram& d) {
  if (!present_.load()) {
    return false;  // unplugged: the packet is lost with the cable
  }
  if (d.length > protocol::kHidReportBytes) {
    return false;  // the unit's descriptor has 64-byte reports: a larger datagram has no form here
  }
  uhid_event ev{};
  ev.type = UHID_INPUT2;
  ev.u.input2.size = static_cast<std::uint16_t>(protocol::kHidReportBytes);
  std::copy_n(d.bytes.begin(), d.length, ev.u.input2.data);
  return uhid_write(fd_, ev);
}

// --- GadgetUnit -------------------------------------------------------------------------------------

GadgetUnit::GadgetUnit(std::shared_ptr<sim::MockDevice> mock, std::string node)
    : FirmwareAdapter(std::move(mock)), node_(std::move(node)) {
  start();
}

GadgetUnit::~GadgetUnit() {
  stop();
  close_node();
}

void GadgetUnit::close_node() noexcept {
  if (fd_ >= 0) {
    ::close(fd_);
    fd_ = -1;
  }
  is_open_ = false;
}

bool GadgetUnit::read_bus(int timeout_ms, const std::function<void(const Datagram&)>& deliver) {
  if (!want_open_.load()) {
    close_node();
    return false;
  }
  if (fd_ < 0) {
    fd_ = ::open(node_.c_str(), O_RDWR | O_CLOEXEC | O_NONBLOCK);
    if (fd_ < 0) {
      return false;  // not bound (yet): try again
    }
    is_open_ = true;
  }
  pollfd p{fd_, POLLIN, 0};
  if (::poll(&p, 1, timeout_ms) <= 0) {
    return true;
  }
  if ((p.revents & (POLLERR | POLLHUP | POLLNVAL)) != 0) {
    close_node();
    return false;
  }
  for (int i = 0; i < 64; ++i) {
    std::array<std::uint8_t, protocol::kHidReportBytes> report{};
    const ssize_t n = ::read(fd_, report.data(), report.size());
    if (n < 0 && errno != EAGAIN && errno != EINTR) {
      close_node();  // the gadget went away: reopen when it is back
      return false;
    }
    if (n <= 0) {
      break;
    }
    Datagram d;
    d.length = static_cast<std::uint16_t>(n);
    std::copy_n(report.begin(), d.length, d.bytes.begin());
    deliver(d);
  }
  return true;
}

bool GadgetUnit::write_bus(const Datagram& d) {
  if (fd_ < 0 || d.length > protocol::kHidReportBytes) {
    return false;  // the gadget's reports are 64 bytes (full speed): a larger datagram has no form
  }
  std::array<std::uint8_t, protocol::kHidReportBytes> report{};
  std::copy_n(d.bytes.begin(), d.length, report.begin());
  // Non-blocking: a host that is not reading (or no host at all) loses the report.
  return ::write(fd_, report.data(), report.size()) == static_cast<ssize_t>(report.size());
}

// --- waiting, children ------------------------------------------------------------------------------

bool poll_until(DeviceSession& session, Clock& clock, const std::function<bool()>& done, double guard_s) {
  const auto guard =
      std::chrono::steady_clock::now() + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                             std::chrono::duration<double>(guard_s * time_scale()));
  while (!done()) {
    if (std::chrono::steady_clock::now() > guard) {
      return done();
    }
    (void)session.poll(clock.now());
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  return true;
}

Child::Child(const std::vector<std::string>& argv, const std::string& output_path) {
  std::vector<char*> args;
  args.reserve(argv.size() + 1);
  for (const std::string& a : argv) {
    args.push_back(const_cast<char*>(a.c_str()));
  }
  args.push_back(nullptr);
  pid_ = ::fork();
  if (pid_ < 0) {
    throw std::runtime_error(std::string("fork: ") + std::strerror(errno));
  }
  if (pid_ == 0) {
    const int out = ::open(output_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
    if (out >= 0) {
      ::dup2(out, 1);
      ::dup2(out, 2);
    }
    ::execvp(args[0], args.data());
    ::_exit(127);
  }
}

Child::~Child() { (void)stop(); }

int Child::stop() {
  if (pid_ <= 0) {
    return -1;
  }
  ::kill(pid_, SIGINT);
  int status = 0;
  for (int i = 0; i < 2000; ++i) {  // bounded: then SIGKILL
    if (::waitpid(pid_, &status, WNOHANG) == pid_) {
      pid_ = -1;
      return status;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  ::kill(pid_, SIGKILL);
  ::waitpid(pid_, &status, 0);
  pid_ = -1;
  return status;
}

int run_command(const std::string& command, std::string* output) {
  FILE* pipe = ::popen((command + " 2>&1").c_str(), "r");
  if (pipe == nullptr) {
    return -1;
  }
  std::array<char, 4096> buffer{};
  std::size_t n = 0;
  while ((n = std::fread(buffer.data(), 1, buffer.size(), pipe)) > 0) {
    if (output != nullptr) {
      output->append(buffer.data(), n);
    }
  }
  const int status = ::pclose(pipe);
  return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

OpenedDevice open_with_retry(const std::string& uri, Clock& clock) {
  for (int attempt = 0;; ++attempt) {
    try {
      return open_device(uri, clock);
    } catch (const DeviceNotFound&) {
      if (attempt >= 100) {
        throw;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
  }
}

void print_counters(const char* prefix, const char* when, const DeviceSession& s) {
  const SessionCounters& c = s.counters();
  std::printf(
      "%s: %s: telemetry %llu, sent %llu, received %llu, decode errors %llu, gaps %llu, "
      "disconnects %llu, reconnects %llu, state %s\n",
      prefix, when, static_cast<unsigned long long>(c.telemetry), static_cast<unsigned long long>(c.sent),
      static_cast<unsigned long long>(c.received), static_cast<unsigned long long>(c.decode_errors),
      static_cast<unsigned long long>(c.sequence_gaps), static_cast<unsigned long long>(c.disconnects),
      static_cast<unsigned long long>(c.reconnects), to_string(s.state()));
}

void expect_session_runs(DeviceSession& session, sim::MockDevice& mock, Clock& clock) {
  EXPECT_EQ(session.info().serial, kSerial);
  EXPECT_EQ(session.info().valves, mock.layout().valves().size());
  ASSERT_NE(session.profile(), nullptr);
  ASSERT_EQ(session.request_enable(), ResultCode::ok);
  ASSERT_TRUE(poll_until(
      session, clock, [&] { return session.state() == DeviceState::enabled; }, 5.0))
      << "state " << to_string(session.state());
  std::vector<double> currents(session.info().valves, 0.25 * session.info().max_current_A);
  ASSERT_EQ(session.send_valve_currents(currents), ResultCode::ok);
  std::vector<double> applied(currents.size());
  EXPECT_TRUE(poll_until(
      session, clock,
      [&] {
        mock.applied_currents(applied);
        return applied[0] > 0.2 * session.info().max_current_A;
      },
      5.0));
  const std::uint64_t t0 = session.counters().telemetry;
  EXPECT_TRUE(poll_until(
      session, clock, [&] { return session.counters().telemetry >= t0 + 50; }, 10.0));
}

void expect_unplug_noticed_and_replug_reconnects(const char* prefix, DeviceSession& session, Clock& clock,
                                                 const std::function<void()>& unplug,
                                                 const std::function<void()>& plug,
                                                 double reconnect_guard_s) {
  const std::uint64_t disconnects = session.counters().disconnects;
  const std::uint64_t reconnects = session.counters().reconnects;
  unplug();
  EXPECT_TRUE(poll_until(
      session, clock, [&] { return !session.connected(); }, 10.0))
      << "the unplug was not noticed";
  EXPECT_GT(session.counters().disconnects, disconnects);
  print_counters(prefix, "unplugged", session);
  plug();
  EXPECT_TRUE(poll_until(
      session, clock, [&] { return session.connected(); }, reconnect_guard_s))
      << "no reconnect";
  EXPECT_GT(session.counters().reconnects, reconnects);
  const std::uint64_t t1 = session.counters().telemetry;
  EXPECT_TRUE(poll_until(
      session, clock, [&] { return session.counters().telemetry >= t1 + 50; }, 10.0));
}

}  // namespace mrskin::vmtest
