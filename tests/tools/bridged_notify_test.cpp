// mrskin-bridged as systemd sees it (Type=notify, WatchdogSec): a NOTIFY_SOCKET of the test's
// own receives READY=1 after the first tick, then WATCHDOG=1; with the tick thread alone stopped
// (ptrace, the rest of the daemon running) the pings stop, and they resume with it; SIGTERM sends
// STOPPING=1. Bounded waits; no timing is asserted beyond "nothing while stalled".
#include <gtest/gtest.h>
#include <sys/ptrace.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "child_process.hpp"

namespace fs = std::filesystem;
using namespace std::chrono_literals;

namespace {

// The test's end of the notification socket.
class NotifySocket {
 public:
  explicit NotifySocket(const fs::path& path) : fd_(::socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC, 0)) {
    sockaddr_un a{};
    a.sun_family = AF_UNIX;
    std::strncpy(a.sun_path, path.c_str(), sizeof(a.sun_path) - 1);
    bound_ =
        fd_ >= 0 && ::bind(fd_, static_cast<const sockaddr*>(static_cast<const void*>(&a)), sizeof(a)) == 0;
    timeval tv{0, 20000};  // 20 ms receive timeout: the waits below are loops with bounds
    (void)::setsockopt(fd_, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof(tv));
  }
  NotifySocket(const NotifySocket&) = delete;
  NotifySocket& operator=(const NotifySocket&) = delete;
  NotifySocket(NotifySocket&&) = delete;
  NotifySocket& operator=(NotifySocket&&) = delete;
  ~NotifySocket() {
    if (fd_ >= 0) {
      ::close(fd_);
    }
  }
  [[nodiscard]] bool bound() const noexcept { return bound_; }
  // The messages received within `for_how_long` (each datagram one entry).
  std::vector<std::string> receive(std::chrono::milliseconds for_how_long) const {
    std::vector<std::string> got;
    const auto end = std::chrono::steady_clock::now() + for_how_long;
    char buf[512];
    while (std::chrono::steady_clock::now() < end) {
      const ssize_t n = ::recv(fd_, buf, sizeof(buf), 0);
      if (n > 0) {
        got.emplace_back(buf, static_cast<std::size_t>(n));
      }
    }
    return got;
  }
  // Waits (bounded) for a datagram containing `what`; the ones before it are dropped.
  [[nodiscard]] bool wait_for(const std::string& what, std::chrono::seconds bound = 20s) const {
    const auto end = std::chrono::steady_clock::now() + bound;
    while (std::chrono::steady_clock::now() < end) {
      for (const std::string& m : receive(50ms)) {
        if (m.find(what) != std::string::npos) {
          return true;
        }
      }
    }
    return false;
  }

 private:
  int fd_;
  bool bound_ = false;
};

std::size_t count(const std::vector<std::string>& msgs, const std::string& what) {
  std::size_t n = 0;
  for (const std::string& m : msgs) {
    n += m.find(what) != std::string::npos ? 1 : 0;
  }
  return n;
}

// ptrace(2) on one thread, with no address or data.
long trace(__ptrace_request request, pid_t tid) {
  return ::ptrace(request, tid, nullptr, nullptr);  // NOLINT(cppcoreguidelines-pro-type-vararg)
}

// The daemon's tick thread, by the name the loop gives it; -1 if not found.
pid_t loop_thread(pid_t pid) {
  std::error_code ec;
  for (const fs::directory_entry& e :
       fs::directory_iterator(fs::path("/proc") / std::to_string(pid) / "task", ec)) {
    std::ifstream comm(e.path() / "comm");
    std::string name;
    std::getline(comm, name);
    if (name == "mrskin-loop") {
      return static_cast<pid_t>(std::stol(e.path().filename().string()));
    }
  }
  return -1;
}

class BridgedNotify : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string tmpl = (fs::temp_directory_path() / "mrskin-notify-test-XXXXXX").string();
    ASSERT_NE(::mkdtemp(tmpl.data()), nullptr);
    dir_ = tmpl;
  }
  void TearDown() override {
    ::unsetenv("NOTIFY_SOCKET");
    ::unsetenv("WATCHDOG_USEC");
    fs::remove_all(dir_);
  }
  fs::path dir_;
};

