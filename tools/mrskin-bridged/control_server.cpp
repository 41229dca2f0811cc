#include "control_server.hpp"

#include <fcntl.h>
#include <fmt/format.h>
#include <poll.h>
#include <pthread.h>
#include <sys/eventfd.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <cstring>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>
#include <system_error>

#include "json_reply.hpp"
#include "json_text.hpp"
#include "lease_framing.hpp"

namespace mrskin::bridged {
namespace {

using SteadyClock = std::chrono::steady_clock;

std::string os_error(int err) { return std::system_category().message(err); }

sockaddr_un unix_address(const std::string& path) {
  sockaddr_un addr{};
  addr.sun_family = AF_UNIX;
  if (path.size() >= sizeof(addr.sun_path)) {
    throw InvalidArgument(fmt::format("control socket path {} is longer than {} bytes: choose a shorter one",
                                      path, sizeof(addr.sun_path) - 1));
  }
  std::copy(path.begin(), path.end(), static_cast<char*>(addr.sun_path));
  return addr;
}

// sockaddr_un -> sockaddr: the socket API's own cast.
const sockaddr* as_sockaddr(const sockaddr_un& a) {
  return reinterpret_cast<const sockaddr*>(&a);  // NOLINT(cppcoreguidelines-pro-type-reinterpret-cast)
}

// True when a daemon accepts connections on path.
bool socket_alive(const std::string& path) {
  const sockaddr_un addr = unix_address(path);
  const int fd = ::socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (fd < 0) {
    return false;
  }
  const bool alive = ::connect(fd, as_sockaddr(addr), sizeof(addr)) == 0;
  ::close(fd);
  return alive;
}

void make_private_directory(const std::string& dir) {
  struct stat st {};
  if (::stat(dir.c_str(), &st) != 0) {
    if (::mkdir(dir.c_str(), 0700) != 0 && errno != EEXIST) {
      throw Error(fmt::format("cannot create the control socket directory {}: {}", dir, os_error(errno)));
    }
    return;
  }
  if (!S_ISDIR(st.st_mode)) {
    throw InvalidArgument(fmt::format("{} is not a directory: choose another [control] socket path", dir));
  }
  // A directory of ours that others can enter is tightened; one that is not ours (/tmp, a shared
  // directory) is left alone: the socket's own 0600 mode keeps other users out there.
  if (st.st_uid == ::geteuid() && (st.st_mode & 0077U) != 0 && (st.st_mode & S_ISVTX) == 0) {
    (void)::chmod(dir.c_str(), 0700);
  }
}

// One member of a request object into out; false with error set for an unknown or mistyped one.
bool take_member(const std::string& key, const nlohmann::json& value, ControlRequest& out,
                 std::string& error) {
  if (key == "cmd" && value.is_string()) {
    out.cmd = value.get<std::string>();
  } else if (key == "period_ms" && value.is_number()) {
    out.period_ms = value.get<double>();
  } else if (key == "grid" && value.is_boolean()) {
    out.grid = value.get<bool>();
  } else if (key == "cmd" || key == "period_ms" || key == "grid") {
    error = fmt::format(R"("{}" must be {})", key,
                        key == "cmd"    ? "a string"
                        : key == "grid" ? "true or false"
                                        : "a number");
    return false;
  } else {
    error = R"(unknown field ")" + key + R"(")";
    return false;
  }
  return true;
}

}  // namespace

bool parse_request(std::string_view line, ControlRequest& out, std::string& error) {
  out = ControlRequest{};
  error.clear();
  const std::size_t i = std::min(line.find_first_not_of(" \t\r\n"), line.size());
  if (i < line.size() && line[i] != '{') {  // a bare word: "status"
    std::size_t end = line.size();
    while (end > i && (line[end - 1] == ' ' || line[end - 1] == '\r' || line[end - 1] == '\t')) {
      --end;
    }
    out.cmd = std::string(line.substr(i, end - i));
    if (!std::all_of(out.cmd.begin(), out.cmd.end(), [](char c) { return c >= 'a' && c <= 'z'; })) {
      error = R"(malformed request: expected a JSON object such as {"cmd":"status"} or a command word)";
      return false;
    }
    return true;
  }
  if (i >= line.size()) {
    error = "empty request";
    return false;
  }
  nlohmann::json request;
  try {
    request = nlohmann::json::parse(line);
  } catch (const nlohmann::json::parse_error& e) {
    error = fmt::format("malformed JSON: {} (column {})", ctl::json_error_text(e.what()), e.byte);
    return false;
  } catch (const nlohmann::json::exception& e) {  // a number out of range
    error = "malformed JSON: " + ctl::json_error_text(e.what());
    return false;
  }
  for (const auto& [key, value] : request.items()) {
    if (!take_member(key, value, out, error)) {
      return false;
    }
  }
  if (out.cmd.empty()) {
    error = R"(missing "cmd")";
    return false;
  }
  return true;
}

ControlServer::ControlServer(std::string path, int max_clients, double idle_timeout_s)
    : path_(std::move(path)),
      max_clients_(static_cast<std::size_t>(std::max(1, max_clients))),
      idle_timeout_(std::chrono::duration_cast<SteadyClock::duration>(
          std::chrono::duration<double>(std::clamp(idle_timeout_s, 0.1, 86400.0)))) {
  const sockaddr_un addr = unix_address(path_);
  if (const std::size_t slash = path_.rfind('/'); slash != std::string::npos && slash > 0) {
    make_private_directory(path_.substr(0, slash));
  }
  struct stat st {};
  if (::lstat(path_.c_str(), &st) == 0) {
    if (!S_ISSOCK(st.st_mode)) {
      throw InvalidArgument(
          fmt::format("{} exists and is not a socket: remove it or choose another [control] socket", path_));
    }
    if (socket_alive(path_)) {
      throw SocketBusy(fmt::format(
          "another mrskin-bridged answers on {}: stop it first, or give this one another --socket", path_));
    }
    (void)::unlink(path_.c_str());  // stale: its daemon is gone
  }
  listen_fd_ = ::socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
  if (listen_fd_ < 0) {
    throw Error(fmt::format("cannot create the control socket: {}", os_error(errno)));
  }
  // Created 0600 (umask at bind), so no other user can connect even for an instant.
  const mode_t old_mask = ::umask(0177);
  const int bound = ::bind(listen_fd_, as_sockaddr(addr), sizeof(addr));
  const int bind_errno = errno;
  (void)::umask(old_mask);
  if (bound != 0 || ::listen(listen_fd_, 16) != 0) {
    const int err = bound != 0 ? bind_errno : errno;
    ::close(listen_fd_);
    throw Error(fmt::format("cannot listen on {}: {}", path_, os_error(err)));
  }
  (void)::chmod(path_.c_str(), 0600);
  wake_fd_ = ::eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK);
  if (wake_fd_ < 0) {
    ::close(listen_fd_);
    (void)::unlink(path_.c_str());
    throw Error(fmt::format("eventfd: {}", os_error(errno)));
  }
}

