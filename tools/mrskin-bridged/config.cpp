#include "config.hpp"

#include <fmt/format.h>
#include <toml++/toml.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <initializer_list>
#include <numbers>
#include <string_view>

#include "logging.hpp"
#include "mrskin/bridge/loop.hpp"
#include "mrskin/bridge/ros2_topics.hpp"
#include "mrskin/bridge/sources.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/driver/model/profile.hpp"
#include "mrskin/sim/open_mock.hpp"

namespace mrskin::bridged {
namespace {

class Reader {
 public:
  explicit Reader(std::string path) : path_(std::move(path)) {}

  [[noreturn]] void fail(const toml::node& n, std::string_view key, std::string_view what) const {
    throw ConfigError(fmt::format("{}:{}: {}: {}", path_, n.source().begin.line, key, what));
  }

  void check_keys(const toml::table& t, std::string_view section,
                  std::initializer_list<std::string_view> known) const {
    for (auto&& [k, v] : t) {
      bool ok = false;
      for (const std::string_view name : known) {
        ok = ok || k.str() == name;
      }
      if (!ok) {
        std::string names;
        for (const std::string_view name : known) {
          names += fmt::format("{}{}", names.empty() ? "" : ", ", name);
        }
        fail(v, full(section, k.str()), fmt::format("unknown key (known here: {})", names));
      }
    }
  }

  void get(const toml::table& t, std::string_view section, std::string_view key, double& out) const {
    if (const toml::node* n = t.get(key)) {
      const std::optional<double> v = n->is_number() ? n->value<double>() : std::nullopt;
      if (!v || !std::isfinite(*v)) {
        fail(*n, full(section, key), "expected a finite number");
      }
      out = *v;
    }
  }
  void get(const toml::table& t, std::string_view section, std::string_view key, int& out) const {
    if (const toml::node* n = t.get(key)) {
      const auto* v = n->as_integer();
      if (v == nullptr || v->get() < -1'000'000 || v->get() > 1'000'000) {
        fail(*n, full(section, key), "expected an integer");
      }
      out = static_cast<int>(v->get());
    }
  }
  void get(const toml::table& t, std::string_view section, std::string_view key, bool& out) const {
    if (const toml::node* n = t.get(key)) {
      const auto* v = n->as_boolean();
      if (v == nullptr) {
        fail(*n, full(section, key), "expected true or false");
      }
      out = v->get();
    }
  }
  void get(const toml::table& t, std::string_view section, std::string_view key, std::string& out) const {
    if (const toml::node* n = t.get(key)) {
      const auto* v = n->as_string();
      if (v == nullptr) {
        fail(*n, full(section, key), "expected a string");
      }
      out = v->get();
    }
  }
  void get(const toml::table& t, std::string_view section, std::string_view key,
           std::array<double, 3>& out) const {
    if (const toml::node* n = t.get(key)) {
      const auto* a = n->as_array();
      if (a == nullptr || a->size() != 3) {
        fail(*n, full(section, key), "expected an array of 3 numbers");
      }
      for (std::size_t i = 0; i < 3; ++i) {
        const std::optional<double> v = a->get(i)->is_number() ? a->get(i)->value<double>() : std::nullopt;
        if (!v || !std::isfinite(*v)) {
          fail(*n, full(section, key), "expected an array of 3 finite numbers");
        }
        out.at(i) = *v;
      }
    }
  }
  // An OpenIGTLink device or tool name: 1 to 20 printable characters, or * for any.
  void get_name(const toml::table& t, std::string_view section, std::string_view key,
                std::string& out) const {
    get(t, section, key, out);
    const toml::node* n = t.get(key);
    const bool printable = std::all_of(out.begin(), out.end(), [](char c) { return c >= 0x20 && c < 0x7F; });
    if (n != nullptr && (out.empty() || out.size() > 20 || !printable)) {
      fail(*n, full(section, key),
           "expected an OpenIGTLink device name (1 to 20 printable characters, or *)");
    }
  }
  // A number that must satisfy ok(), else the error names the range.
  template <class T, class Ok>
  void get_checked(const toml::table& t, std::string_view section, std::string_view key, T& out, Ok ok,
                   std::string_view range) const {
    get(t, section, key, out);
    if (const toml::node* n = t.get(key); n != nullptr && !ok(out)) {
      fail(*n, full(section, key), fmt::format("{} is out of range ({})", out, range));
    }
  }
  const toml::table* section(const toml::table& root, std::string_view name) const {
    const toml::node* n = root.get(name);
    if (n == nullptr) {
      return nullptr;
    }
    if (!n->is_table()) {
      fail(*n, name, "expected a table ([" + std::string(name) + "])");
    }
    return n->as_table();
  }

