// make_source(): URI -> source.
#include <array>
#include <charconv>
#include <string>

#include "core.hpp"
#include "mrskin/driver/errors.hpp"
#include "udp_source.hpp"

namespace mrskin::bridge {
namespace {

constexpr std::array<std::string_view, 5> kSchemes{"scene://", "udp://", "replay://", "igtl://",
                                                   "igtl-listen://"};

std::string scheme_list() {
  std::string s;
  for (const std::string_view scheme : kSchemes) {
    s += s.empty() ? "" : ", ";
    s += scheme;
  }
  return s + " (docs/sources.md)";
}

[[noreturn]] void bad(std::string_view uri, const std::string& what) {
  throw InvalidArgument("source '" + std::string(uri) + "': " + what);
}

bool parse_flag(std::string_view uri, std::string_view key, std::string_view value) {
  if (value == "1" || value == "true") {
    return true;
  }
  if (value == "0" || value == "false") {
    return false;
  }
  bad(uri, "bad value '" + std::string(value) + "' for " + std::string(key) + " (0 or 1)");
}

// Applies ?k=v&k=v to options; keys depend on the scheme.
void apply_query(std::string_view uri, std::string_view query, bool replay, SourceOptions& o) {
  while (!query.empty()) {
    const auto amp = query.find('&');
    const std::string_view item = query.substr(0, amp);
    query = amp == std::string_view::npos ? std::string_view{} : query.substr(amp + 1);
    const auto eq = item.find('=');
    if (eq == std::string_view::npos) {
      bad(uri, "bad option '" + std::string(item) + "' (KEY=VALUE)");
    }
    const std::string_view key = item.substr(0, eq);
    const std::string_view value = item.substr(eq + 1);
    if (replay && key == "speed") {
      if (value != "max" && value != "1") {
        bad(uri, "bad speed '" + std::string(value) + "' (max, or 1 for the recorded timing)");
      }
      o.replay_max_speed = value == "max";
    } else if (replay && key == "loop") {
      o.replay_loop = parse_flag(uri, key, value);
    } else if (!replay && key == "queue") {
      std::size_t n = 0;
      const auto [end, ec] = std::from_chars(value.data(), value.data() + value.size(), n);
      if (ec != std::errc{} || end != value.data() + value.size() || n == 0) {
        bad(uri, "bad queue '" + std::string(value) + "' (samples, > 0)");
      }
      o.queue_capacity = n;
    } else {
      bad(uri, "unknown option '" + std::string(key) + "' (" +
                   (replay ? "replay takes speed=max|1 and loop=0|1" : "queue=N") + ")");
    }
  }
}

}  // namespace

std::span<const std::string_view> source_schemes() noexcept { return kSchemes; }

std::unique_ptr<StreamSource> open_stream(std::string_view uri, const SourceOptions& options, Clock* clock) {
  const auto sep = uri.find("://");
  if (sep == std::string_view::npos) {
    bad(uri, "not a URI; sources are " + scheme_list());
  }
  const std::string_view scheme = uri.substr(0, sep);
  std::string_view rest = uri.substr(sep + 3);
  std::string_view query;
  if (const auto q = rest.find('?'); q != std::string_view::npos) {
    query = rest.substr(q + 1);
    rest = rest.substr(0, q);
  }
  SourceOptions o = options;
  if (scheme == "scene") {
    bad(uri, "a scene is not a network or replay stream (make_source() takes scene://NAME)");
  }
  if (scheme == "replay") {
    if (rest.empty()) {
      bad(uri, "missing file (replay://FILE)");
    }
    apply_query(uri, query, true, o);
    return sources::open_replay(std::string(rest), o);
  }
  if (scheme == "udp" || scheme == "igtl" || scheme == "igtl-listen") {
    apply_query(uri, query, false, o);
    const bool client = scheme == "igtl";
    const sources::Endpoint where = sources::parse_endpoint(rest, uri, client, !client);
    if (scheme == "udp") {
      return std::make_unique<sources::UdpSource>(where, o, clock);
    }
    return sources::open_igtl(where, !client, o, clock);
  }
  bad(uri, "unknown scheme '" + std::string(scheme) + "://'; sources are " + scheme_list());
}

std::unique_ptr<SlaveSource> make_source(std::string_view uri, const SourceOptions& options, Clock* clock) {
  if (uri.starts_with("scene://")) {
    return make_scene(uri);
  }
  return open_stream(uri, options, clock);
}

}  // namespace mrskin::bridge