ControlServer::~ControlServer() {
  stop();
  if (wake_fd_ >= 0) {
    ::close(wake_fd_);
  }
}

void ControlServer::start(ControlBackend& backend) {
  if (!thread_.joinable()) {
    backend_ = &backend;
    thread_ = std::thread([this] {
      (void)::pthread_setname_np(::pthread_self(), "mrskin-control");
      run();
    });
  }
}

void ControlServer::stop() noexcept {
  stop_.store(true, std::memory_order_release);
  if (wake_fd_ >= 0) {
    const std::uint64_t one = 1;
    [[maybe_unused]] const ssize_t n = ::write(wake_fd_, &one, sizeof(one));  // full: already woken
  }
  if (thread_.joinable()) {
    thread_.join();
  }
  for (Client& c : clients_) {
    ::close(c.fd);
  }
  clients_.clear();
  if (listen_fd_ >= 0) {
    ::close(listen_fd_);
    listen_fd_ = -1;
    (void)::unlink(path_.c_str());
  }
}

std::vector<std::string> ControlServer::take_events() {
  const std::lock_guard<std::mutex> lock(events_mutex_);
  std::vector<std::string> out;
  out.swap(events_);
  return out;
}

void ControlServer::event(std::string text) {
  const std::lock_guard<std::mutex> lock(events_mutex_);
  if (events_.size() < 256) {  // bounded: the main thread drains it twice a second
    events_.push_back(std::move(text));
  }
}