 private:
  static std::string full(std::string_view section, std::string_view key) {
    return section.empty() ? std::string(key) : fmt::format("{}.{}", section, key);
  }
  std::string path_;
};

bool positive(double v) { return v > 0.0; }
// Three years: far from the clock's int64 nanoseconds (292 years), which a larger value overflowed.
constexpr double kMaxDuration_s = 1e8;
bool non_negative(double v) { return v >= 0.0; }

}  // namespace

Settings load_settings(const std::string& path) {
  toml::table root;
  try {
    root = toml::parse_file(path);
  } catch (const toml::parse_error& e) {
    if (e.source().begin.line == 0) {  // no position: the file could not be read
      throw ConfigError(fmt::format("{}: cannot read the configuration: {}", path, e.description()));
    }
    throw ConfigError(fmt::format("{}:{}: {}", path, e.source().begin.line, e.description()));
  }
  Settings s;
  const Reader r(path);
  r.check_keys(root, "",
               {"device", "source", "rate_hz", "duration_s", "stats_json", "record", "quiet", "log_level",
                "device_lost_s", "mapping", "stream", "bridge", "topics", "control"});
  r.get(root, "", "device", s.device);
  r.get(root, "", "source", s.source);
  r.get_checked(
      root, "", "rate_hz", s.rate_hz, [](double v) { return v >= 1.0 && v <= 20000.0; }, "1 to 20000 Hz");
  s.rate_given = root.contains("rate_hz");
  r.get_checked(
      root, "", "duration_s", s.duration_s, [](double v) { return v >= 0.0 && v <= kMaxDuration_s; },
      "0 to 1e8 s; 0 runs until a signal");
  r.get(root, "", "stats_json", s.stats_json);
  r.get(root, "", "record", s.record);
  r.get(root, "", "quiet", s.quiet);
  r.get(root, "", "log_level", s.log_level);
  r.get_checked(root, "", "device_lost_s", s.device_lost_s, positive, "> 0 s");
  if (const toml::table* m = r.section(root, "mapping")) {
    r.check_keys(*m, "mapping",
                 {"origin_x_m", "origin_y_m", "cells_per_m", "rotation_deg", "mirror_x", "mirror_y"});
    r.get(*m, "mapping", "origin_x_m", s.mapping.origin_x_m);
    r.get(*m, "mapping", "origin_y_m", s.mapping.origin_y_m);
    r.get_checked(*m, "mapping", "cells_per_m", s.mapping.cells_per_m, positive, "> 0");
    double rotation_deg = s.mapping.rotation_rad * 180.0 / std::numbers::pi;
    r.get(*m, "mapping", "rotation_deg", rotation_deg);
    s.mapping.rotation_rad = rotation_deg * std::numbers::pi / 180.0;
    r.get(*m, "mapping", "mirror_x", s.mapping.mirror_x);
    r.get(*m, "mapping", "mirror_y", s.mapping.mirror_y);
  }
  if (const toml::table* src = r.section(root, "stream")) {
    r.check_keys(
        *src, "stream",
        {"force_device", "pose_device", "map_device", "pose_tool", "robot_rpy_deg", "robot_origin_m"});
    r.get_name(*src, "stream", "force_device", s.force_device);
    r.get_name(*src, "stream", "pose_device", s.pose_device);
    r.get_name(*src, "stream", "map_device", s.map_device);
    r.get_name(*src, "stream", "pose_tool", s.pose_tool);
    r.get(*src, "stream", "robot_rpy_deg", s.robot_rpy_deg);
    r.get(*src, "stream", "robot_origin_m", s.robot_origin_m);
    for (const double a : s.robot_rpy_deg) {
      if (std::abs(a) > 360.0) {
        r.fail(*src->get("robot_rpy_deg"), "stream.robot_rpy_deg", "each angle within +-360 degrees");
      }
    }
    for (const double x : s.robot_origin_m) {
      if (std::abs(x) > 10.0) {
        r.fail(*src->get("robot_origin_m"), "stream.robot_origin_m", "each coordinate within +-10 m");
      }
    }
  }
  if (const toml::table* b = r.section(root, "bridge")) {
    r.check_keys(*b, "bridge",
                 {"feedback_gain_per_s", "footprint_cells", "resend_period_s", "realtime", "rt_priority",
                  "cpu", "stale_hold_s", "stale_fade_s"});
    r.get_checked(*b, "bridge", "feedback_gain_per_s", s.feedback_gain_per_s, non_negative, ">= 0");
    r.get_checked(*b, "bridge", "footprint_cells", s.footprint_cells, positive, "> 0");
    r.get_checked(*b, "bridge", "resend_period_s", s.resend_period_s, positive, "> 0 s");
    r.get(*b, "bridge", "realtime", s.realtime);
    r.get_checked(
        *b, "bridge", "rt_priority", s.rt_priority, [](int v) { return v >= 1 && v <= 99; }, "1 to 99");
    r.get_checked(
        *b, "bridge", "cpu", s.cpu, [](int v) { return bridge::cpu_allowed(v); },
        "-1 (not pinned) or a CPU this process may run on (" + bridge::allowed_cpus() + ")");
    r.get_checked(
        *b, "bridge", "stale_hold_s", s.stale_hold_s, [](double v) { return v >= 0.0 && v <= 10.0; },
        "0 to 10 s: the stream watchdog must act");
    r.get_checked(
        *b, "bridge", "stale_fade_s", s.stale_fade_s, [](double v) { return v > 0.0 && v <= 10.0; },
        "above 0, at most 10 s");
  }
  if (const toml::table* t = r.section(root, "topics")) {
    r.check_keys(*t, "topics", {"namespace", "rate_hz", "domain"});
    r.get(*t, "topics", "namespace", s.topics_namespace);
    r.get_checked(
        *t, "topics", "rate_hz", s.topics_rate_hz, [](double v) { return v >= 1.0 && v <= 100.0; },
        "1 to 100 Hz (the tick hands its arrays over every 10 ms)");
    r.get_checked(
        *t, "topics", "domain", s.topics_domain, [](int v) { return v >= 0 && v <= 232; }, "0 to 232");
  }
  if (const toml::table* c = r.section(root, "control")) {
    r.check_keys(*c, "control", {"socket", "max_clients", "idle_timeout_s"});
    r.get(*c, "control", "socket", s.socket);
    r.get_checked(
        *c, "control", "max_clients", s.max_clients, [](int v) { return v >= 1 && v <= 64; }, "1 to 64");
    r.get_checked(
        *c, "control", "idle_timeout_s", s.idle_timeout_s, [](double v) { return v >= 1.0 && v <= 86400.0; },
        "1 to 86400 s");
  }
  return s;
}

void check_uris(const Settings& s) {
  if (s.device.starts_with("mock://")) {
    (void)model::load_profile_with_text(sim::parse_mock_uri(s.device).profile);
  } else {
    check_device_uri(s.device);
  }
  bridge::check_source_uri(s.source);
}

void validate(const Settings& s, const std::string& origin) {
  const auto bad = [&](std::string_view key, std::string_view what) {
    throw ConfigError(fmt::format("{}: {}: {}", origin, key, what));
  };
  if (!(s.rate_hz >= 1.0 && s.rate_hz <= 20000.0)) {
    bad("rate", "out of range (1 to 20000 Hz)");
  }
  if (!(s.duration_s >= 0.0 && s.duration_s <= kMaxDuration_s)) {
    bad("duration", "must be 0 to 1e8 s (0 runs until a signal)");
  }
  if (!bridge::cpu_allowed(s.cpu)) {
    bad("cpu", fmt::format("{} is not a CPU this process may run on (allowed: {}); -1: not pinned", s.cpu,
                           bridge::allowed_cpus()));
  }
  if (s.device.empty()) {
    bad("device", "empty device URI");
  }
  if (!tools::is_log_level(s.log_level)) {
    bad("log_level", fmt::format("\"{}\" is not a level: use {}", s.log_level, tools::kLogLevels));
  }
  if (s.source.empty()) {
    bad("source", "empty source URI");
  }
  if (!s.mapping.valid()) {
    bad("mapping", "origin, rotation and a positive cells_per_m must be finite");
  }
  if (!s.topics_namespace.empty() && !bridge::valid_ros_name(s.topics_namespace)) {
    bad("topics namespace", "'" + s.topics_namespace +
                                "' is not a ROS 2 name (tokens of letters, digits and '_', not starting with "
                                "a digit, joined by '/')");
  }
}

void apply(const Overrides& o, Settings& s) {
  s.device = o.device.value_or(s.device);
  s.source = o.source.value_or(s.source);
  s.rate_hz = o.rate_hz.value_or(s.rate_hz);
  s.rate_given = s.rate_given || o.rate_hz.has_value();
  s.cpu = o.cpu.value_or(s.cpu);
  s.duration_s = o.duration_s.value_or(s.duration_s);
  s.stats_json = o.stats_json.value_or(s.stats_json);
  s.record = o.record.value_or(s.record);
  s.quiet = o.quiet.value_or(s.quiet);
  s.log_level = o.log_level.value_or(s.log_level);
  s.socket = o.socket.value_or(s.socket);
  s.topics_namespace = o.topics_namespace.value_or(s.topics_namespace);
}

bridge::BridgeOptions bridge_options(const Settings& s) {
  bridge::BridgeOptions o;
  bridge::apply_tuning(bridge_tuning(s), o);
  return o;
}

bridge::BridgeTuning bridge_tuning(const Settings& s) {
  bridge::BridgeTuning t;
  t.rate_hz = s.rate_hz;
  t.feedback_gain_per_s = s.feedback_gain_per_s;
  t.footprint_cells = s.footprint_cells;
  t.resend_period_s = s.resend_period_s;
  t.mapping = s.mapping;
  t.stale_hold_s = s.stale_hold_s;
  t.stale_fade_s = s.stale_fade_s;
  t.realtime = s.realtime;
  t.rt_priority = s.rt_priority;
  t.loop_cpu = s.cpu;
  return t;
}

bridge::SourceOptions source_options(const Settings& s) {
  bridge::SourceOptions o;
  o.igtl_force_device = s.force_device;
  o.igtl_pose_device = s.pose_device;
  o.igtl_map_device = s.map_device;
  o.igtl_pose_tool = s.pose_tool;
  o.robot_to_tissue =
      bridge::rotation_from_rpy_deg(s.robot_rpy_deg[0], s.robot_rpy_deg[1], s.robot_rpy_deg[2]);
  o.robot_origin_m = s.robot_origin_m;
  return o;
}

bool same_source_options(const Settings& a, const Settings& b) noexcept {
  return a.force_device == b.force_device && a.pose_device == b.pose_device && a.map_device == b.map_device &&
         a.pose_tool == b.pose_tool && a.robot_rpy_deg == b.robot_rpy_deg &&
         a.robot_origin_m == b.robot_origin_m;
}

}  // namespace mrskin::bridged
