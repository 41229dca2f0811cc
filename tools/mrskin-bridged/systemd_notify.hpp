// systemd's service notification protocol (sd_notify(3)), without libsystemd: datagrams to
// $NOTIFY_SOCKET. READY=1 after the first tick, WATCHDOG=1 while the tick counter advances
// without an overrun storm, STOPPING=1 at the end (docs/daemon.md, "systemd").
#pragma once

#include <sys/socket.h>
#include <sys/un.h>

#include <chrono>
#include <cstdint>
#include <optional>
#include <string_view>

namespace mrskin::bridged {

class SystemdNotifier {
 public:
  // Reads NOTIFY_SOCKET (a path, or "@name" in the abstract namespace), WATCHDOG_USEC and
  // WATCHDOG_PID; inactive without NOTIFY_SOCKET. Never throws: a bad variable is ignored.
  SystemdNotifier() noexcept;
  SystemdNotifier(const SystemdNotifier&) = delete;
  SystemdNotifier& operator=(const SystemdNotifier&) = delete;
  SystemdNotifier(SystemdNotifier&&) = delete;
  SystemdNotifier& operator=(SystemdNotifier&&) = delete;
  ~SystemdNotifier();

  [[nodiscard]] bool active() const noexcept { return fd_ >= 0; }
  // Half of WATCHDOG_USEC (sd_watchdog_enabled(3)'s advice), when the watchdog is on for us.
  [[nodiscard]] std::optional<std::chrono::microseconds> watchdog_interval() const noexcept {
    return watchdog_interval_;
  }
  // Best effort: false if not active or the datagram was not sent.
  bool notify(std::string_view state) const noexcept;

 private:
  int fd_ = -1;
  sockaddr_un addr_{};
  socklen_t addr_len_ = 0;
  std::optional<std::chrono::microseconds> watchdog_interval_;
};

// Whether the loop is healthy enough to pet the watchdog: the tick counter advanced since the
// last verdict and at most half of those ticks overran (an overrun storm: the loop runs but
// misses its deadlines). Counters are cumulative; a counter that goes back (a rebuilt loop on
// reload) restarts the comparison.
class WatchdogGate {
 public:
  bool healthy(std::uint64_t ticks, std::uint64_t overruns) noexcept;

 private:
  std::uint64_t last_ticks_ = 0;
  std::uint64_t last_overruns_ = 0;
};

}  // namespace mrskin::bridged