void ControlServer::run() noexcept {
  std::vector<pollfd> fds;
  while (!stop_.load(std::memory_order_acquire)) {
    fds.clear();
    fds.push_back({wake_fd_, POLLIN, 0});
    fds.push_back({listen_fd_, POLLIN, 0});
    const SteadyClock::time_point now = SteadyClock::now();
    int timeout_ms = 1000;
    for (const Client& c : clients_) {
      fds.push_back({c.fd, static_cast<short>(POLLIN | (c.out.empty() ? 0 : POLLOUT)), 0});
      if (c.leased) {
        timeout_ms = 1;  // the device's datagrams are pumped every millisecond
      }
      if (c.telemetry_ms > 0.0) {
        const auto wait =
            std::chrono::duration_cast<std::chrono::milliseconds>(c.next_telemetry - now).count();
        timeout_ms = std::clamp(static_cast<int>(wait), 0, timeout_ms);
      }
    }
    if (::poll(fds.data(), fds.size(), timeout_ms) < 0 && errno != EINTR) {
      event(fmt::format("control socket: poll failed ({}); control stops", os_error(errno)));
      return;
    }
    if ((fds[1].revents & POLLIN) != 0) {
      accept_clients();
    }
    const std::size_t polled = fds.size() - 2;  // clients accepted just now were not polled
    for (std::size_t k = 0; k < polled && k < clients_.size(); ++k) {
      Client& c = clients_[k];
      const short re = fds[k + 2].revents;
      if ((re & (POLLIN | POLLHUP | POLLERR)) != 0) {
        read_client(c);
      }
      if ((re & POLLOUT) != 0) {
        flush(c);
      }
    }
    for (Client& c : clients_) {
      if (c.leased && !c.dead) {
        pump_lease(c);
      }
    }
    const SteadyClock::time_point t = SteadyClock::now();
    std::string grid;  // built once per round for every grid subscriber due
    for (Client& c : clients_) {
      if (c.telemetry_ms > 0.0 && !c.dead && !c.closing && t >= c.next_telemetry) {
        c.next_telemetry = t + std::chrono::microseconds(static_cast<std::int64_t>(c.telemetry_ms * 1e3));
        try {
          if (c.grid && grid.empty()) {
            grid = backend_->grid_members();
          }
          std::string line = R"({"event":"telemetry",)";
          line += backend_->telemetry_members();
          if (c.grid) {
            line += ',';
            line += grid;
          }
          line += '}';
          send(c, line);
        } catch (...) {
          c.dead = true;  // out of memory: drop this client, keep serving the others
        }
      }
    }
    close_idle(t);
    for (Client& c : clients_) {
      if (c.closing && c.out.empty()) {
        c.dead = true;
      }
      if (c.dead) {
        if (c.leased) {
          c.leased = false;
          backend_->lease_end();
          event("control socket: the device lease ended; the bridge stays halted until enabled");
        }
        ::close(c.fd);
        c.fd = -1;
      }
    }
    std::erase_if(clients_, [](const Client& c) { return c.fd < 0; });
    const auto grid_clients = static_cast<std::size_t>(
        std::count_if(clients_.begin(), clients_.end(), [](const Client& c) { return c.grid; }));
    if (grid_clients != grid_clients_) {
      grid_clients_ = grid_clients;
      backend_->grid_subscribers(grid_clients);
    }
  }
  if (grid_clients_ != 0) {
    grid_clients_ = 0;
    backend_->grid_subscribers(0);
  }
  for (Client& c : clients_) {
    if (c.leased) {
      c.leased = false;
      backend_->lease_end();
    }
  }
}

