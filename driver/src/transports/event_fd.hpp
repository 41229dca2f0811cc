// An eventfd owned by a transport's I/O side: wakes a thread blocked in poll(). Internal header.
#pragma once

#include <fmt/format.h>
#include <sys/eventfd.h>
#include <unistd.h>

#include <cerrno>
#include <cstdint>
#include <cstring>
#include <string_view>

#include "mrskin/driver/errors.hpp"

namespace mrskin::transports {

class EventFd {
 public:
  // Throws Error naming what it is for when the process is out of file descriptors.
  explicit EventFd(std::string_view purpose) : fd_(::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC)) {
    if (fd_ < 0) {
      throw Error(fmt::format("cannot create an eventfd for {}: {} (raise the open-file limit, ulimit -n)",
                              purpose, std::strerror(errno)));
    }
  }
  EventFd(const EventFd&) = delete;
  EventFd& operator=(const EventFd&) = delete;
  EventFd(EventFd&&) = delete;
  EventFd& operator=(EventFd&&) = delete;
  ~EventFd() { ::close(fd_); }
  [[nodiscard]] int fd() const noexcept { return fd_; }
  void signal() const noexcept {
    const std::uint64_t one = 1;
    // Fails only when the counter would overflow: the waiters are woken already.
    [[maybe_unused]] const ssize_t n = ::write(fd_, &one, sizeof one);
  }
  void clear() const noexcept {
    std::uint64_t value = 0;
    [[maybe_unused]] const ssize_t n = ::read(fd_, &value, sizeof value);
  }

 private:
  int fd_;
};

}  // namespace mrskin::transports
