// mrskinctl's side of mrskin-bridged's control socket: connecting with an actionable error, and
// streaming its grid telemetry (the replies are read with JsonReply, json_reply.hpp).
#pragma once

#include <fmt/format.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <cstring>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "../mrskin-bridged/socket_path.hpp"
#include "exit_codes.hpp"
#include "json_reply.hpp"
#include "line_client.hpp"
#include "mrskin/driver/errors.hpp"

namespace mrskin::ctl {

// The socket to use: --bridge, else the daemon's default.
inline std::string bridge_socket(const std::string& given) {
  return given.empty() ? bridged::default_socket_path() : given;
}

// Throws DeviceNotFound (exit 3) naming the path when no daemon answers there.
inline LineClient connect_bridge(const std::string& path) {
  LineClient c;
  if (!c.connect(path)) {
    const int err = errno;
    throw DeviceNotFound(fmt::format(
        "no mrskin-bridged answers on {} ({}): is mrskin-bridged running? Start it, or give its socket "
        "with --bridge PATH",
        path, std::strerror(err)));  // NOLINT(concurrency-mt-unsafe): one thread
  }
  return c;
}

// SIGINT/SIGTERM while a command streams from the daemon: it stops cleanly (exit 0, files
// closed). Set from the handler, read by the loop.
inline std::atomic<bool> g_stop{false};  // NOLINT(cppcoreguidelines-avoid-non-const-global-variables)
static_assert(std::atomic<bool>::is_always_lock_free);
extern "C" inline void on_stop_signal(int /*signal*/) { g_stop.store(true, std::memory_order_relaxed); }
inline bool stop_requested() noexcept { return g_stop.load(std::memory_order_relaxed); }

class StopSignals {
 public:
  StopSignals() {
    g_stop.store(false);
    struct sigaction sa {};
    sa.sa_handler = &on_stop_signal;  // no SA_RESTART: poll(2) returns and the loop looks
    sigemptyset(&sa.sa_mask);
    (void)::sigaction(SIGINT, &sa, &old_int_);
    (void)::sigaction(SIGTERM, &sa, &old_term_);
  }
  StopSignals(const StopSignals&) = delete;
  StopSignals& operator=(const StopSignals&) = delete;
  StopSignals(StopSignals&&) = delete;
  StopSignals& operator=(StopSignals&&) = delete;
  ~StopSignals() {
    (void)::sigaction(SIGINT, &old_int_, nullptr);
    (void)::sigaction(SIGTERM, &old_term_, nullptr);
  }

 private:
  struct sigaction old_int_ {};
  struct sigaction old_term_ {};
};

// Subscribes to the daemon's grid telemetry every period_ms and hands each line it sends, parsed,
// to on_line until duration_s (0: until SIGINT/SIGTERM). Exit code: 0 ended, 1 the daemon refused,
// closed the socket or went silent (5 s, or three periods); throws DeviceNotFound (exit 3) when
// no daemon answers. `who` names the command in messages.
template <class OnLine>
int stream_bridge_grid(const std::string& path, double period_ms, double duration_s, const char* who,
                       OnLine&& on_line) {
  using namespace std::chrono_literals;
  LineClient c = connect_bridge(path);
  const std::optional<std::string> ack =
      c.request(fmt::format(R"({{"cmd":"telemetry","period_ms":{},"grid":true}})", period_ms), 5s);
  if (!ack) {
    throw Error(
        fmt::format("mrskin-bridged on {} did not answer the telemetry request within 5 s (it closed the "
                    "connection or is busy)",
                    path));
  }
  if (const JsonReply reply(*ack); reply.text("ok") != "true") {
    fmt::print(stderr, "mrskinctl {}: mrskin-bridged on {} refused the grid telemetry: {}\n", who, path,
               reply.text("error").value_or(*ack));
    return tools::kFailure;
  }
  const auto t0 = std::chrono::steady_clock::now();
  const auto end = t0 + std::chrono::microseconds(static_cast<std::int64_t>(duration_s * 1e6));
  // Silence for this long means the daemon is stuck or gone.
  const auto patience = std::max(std::chrono::milliseconds(5000),
                                 std::chrono::milliseconds(static_cast<std::int64_t>(3.0 * period_ms)));
  auto last_event = t0;
  while (!stop_requested()) {
    const auto now = std::chrono::steady_clock::now();
    if (duration_s > 0.0 && now >= end) {
      break;
    }
    auto wait = std::chrono::duration_cast<std::chrono::milliseconds>(duration_s > 0.0 ? end - now : 200ms);
    wait = std::clamp(wait, std::chrono::milliseconds(1), std::chrono::milliseconds(200));
    const auto asked = std::chrono::steady_clock::now();
    const std::optional<std::string> line = c.read_line(wait);
    if (!line) {
      // Nothing long before the wait was up: the daemon closed the socket.
      const bool closed = wait >= 20ms && std::chrono::steady_clock::now() - asked < wait / 2;
      if (closed || std::chrono::steady_clock::now() - last_event > patience) {
        fmt::print(stderr, "mrskinctl {}: mrskin-bridged on {} stopped sending (closed or stuck)\n", who,
                   path);
        return tools::kFailure;
      }
      continue;
    }
    last_event = std::chrono::steady_clock::now();
    on_line(JsonReply(*line));
  }
  (void)c.send_line("stop");
  return tools::kOk;
}

}  // namespace mrskin::ctl
