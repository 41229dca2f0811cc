// The control socket's default path, shared by mrskin-bridged and mrskinctl (header-only, so
// mrskinctl needs none of the daemon's libraries).
#pragma once

#include <fmt/format.h>
#include <unistd.h>

#include <cstdlib>
#include <string>
#include <string_view>

namespace mrskin::bridged {

// $RUNTIME_DIRECTORY/bridged.sock (systemd), else $XDG_RUNTIME_DIR/mrskin/bridged.sock, else
// /tmp/mrskin-UID/bridged.sock.
inline std::string default_socket_path() {
  // NOLINTNEXTLINE(concurrency-mt-unsafe): read at setup, before any thread
  if (const char* rd = std::getenv("RUNTIME_DIRECTORY"); rd != nullptr && rd[0] != '\0') {
    const std::string_view all(rd);  // systemd lists several directories with ':'
    return fmt::format("{}/bridged.sock", all.substr(0, all.find(':')));
  }
  // NOLINTNEXTLINE(concurrency-mt-unsafe): read at setup, before any thread
  if (const char* xdg = std::getenv("XDG_RUNTIME_DIR"); xdg != nullptr && xdg[0] != '\0') {
    return fmt::format("{}/mrskin/bridged.sock", xdg);
  }
  return fmt::format("/tmp/mrskin-{}/bridged.sock", ::getuid());
}

}  // namespace mrskin::bridged
