// make_source(): URI -> source.
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstring>
#include <string>

#include "../dds/entities.hpp"
#include "core.hpp"
#include "mrskin/driver/errors.hpp"
#include "udp_source.hpp"

namespace mrskin::bridge {
namespace {

constexpr std::array<std::string_view, 6> kSchemes{"scene://", "udp://",         "replay://",
                                                   "igtl://",  "igtl-listen://", "dds://"};

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

// An OpenIGTLink device or tool name: 1 to 20 printable characters (the header's field), or *.
std::string device_name(std::string_view uri, std::string_view key, std::string_view value) {
  const bool printable =
      std::all_of(value.begin(), value.end(), [](char c) { return c >= 0x20 && c < 0x7F && c != '&'; });
  if (value.empty() || value.size() > 20 || !printable) {
    bad(uri, "bad " + std::string(key) + " '" + std::string(value) +
                 "' (an OpenIGTLink device name: 1 to 20 printable characters, or * for any)");
  }
  return std::string(value);
}

// ROLL,PITCH,YAW in degrees.
std::array<double, 9> rpy(std::string_view uri, std::string_view value) {
  std::array<double, 3> a{};
  std::string_view rest = value;
  for (std::size_t i = 0; i < 3; ++i) {
    const auto comma = rest.find(',');
    const std::string_view item = rest.substr(0, comma);
    const auto [end, ec] = std::from_chars(item.data(), item.data() + item.size(), a.at(i));
    if (ec != std::errc{} || end != item.data() + item.size() || !std::isfinite(a.at(i)) ||
        std::abs(a.at(i)) > 360.0 || (i < 2) == (comma == std::string_view::npos)) {
      bad(uri, "bad rpy_deg '" + std::string(value) + "' (ROLL,PITCH,YAW in degrees, each within +-360)");
    }
    rest = comma == std::string_view::npos ? std::string_view{} : rest.substr(comma + 1);
  }
  return rotation_from_rpy_deg(a[0], a[1], a[2]);
}

enum class Scheme : unsigned char { udp, replay, igtl, dds };

// 65 s of a 1 kHz stream: far more than the tick ever leaves queued, and a bounded allocation.
constexpr std::size_t kMaxQueue = 65536;

// Applies ?k=v&k=v to options; keys depend on the scheme.
void apply_query(std::string_view uri, std::string_view query, Scheme scheme, SourceOptions& o) {
  const bool replay = scheme == Scheme::replay;
  const bool igtl = scheme == Scheme::igtl;
  const bool dds = scheme == Scheme::dds;
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
      if (ec != std::errc{} || end != value.data() + value.size() || n == 0 || n > kMaxQueue) {
        bad(uri, "bad queue '" + std::string(value) + "' (samples, 1 to " + std::to_string(kMaxQueue) + ")");
      }
      o.queue_capacity = n;
    } else if (igtl && key == "force_device") {
      o.igtl_force_device = device_name(uri, key, value);
    } else if (igtl && key == "pose_device") {
      o.igtl_pose_device = device_name(uri, key, value);
    } else if (igtl && key == "map_device") {
      o.igtl_map_device = device_name(uri, key, value);
    } else if (igtl && key == "pose_tool") {
      o.igtl_pose_tool = device_name(uri, key, value);
    } else if ((igtl || dds) && key == "rpy_deg") {
      o.robot_to_tissue = rpy(uri, value);
    } else if (dds && key == "domain") {
      int d = -1;
      const auto [end, ec] = std::from_chars(value.data(), value.data() + value.size(), d);
      if (ec != std::errc{} || end != value.data() + value.size() || d < 0 || d > dds::kMaxDomain) {
        bad(uri, "bad domain '" + std::string(value) + "' (a DDS domain id, 0 to " +
                     std::to_string(dds::kMaxDomain) + ")");
      }
      o.dds_domain = d;
    } else if (dds && key == "wrench") {
      o.dds_wrench_topic = dds::absolute_ros_name(value, "wrench topic");
    } else if (dds && key == "pose") {
      o.dds_pose_topic = dds::absolute_ros_name(value, "pose topic");
    } else {
      bad(uri, "unknown option '" + std::string(key) + "' (" +
                   (replay ? "replay takes speed=max|1 and loop=0|1"
                    : igtl ? "igtl takes queue=N, force_device, pose_device, map_device, pose_tool and "
                             "rpy_deg=ROLL,PITCH,YAW"
                    : dds ? "dds takes queue=N, domain=N, wrench=TOPIC, pose=TOPIC and rpy_deg=ROLL,PITCH,YAW"
                          : "udp takes queue=N") +
                   ")");
    }
  }
}

}  // namespace

std::span<const std::string_view> source_schemes() noexcept { return kSchemes; }