namespace {

// The peer of a UNIX socket, for the log: its pid, command name and user.
std::string peer_of(int fd) {
  ucred cred{};
  socklen_t len = sizeof(cred);
  if (::getsockopt(fd, SOL_SOCKET, SO_PEERCRED, &cred, &len) != 0) {
    return "a client";
  }
  std::string comm;
  if (std::ifstream in("/proc/" + std::to_string(cred.pid) + "/comm"); in) {
    std::getline(in, comm);
  }
  return comm.empty() ? fmt::format("pid {}, uid {}", cred.pid, cred.uid)
                      : fmt::format("pid {} ({}), uid {}", cred.pid, comm, cred.uid);
}

}  // namespace

void ControlServer::accept_clients() noexcept {
  for (;;) {
    const int fd = ::accept4(listen_fd_, nullptr, nullptr, SOCK_NONBLOCK | SOCK_CLOEXEC);
    if (fd < 0) {
      return;  // EAGAIN: all taken; anything else: the next poll retries
    }
    if (clients_.size() >= max_clients_) {
      const std::string busy = fmt::format(
          "{{\"ok\":false,\"error\":\"too many control clients ({}); try again later\"}}\n", max_clients_);
      [[maybe_unused]] const ssize_t n = ::send(fd, busy.data(), busy.size(), MSG_NOSIGNAL | MSG_DONTWAIT);
      ::close(fd);
      event("control socket: a client was refused (max_clients reached)");
      continue;
    }
    try {
      Client c;
      c.fd = fd;
      c.last_heard = SteadyClock::now();
      c.who = peer_of(fd);
      clients_.push_back(std::move(c));
    } catch (...) {
      ::close(fd);
    }
  }
}

void ControlServer::close_idle(SteadyClock::time_point now) noexcept {
  for (Client& c : clients_) {
    if (c.dead || c.closing || c.leased || c.telemetry_ms > 0.0 || now - c.last_heard < idle_timeout_) {
      continue;
    }
    const double idle_s = std::chrono::duration<double>(idle_timeout_).count();
    try {
      send(c, fmt::format(R"({{"ok":false,"error":"idle for {:g} s: closed, see [control] idle_timeout_s"}})",
                          idle_s));
      event(fmt::format("control socket: a client idle for {:g} s was closed ({})", idle_s, c.who));
    } catch (...) {  // NOLINT(bugprone-empty-catch): closed all the same
    }
    c.closing = true;
  }
}

void ControlServer::read_client(Client& c) noexcept {
  std::array<char, 4096> buf{};
  for (;;) {
    const ssize_t n = ::recv(c.fd, buf.data(), buf.size(), MSG_DONTWAIT);
    if (n == 0) {
      c.dead = true;  // the client closed: an open telemetry subscription ends here
      return;
    }
    if (n < 0) {
      if (errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR) {
        c.dead = true;
      }
      return;
    }
    c.last_heard = SteadyClock::now();
    try {
      c.in.append(buf.data(), static_cast<std::size_t>(n));
      std::size_t nl = 0;
      while (!c.leased && !c.dead && !c.closing && (nl = c.in.find('\n')) != std::string::npos) {
        if (nl > kMaxLine) {
          break;  // too long, whole or not: refused below
        }
        const std::string line = c.in.substr(0, nl);
        c.in.erase(0, nl + 1);
        handle_line(c, line);
      }
      if (c.leased) {
        read_frames(c);
        continue;
      }
      // What is left is one partial line, or a whole one the loop stopped at for its length.
      const std::size_t end = std::min(c.in.find('\n'), c.in.size());
      if (!c.closing && !c.dead && end > kMaxLine) {
        send(c, fmt::format(R"({{"ok":false,"error":"request longer than {} bytes: closed"}})", kMaxLine));
        event(fmt::format("control socket: a client sent a line longer than {} bytes and was closed",
                          kMaxLine));
        c.closing = true;
        c.in.clear();
      }
    } catch (...) {
      c.dead = true;  // out of memory: drop this client, keep serving the others
      return;
    }
  }
}

