#include "systemd_notify.hpp"

#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <string>

namespace mrskin::bridged {

SystemdNotifier::SystemdNotifier() noexcept {
  // NOLINTBEGIN(concurrency-mt-unsafe): read once in main before any thread starts
  const char* socket_path = std::getenv("NOTIFY_SOCKET");
  const char* usec = std::getenv("WATCHDOG_USEC");
  const char* pid = std::getenv("WATCHDOG_PID");
  // NOLINTEND(concurrency-mt-unsafe)
  if (socket_path == nullptr || (socket_path[0] != '/' && socket_path[0] != '@')) {
    return;
  }
  const std::size_t len = std::strlen(socket_path);
  if (len < 2 || len >= sizeof(addr_.sun_path)) {
    return;
  }
  addr_.sun_family = AF_UNIX;
  std::memcpy(addr_.sun_path, socket_path, len);
  if (addr_.sun_path[0] == '@') {
    addr_.sun_path[0] = '\0';  // abstract namespace
  }
  addr_len_ = static_cast<socklen_t>(offsetof(sockaddr_un, sun_path) + len);
  fd_ = ::socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
  if (usec != nullptr) {
    char* end = nullptr;
    errno = 0;
    const unsigned long long us = std::strtoull(usec, &end, 10);
    const bool for_us =
        pid == nullptr || std::strtoll(pid, nullptr, 10) == static_cast<long long>(::getpid());
    if (errno == 0 && end != usec && *end == '\0' && us > 0 && for_us) {
      watchdog_interval_ = std::chrono::microseconds(static_cast<std::int64_t>(us / 2));
    }
  }
}

SystemdNotifier::~SystemdNotifier() {
  if (fd_ >= 0) {
    ::close(fd_);
  }
}

bool SystemdNotifier::notify(std::string_view state) const noexcept {
  if (fd_ < 0) {
    return false;
  }
  const ssize_t n = ::sendto(fd_, state.data(), state.size(), MSG_NOSIGNAL,
                             static_cast<const sockaddr*>(static_cast<const void*>(&addr_)), addr_len_);
  return n == static_cast<ssize_t>(state.size());
}

bool WatchdogGate::healthy(std::uint64_t ticks, std::uint64_t overruns) noexcept {
  if (ticks < last_ticks_ || overruns < last_overruns_) {  // a new loop: compare from here
    last_ticks_ = ticks;
    last_overruns_ = overruns;
    return true;
  }
  const std::uint64_t dt = ticks - last_ticks_;
  const std::uint64_t dover = overruns - last_overruns_;
  last_ticks_ = ticks;
  last_overruns_ = overruns;
  return dt > 0 && 2 * dover <= dt;
}

}  // namespace mrskin::bridged
