#include "entities.hpp"

#include <algorithm>
#include <cctype>
#include <cstdio>
#include <cstdlib>
#include <mutex>
#include <utility>
#include <vector>

#include "mrskin/driver/errors.hpp"

namespace mrskin::bridge::dds {

Entity& Entity::operator=(Entity&& o) noexcept {
  if (this != &o) {
    reset();
    e_ = o.e_;
    o.e_ = 0;
  }
  return *this;
}

void Entity::reset() noexcept {
  if (e_ > 0) {
    (void)dds_delete(e_);
  }
  e_ = 0;
}

dds_entity_t check(dds_entity_t rc, std::string_view what) {
  if (rc < 0) {
    throw Error("DDS: " + std::string(what) + " failed: " + dds_strretcode(rc));
  }
  return rc;
}

Entity make_participant(int domain) {
  const dds_entity_t p = dds_create_participant(static_cast<dds_domainid_t>(domain), nullptr, nullptr);
  if (p < 0) {
    const char* uri = std::getenv("CYCLONEDDS_URI");
    throw Error("DDS: cannot join domain " + std::to_string(domain) + ": " + dds_strretcode(p) +
                (uri != nullptr
                     ? std::string("; check the Cyclone DDS configuration in CYCLONEDDS_URI (") + uri + ")"
                     : std::string("; set CYCLONEDDS_URI to a configuration that names a network "
                                   "interface (docs/sources.md)")));
  }
  return Entity(p);
}

namespace {

Qos new_qos() {
  Qos q(dds_create_qos());
  if (!q) {
    throw Error("DDS: out of memory creating a QoS");
  }
  return q;
}

}  // namespace

Qos sensor_data_qos() {
  Qos q = new_qos();
  dds_qset_reliability(q.get(), DDS_RELIABILITY_BEST_EFFORT, 0);
  dds_qset_durability(q.get(), DDS_DURABILITY_VOLATILE);
  dds_qset_history(q.get(), DDS_HISTORY_KEEP_LAST, 5);
  return q;
}

Qos default_qos(int depth) {
  Qos q = new_qos();
  // A slow subscriber may hold the publishing thread (never the tick) at most this long.
  dds_qset_reliability(q.get(), DDS_RELIABILITY_RELIABLE, DDS_MSECS(10));
  dds_qset_durability(q.get(), DDS_DURABILITY_VOLATILE);
  dds_qset_history(q.get(), DDS_HISTORY_KEEP_LAST, depth);
  return q;
}

bool valid_ros_name(std::string_view name) noexcept {
  if (name.starts_with('/')) {
    name.remove_prefix(1);
  }
  if (name.empty() || name.size() > 200) {
    return false;
  }
  bool token_start = true;
  for (const char c : name) {
    if (c == '/') {
      if (token_start) {
        return false;  // "//" or a trailing '/'
      }
      token_start = true;
      continue;
    }
    const auto u = static_cast<unsigned char>(c);
    if (!(std::isalnum(u) != 0 || c == '_') || (token_start && std::isdigit(u) != 0)) {
      return false;
    }
    token_start = false;
  }
  return !token_start;
}

std::string absolute_ros_name(std::string_view name, std::string_view what) {
  if (!valid_ros_name(name)) {
    throw InvalidArgument(std::string(what) + " '" + std::string(name) +
                          "' is not a ROS 2 name (tokens of letters, digits and '_', not starting "
                          "with a digit, joined by '/')");
  }
  std::string out = name.starts_with('/') ? std::string() : std::string(1, '/');
  out.append(name);
  return out;
}

std::string dds_topic(std::string_view ros_name) {
  std::string out = ros_name.starts_with('/') ? std::string("rt") : std::string("rt/");
  out.append(ros_name);
  return out;
}

namespace {

struct Watchers {
  std::mutex sink;   // serialises watch/unwatch, so the sink is set and cleared in their order
  std::mutex mutex;  // the list; the only lock the sink's callers take
  std::vector<std::pair<void*, MalformedHook>> list;  // guarded by mutex
};
Watchers& watchers() {
  static Watchers w;
  return w;
}

void log_sink(void* /*userdata*/, const dds_log_data_t* data) {
  const std::string_view message(data->message, data->size);
  constexpr std::string_view kBegin = "deserialization ";
  const std::size_t begin = message.find(kBegin);
  const std::size_t end = message.find(" failed", begin == std::string_view::npos ? 0 : begin);
  if (begin != std::string_view::npos && end != std::string_view::npos) {
    const std::string_view topic_type = message.substr(begin + kBegin.size(), end - begin - kBegin.size());
    const std::string_view topic = topic_type.substr(0, topic_type.rfind('/'));
    Watchers& w = watchers();
    const std::lock_guard<std::mutex> lock(w.mutex);
    for (const auto& [context, hook] : w.list) {
      hook(context, topic);
    }
    return;
  }
  (void)std::fwrite(data->message, 1, data->size, stderr);
}

}  // namespace

void watch_malformed(void* context, MalformedHook hook) {
  Watchers& w = watchers();
  const std::lock_guard<std::mutex> order(w.sink);
  bool first = false;
  {
    const std::lock_guard<std::mutex> lock(w.mutex);
    first = w.list.empty();
    w.list.emplace_back(context, hook);
  }
  if (first) {
    dds_set_log_sink(&log_sink, nullptr);  // without w.mutex: it waits for the sink's callers
  }
}

void unwatch_malformed(void* context) noexcept {
  Watchers& w = watchers();
  const std::lock_guard<std::mutex> order(w.sink);
  bool last = false;
  {
    const std::lock_guard<std::mutex> lock(w.mutex);
    std::erase_if(w.list, [&](const auto& entry) { return entry.first == context; });
    last = w.list.empty();
  }
  if (last) {
    dds_set_log_sink(nullptr, nullptr);  // Cyclone's own sink again
  }
}

}  // namespace mrskin::bridge::dds