TEST_F(BridgedNotify, ReadyThenWatchdogThatStopsWhileTheTickThreadIsStalled) {
  const NotifySocket sock(dir_ / "notify.sock");
  ASSERT_TRUE(sock.bound());
  // Inherited by the daemon: WatchdogSec=0.2 s, so a ping every 0.1 s. The session timeouts are
  // stretched (MRSKIN_TIME_SCALE) so that the stall below does not also trip the mock's
  // heartbeat watchdog.
  ::setenv("NOTIFY_SOCKET", (dir_ / "notify.sock").c_str(), 1);
  ::setenv("WATCHDOG_USEC", "200000", 1);
  ::setenv("MRSKIN_TIME_SCALE", "50", 1);
  mrskin::test::ChildProcess daemon(dir_ / "daemon.out", dir_ / "daemon.out",
                                    {MRSKIN_BRIDGED_EXE, "--device", "mock://", "--duration", "60", "--quiet",
                                     "--socket", (dir_ / "ctl.sock").string()});
  ::unsetenv("MRSKIN_TIME_SCALE");

  ASSERT_TRUE(sock.wait_for("READY=1")) << daemon.out();
  ASSERT_TRUE(sock.wait_for("WATCHDOG=1")) << daemon.out();
  ASSERT_TRUE(sock.wait_for("WATCHDOG=1")) << daemon.out();

  pid_t tid = -1;
  ASSERT_TRUE(mrskin::test::eventually([&] { return (tid = loop_thread(daemon.pid())) > 0; }))
      << "no thread named mrskin-loop in the daemon";
  // Stops that one thread only (PTRACE_INTERRUPT, no group stop): the main thread runs on.
  if (trace(PTRACE_SEIZE, tid) != 0) {
    GTEST_SKIP() << "ptrace refused (" << std::strerror(errno)
                 << "): cannot stall the tick thread alone here";
  }
  ASSERT_EQ(trace(PTRACE_INTERRUPT, tid), 0) << std::strerror(errno);
  int status = 0;
  ASSERT_EQ(::waitpid(tid, &status, __WALL), tid);

  const std::string withheld = "service watchdog not petted";
  const bool said =
      mrskin::test::eventually([&] { return daemon.out().find(withheld) != std::string::npos; });
  (void)sock.receive(50ms);  // pings sent before that line
  const std::vector<std::string> while_stalled = sock.receive(500ms);
  ASSERT_EQ(trace(PTRACE_DETACH, tid), 0) << std::strerror(errno);
  EXPECT_TRUE(said) << daemon.out();
  EXPECT_EQ(count(while_stalled, "WATCHDOG=1"), 0U) << "pinged while the tick thread was stopped";

  EXPECT_TRUE(sock.wait_for("WATCHDOG=1")) << "no ping after the tick thread resumed\n" << daemon.out();
  daemon.signal(SIGTERM);
  EXPECT_TRUE(sock.wait_for("STOPPING=1")) << daemon.out();
  EXPECT_EQ(daemon.wait(60s), 0) << daemon.out();
  EXPECT_NE(daemon.out().find("ticks on time again"), std::string::npos) << daemon.out();
}

TEST_F(BridgedNotify, NothingIsSentWithoutNotifySocket) {
  // The daemon outside systemd: no NOTIFY_SOCKET, and the run is the same (exit 0 at --duration).
  const NotifySocket sock(dir_ / "notify.sock");
  ASSERT_TRUE(sock.bound());
  mrskin::test::ChildProcess daemon(dir_ / "daemon.out", dir_ / "daemon.out",
                                    {MRSKIN_BRIDGED_EXE, "--device", "mock://", "--duration", "0.5",
                                     "--quiet", "--socket", (dir_ / "ctl.sock").string()});
  EXPECT_EQ(daemon.wait(60s), 0) << daemon.out();
  EXPECT_TRUE(sock.receive(100ms).empty());
}

}  // namespace
