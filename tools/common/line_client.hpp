// A client for mrskin-bridged's control socket (docs/daemon.md): connect to the UNIX socket,
// send one request line, read response lines with a timeout. Header-only, no JSON library:
// callers read the lines with JsonReply (json_reply.hpp) or print them as they come.
#pragma once

#include <poll.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <chrono>
#include <optional>
#include <string>
#include <string_view>
#include <utility>

namespace mrskin::ctl {

class LineClient {
 public:
  LineClient() = default;
  LineClient(const LineClient&) = delete;
  LineClient& operator=(const LineClient&) = delete;
  LineClient(LineClient&& o) noexcept : fd_(o.fd_), buffer_(std::move(o.buffer_)) { o.fd_ = -1; }
  LineClient& operator=(LineClient&& o) noexcept {
    std::swap(fd_, o.fd_);
    std::swap(buffer_, o.buffer_);
    return *this;
  }
  ~LineClient() { close(); }

  // False with errno set when nobody listens on path.
  bool connect(const std::string& path) {
    close();
    sockaddr_un addr{};
    addr.sun_family = AF_UNIX;
    if (path.size() >= sizeof(addr.sun_path)) {
      errno = ENAMETOOLONG;
      return false;
    }
    std::copy(path.begin(), path.end(), static_cast<char*>(addr.sun_path));
    fd_ = ::socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
    // NOLINTNEXTLINE(cppcoreguidelines-pro-type-reinterpret-cast): the socket API's own cast
    if (fd_ < 0 || ::connect(fd_, reinterpret_cast<const sockaddr*>(&addr), sizeof(addr)) != 0) {
      close();
      return false;
    }
    return true;
  }
  [[nodiscard]] bool connected() const noexcept { return fd_ >= 0; }
  void close() noexcept {
    if (fd_ >= 0) {
      ::close(fd_);
      fd_ = -1;
    }
    buffer_.clear();
  }

  // Sends text plus a newline.
  bool send_line(std::string_view text) const {
    std::string line(text);
    line += '\n';
    std::size_t done = 0;
    while (done < line.size()) {
      const ssize_t n = ::send(fd_, line.data() + done, line.size() - done, MSG_NOSIGNAL);
      if (n < 0) {
        if (errno == EINTR) {
          continue;
        }
        return false;
      }
      done += static_cast<std::size_t>(n);
    }
    return true;
  }

  // The next line without its newline; nullopt on timeout or when the daemon closed the socket.
  std::optional<std::string> read_line(std::chrono::milliseconds timeout) {
    const auto deadline = std::chrono::steady_clock::now() + timeout;
    for (;;) {
      if (const std::size_t nl = buffer_.find('\n'); nl != std::string::npos) {
        std::string line = buffer_.substr(0, nl);
        buffer_.erase(0, nl + 1);
        return line;
      }
      const auto left =
          std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
      if (fd_ < 0 || left.count() <= 0) {
        return std::nullopt;
      }
      pollfd p{fd_, POLLIN, 0};
      if (::poll(&p, 1, static_cast<int>(left.count())) <= 0) {
        continue;
      }
      std::array<char, 4096> chunk{};
      const ssize_t n = ::recv(fd_, chunk.data(), chunk.size(), 0);
      if (n <= 0) {
        return std::nullopt;
      }
      buffer_.append(chunk.data(), static_cast<std::size_t>(n));
    }
  }

  // Hands over the socket and whatever was read past the last line (a connection that leaves
  // the line protocol: mrskinctl's device lease); the client is closed after.
  std::pair<int, std::string> release() noexcept {
    std::pair<int, std::string> out{fd_, std::move(buffer_)};
    fd_ = -1;
    buffer_.clear();
    return out;
  }

  // One request, one response line.
  std::optional<std::string> request(std::string_view line,
                                     std::chrono::milliseconds timeout = std::chrono::seconds(5)) {
    if (!send_line(line)) {
      return std::nullopt;
    }
    return read_line(timeout);
  }

 private:
  int fd_ = -1;
  std::string buffer_;
};

}  // namespace mrskin::ctl