void ControlServer::handle_line(Client& c, std::string_view line) {
  if (!line.empty() && line.back() == '\r') {
    line.remove_suffix(1);
  }
  if (line.find_first_not_of(" \t") == std::string_view::npos) {
    return;  // blank lines are ignored
  }
  ControlRequest r;
  std::string error;
  if (!parse_request(line, r, error)) {
    send(c, fmt::format(R"({{"ok":false,"error":"{}"}})", ctl::json_escape(error)));
    return;
  }
  const std::string cmd = ctl::json_escape(r.cmd);
  if (r.cmd == "status") {
    send(c, R"({"ok":true,"cmd":"status",)" + backend_->status_members() + "}");
  } else if (r.cmd == "enable" || r.cmd == "disable" || r.cmd == "estop") {
    backend_->request(r.cmd);
    event(fmt::format("control socket: {} requested by {}", r.cmd, c.who));
    send(c, fmt::format(R"({{"ok":true,"cmd":"{}","note":"acted on at the next tick"}})", cmd));
  } else if (r.cmd == "fault") {
    send(c, R"({"ok":true,"cmd":"fault",)" + backend_->fault_members() + "}");
  } else if (r.cmd == "telemetry") {
    if (!(r.period_ms >= 10.0 && r.period_ms <= 60000.0)) {
      send(c, R"({"ok":false,"cmd":"telemetry","error":"period_ms must be 10 to 60000"})");
      return;
    }
    c.telemetry_ms = r.period_ms;
    c.grid = r.grid;
    c.next_telemetry = SteadyClock::now();
    if (r.grid) {  // the round's end tells the tick; 20 ms lets it publish a first snapshot
      c.next_telemetry += std::chrono::milliseconds(20);
    }
    send(c, fmt::format(R"({{"ok":true,"cmd":"telemetry","period_ms":{},"grid":{}}})",
                        ctl::json_number(r.period_ms), r.grid));
  } else if (r.cmd == "lease") {
    if (std::any_of(clients_.begin(), clients_.end(), [](const Client& o) { return o.leased; })) {
      send(c, R"({"ok":false,"cmd":"lease","error":"another client holds the device lease"})");
      return;
    }
    const std::string why = backend_->lease_begin();
    if (!why.empty()) {
      send(c, fmt::format(R"({{"ok":false,"cmd":"lease","error":"{}"}})", ctl::json_escape(why)));
      return;
    }
    c.telemetry_ms = 0.0;
    c.grid = false;
    // The bus the device sits on, so that the lessee's session fits its traffic to it.
    std::string bus;
    if (const Transport* t = backend_->leased_transport(); t != nullptr) {
      if (const std::optional<protocol::BusSpec> b = t->bus()) {
        bus = fmt::format(
            R"(,"bus":"{}","bus_usb_interval_s":{},"bus_usb_reports_per_interval":{},"bus_usb_report_bytes":{},)"
            R"("bus_nominal_bitrate_bit_per_s":{},"bus_data_bitrate_bit_per_s":{})",
            protocol::to_string(b->kind), ctl::json_number(b->usb.interval_s), b->usb.reports_per_interval,
            b->usb.report_bytes, ctl::json_number(b->nominal_bitrate_bit_per_s),
            ctl::json_number(b->data_bitrate_bit_per_s));
      }
    }
    send(c, fmt::format(R"({{"ok":true,"cmd":"lease","framing":"{}"{}}})", tools::kLeaseFraming, bus));
    c.leased = true;
    event(fmt::format("control socket: the device is leased to {} (bridge halted)", c.who));
  } else if (r.cmd == "stop") {
    c.telemetry_ms = 0.0;
    c.grid = false;
    send(c, R"({"ok":true,"cmd":"stop"})");
  } else if (r.cmd == "help") {
    send(
        c,
        R"({"ok":true,"cmd":"help","commands":{)"
        R"("status":"state, fault, halted, ticks, live error, stiffness, stream, rate, device, uptime",)"
        R"("enable":"leave a disable, an e-stop or a latched fault",)"
        R"("disable":"release every valve and disable the device",)"
        R"("estop":"release every valve within one tick and e-stop the device",)"
        R"("fault":"fault cause and the decoded ring log frozen at the fault",)"
        "\"telemetry\":\"{\\\"cmd\\\":\\\"telemetry\\\",\\\"period_ms\\\":N[,\\\"grid\\\":true]}: one line "
        R"(every N ms until stop; grid adds per-cell force, displacement, target and per-valve current, )"
        R"(coil temperature",)"
        R"("stop":"end a telemetry subscription",)"
        R"("lease":"disable, then this connection carries the device's datagrams (u16 LE length + bytes) until it )"
        R"(closes; the bridge stays halted after",)"
        R"("help":"this"}})");
  } else {
    send(c, fmt::format(R"({{"ok":false,"cmd":"{}","error":"unknown command; send help"}})", cmd));
  }
}