std::array<double, 9> rotation_from_rpy_deg(double roll_deg, double pitch_deg, double yaw_deg) {
  if (!std::isfinite(roll_deg) || !std::isfinite(pitch_deg) || !std::isfinite(yaw_deg)) {
    throw InvalidArgument("robot frame: roll, pitch and yaw must be finite (degrees)");
  }
  constexpr double kRadPerDeg = 3.14159265358979323846 / 180.0;
  const double cr = std::cos(roll_deg * kRadPerDeg);
  const double sr = std::sin(roll_deg * kRadPerDeg);
  const double cp = std::cos(pitch_deg * kRadPerDeg);
  const double sp = std::sin(pitch_deg * kRadPerDeg);
  const double cy = std::cos(yaw_deg * kRadPerDeg);
  const double sy = std::sin(yaw_deg * kRadPerDeg);
  // Rz(yaw) Ry(pitch) Rx(roll), row-major.
  return {cy * cp,
          cy * sp * sr - sy * cr,
          cy * sp * cr + sy * sr,  //
          sy * cp,
          sy * sp * sr + cy * cr,
          sy * sp * cr - cy * sr,  //
          -sp,
          cp * sr,
          cp * cr};
}

namespace {

// A stream URI taken apart and checked, nothing opened: open_stream opens it, check_source_uri
// stops here.
struct StreamUri {
  std::string_view scheme;
  std::string_view rest;  // after "://", before '?'
  SourceOptions options;
  sources::Endpoint where{};  // udp, igtl, igtl-listen
  std::string wrench_topic;   // dds
  std::string pose_topic;     // dds
};

StreamUri parse_stream_uri(std::string_view uri, const SourceOptions& options) {
  const auto sep = uri.find("://");
  if (sep == std::string_view::npos) {
    bad(uri, "not a URI; sources are " + scheme_list());
  }
  StreamUri u;
  u.scheme = uri.substr(0, sep);
  u.rest = uri.substr(sep + 3);
  u.options = options;
  std::string_view query;
  if (const auto q = u.rest.find('?'); q != std::string_view::npos) {
    query = u.rest.substr(q + 1);
    u.rest = u.rest.substr(0, q);
  }
  if (u.scheme == "scene") {
    bad(uri, "a scene is not a network or replay stream (make_source() takes scene://NAME)");
  }
  if (u.scheme == "replay") {
    if (u.rest.empty()) {
      bad(uri, "missing file (replay://FILE)");
    }
    apply_query(uri, query, Scheme::replay, u.options);
    return u;
  }
  if (u.scheme == "udp" || u.scheme == "igtl" || u.scheme == "igtl-listen") {
    apply_query(uri, query, u.scheme == "udp" ? Scheme::udp : Scheme::igtl, u.options);
    const bool client = u.scheme == "igtl";
    u.where = sources::parse_endpoint(u.rest, uri, client, !client);
    return u;
  }
  if (u.scheme == "dds") {
    apply_query(uri, query, Scheme::dds, u.options);
    // dds://ARM: a CRTK arm's namespace (PSM1, or dvrk/PSM1).
    const std::string arm = u.rest.empty() ? std::string() : dds::absolute_ros_name(u.rest, "arm");
    if (arm.empty() && (u.options.dds_wrench_topic.empty() || u.options.dds_pose_topic.empty())) {
      bad(uri,
          "missing arm (dds://ARM reads /ARM/measured_cf and /ARM/measured_cp; or give wrench= and pose=)");
    }
    u.wrench_topic = u.options.dds_wrench_topic.empty() ? arm + "/measured_cf" : u.options.dds_wrench_topic;
    u.pose_topic = u.options.dds_pose_topic.empty() ? arm + "/measured_cp" : u.options.dds_pose_topic;
    return u;
  }
  bad(uri, "unknown scheme '" + std::string(u.scheme) + "://'; sources are " + scheme_list());
}

}  // namespace

std::unique_ptr<StreamSource> open_stream(std::string_view uri, const SourceOptions& options, Clock* clock) {
  const StreamUri u = parse_stream_uri(uri, options);
  if (u.scheme == "replay") {
    return sources::open_replay(std::string(u.rest), u.options);
  }
  if (u.scheme == "udp") {
    return std::make_unique<sources::UdpSource>(u.where, u.options, clock);
  }
  if (u.scheme == "dds") {
    return sources::open_dds(u.wrench_topic, u.pose_topic, u.options, clock);
  }
  return sources::open_igtl(u.where, u.scheme == "igtl-listen", u.options, clock);
}

void check_source_uri(std::string_view uri, const SourceOptions& options) {
  if (uri.starts_with("scene://")) {
    (void)make_scene(uri);  // a scene is data: building it opens nothing
    return;
  }
  const StreamUri u = parse_stream_uri(uri, options);
  if (u.scheme == "replay" && ::access(std::string(u.rest).c_str(), R_OK) != 0) {
    throw Error(std::string(uri) + ": cannot read " + std::string(u.rest) + ": " + std::strerror(errno));
  }
}

std::unique_ptr<SlaveSource> make_source(std::string_view uri, const SourceOptions& options, Clock* clock) {
  if (uri.starts_with("scene://")) {
    return make_scene(uri);
  }
  return open_stream(uri, options, clock);
}

}  // namespace mrskin::bridge
