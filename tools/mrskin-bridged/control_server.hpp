// The control socket: a local UNIX stream socket carrying line-oriented JSON (docs/daemon.md).
// One thread serves every client with poll(); sockets are non-blocking and every buffer is
// bounded, so a slow or silent client is dropped rather than waited for.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <mutex>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include "lease_framing.hpp"
#include "mrskin/driver/errors.hpp"
#include "mrskin/driver/transport.hpp"

namespace mrskin::bridged {

// What the daemon answers with. Called on the control thread; must not block for long.
class ControlBackend {
 public:
  ControlBackend() = default;
  ControlBackend(const ControlBackend&) = delete;
  ControlBackend& operator=(const ControlBackend&) = delete;
  ControlBackend(ControlBackend&&) = delete;
  ControlBackend& operator=(ControlBackend&&) = delete;
  virtual ~ControlBackend() = default;
  // JSON object members (no braces): `"state":"ENABLED","halted":false,...`.
  virtual std::string status_members() = 0;
  virtual std::string fault_members() = 0;
  virtual std::string telemetry_members() = 0;
  // The grid arrays and their context (telemetry with "grid":true).
  virtual std::string grid_members() = 0;
  // How many clients subscribe to the grid now: the tick publishes it only while some do.
  virtual void grid_subscribers(std::size_t n) noexcept = 0;
  // cmd is "enable", "disable" or "estop"; returns what was requested, for the response.
  virtual void request(std::string_view cmd) = 0;
  // The device lease: disable, then hand the device's transport to one client, whose own
  // session drives it through the socket while the tick keeps out. "" on success, else why not.
  virtual std::string lease_begin() = 0;
  virtual Transport* leased_transport() noexcept = 0;  // nullptr unless leased
  virtual void lease_end() noexcept = 0;               // the tick takes the session back (halted)
};

// Another daemon answers on the socket: exit kBusy.
class SocketBusy : public DeviceBusy {
 public:
  using DeviceBusy::DeviceBusy;
};

struct ControlRequest {
  std::string cmd;
  double period_ms = 100.0;  // telemetry
  bool grid = false;         // telemetry: add the per-cell and per-valve arrays
};
// Parses one request line: a JSON object {"cmd": "...", "period_ms": N, "grid": true} or a bare
// command word.
// Returns false with error set when it is malformed.
bool parse_request(std::string_view line, ControlRequest& out, std::string& error);

class ControlServer {
 public:
  static constexpr std::size_t kMaxLine = 4096;  // longer request lines: error, closed
  static constexpr std::size_t kLeaseLengthBytes =
      tools::kLeaseLengthBytes;  // a leased datagram's length prefix
  static constexpr std::size_t kMaxPending =
      std::size_t{256} * 1024;  // unsent bytes before a client is dropped

  // Creates the directory (0700) if missing, refuses a live socket (SocketBusy), removes a stale
  // one, binds with mode 0600 and listens. Throws mrskin::Error with the reason otherwise.
  // idle_timeout_s: a client that sends nothing this long, with no telemetry subscription and no
  // lease, is told so and closed.
  ControlServer(std::string path, int max_clients, double idle_timeout_s = kDefaultIdleTimeout_s);
  static constexpr double kDefaultIdleTimeout_s = 300.0;
  ControlServer(const ControlServer&) = delete;
  ControlServer& operator=(const ControlServer&) = delete;
  ControlServer(ControlServer&&) = delete;
  ControlServer& operator=(ControlServer&&) = delete;
  ~ControlServer();

  // Serves clients from a thread of its own until stop().
  void start(ControlBackend& backend);
  void stop() noexcept;  // joins, closes every client, removes the socket
  [[nodiscard]] const std::string& path() const noexcept { return path_; }
  // Events worth a log line (clients dropped, operator requests), for the main thread to log.
  std::vector<std::string> take_events();

 private:
  struct Client {
    int fd = -1;
    std::string in;
    std::string out;
    double telemetry_ms = 0.0;  // 0: not subscribed
    bool grid = false;          // the subscription includes the grid arrays
    std::chrono::steady_clock::time_point next_telemetry{};
    bool closing = false;  // close once out is flushed
    bool dead = false;
    bool leased = false;  // the device lease: `in` and `out` carry length-prefixed datagrams
    std::chrono::steady_clock::time_point last_heard{};  // accepted, or the last bytes read
    std::string who;  // "pid 1234 (mrskinctl), uid 1000": the peer, from SO_PEERCRED, for the log
  };
  void close_idle(std::chrono::steady_clock::time_point now) noexcept;
  void read_frames(Client& c) noexcept;
  void pump_lease(Client& c) noexcept;
  void run() noexcept;
  void accept_clients() noexcept;
  void read_client(Client& c) noexcept;
  void handle_line(Client& c, std::string_view line);
  void send(Client& c, std::string_view line) noexcept;
  static void flush(Client& c) noexcept;
  void event(std::string text);

  std::string path_;
  std::size_t max_clients_;
  std::chrono::steady_clock::duration idle_timeout_;
  ControlBackend* backend_ = nullptr;
  int listen_fd_ = -1;
  int wake_fd_ = -1;  // eventfd: stop()
  std::vector<Client> clients_;
  std::size_t grid_clients_ = 0;  // as last told to the backend
  std::atomic<bool> stop_{false};
  std::thread thread_;
  std::mutex events_mutex_;  // control thread <-> main thread only; never the tick
  std::vector<std::string> events_;
};

}  // namespace mrskin::bridged