// Leased: each datagram is its length (u16, little-endian, 1..kMaxDatagramBytes: a high-speed
// unit's reports reach 1024 bytes) then its bytes, both ways. A zero or oversized length is a
// broken client: it loses the lease.
void ControlServer::read_frames(Client& c) noexcept {
  Transport* t = backend_->leased_transport();
  std::size_t at = 0;
  while (t != nullptr && c.in.size() - at >= kLeaseLengthBytes) {
    const std::size_t length = static_cast<std::uint8_t>(c.in[at]) |
                               (static_cast<std::size_t>(static_cast<std::uint8_t>(c.in[at + 1])) << 8U);
    if (length == 0 || length > kMaxDatagramBytes) {
      c.dead = true;
      return;
    }
    if (c.in.size() - at < kLeaseLengthBytes + length) {
      break;
    }
    const auto* bytes =
        reinterpret_cast<const std::uint8_t*>(c.in.data() + at + kLeaseLengthBytes);  // NOLINT
    (void)t->send(std::span<const std::uint8_t>(bytes, length));  // a full queue drops it, as a bus would
    at += kLeaseLengthBytes + length;
  }
  c.in.erase(0, at);
}

void ControlServer::pump_lease(Client& c) noexcept {
  Transport* t = backend_->leased_transport();
  Datagram d;
  while (t != nullptr && !c.dead && t->receive(d) == ResultCode::ok) {
    try {
      c.out.push_back(static_cast<char>(d.length & 0xFFU));
      c.out.push_back(static_cast<char>(d.length >> 8U));
      c.out.append(reinterpret_cast<const char*>(d.bytes.data()), d.length);  // NOLINT
    } catch (...) {
      c.dead = true;
      return;
    }
    if (c.out.size() > kMaxPending) {
      c.dead = true;  // it does not read: end the lease rather than buffer without bound
      return;
    }
  }
  flush(c);
}

void ControlServer::send(Client& c, std::string_view line) noexcept {
  if (c.dead) {
    return;
  }
  if (c.out.size() + line.size() + 1 > kMaxPending) {
    c.dead = true;  // it does not read: drop it rather than buffer without bound
    event("control socket: a client that did not read its replies was dropped");
    return;
  }
  try {
    c.out.append(line);
    c.out += '\n';
  } catch (...) {
    c.dead = true;
    return;
  }
  flush(c);
}

void ControlServer::flush(Client& c) noexcept {
  while (!c.out.empty() && !c.dead) {
    const ssize_t n = ::send(c.fd, c.out.data(), c.out.size(), MSG_NOSIGNAL | MSG_DONTWAIT);
    if (n < 0) {
      if (errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR) {
        c.dead = true;
      }
      return;
    }
    c.out.erase(0, static_cast<std::size_t>(n));
  }
}

}  // namespace mrskin::bridged
