// mrskinctl's side of mrskin-bridged's control socket: connecting with an actionable error, and
// reading the few JSON shapes the daemon sends (flat objects, arrays of numbers, strings).
#pragma once

#include <fmt/format.h>

#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "../mrskin-bridged/socket_path.hpp"
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

// Decodes the JSON string body that json_field() returns (escapes kept): \" \\ \n \t \r \uXXXX
// (ASCII only; other code points become '?').
inline std::string json_unescape(std::string_view s) {
  std::string out;
  out.reserve(s.size());
  for (std::size_t i = 0; i < s.size(); ++i) {
    if (s[i] != '\\' || i + 1 >= s.size()) {
      out += s[i];
      continue;
    }
    const char e = s[++i];
    switch (e) {
      case 'n':
        out += '\n';
        break;
      case 't':
        out += '\t';
        break;
      case 'r':
        out += '\r';
        break;
      case 'u': {
        const std::string hex(s.substr(i + 1, 4));
        const long code = std::strtol(hex.c_str(), nullptr, 16);
        out += code > 0 && code < 0x80 ? static_cast<char>(code) : '?';
        i += std::min<std::size_t>(4, s.size() - i - 1);
        break;
      }
      default:
        out += e;
    }
  }
  return out;
}

// The numbers of a top-level array of numbers ("key":[1,2.5,null]); null -> NaN. nullopt when
// the key is absent or its value is not such an array.
inline std::optional<std::vector<double>> json_numbers_field(std::string_view json, std::string_view key) {
  const std::string pattern = fmt::format(R"("{}":[)", key);
  const std::size_t at = json.find(pattern);
  if (at == std::string_view::npos) {
    return std::nullopt;
  }
  std::vector<double> out;
  std::size_t i = at + pattern.size();
  while (i < json.size() && json[i] != ']') {
    std::size_t end = i;
    while (end < json.size() && json[end] != ',' && json[end] != ']') {
      ++end;
    }
    const std::string item(json.substr(i, end - i));
    if (item == "null") {
      out.push_back(NAN);
    } else {
      char* stop = nullptr;
      const double v = std::strtod(item.c_str(), &stop);
      if (item.empty() || stop != item.c_str() + item.size()) {
        return std::nullopt;  // not an array of numbers
      }
      out.push_back(v);
    }
    i = end < json.size() && json[end] == ',' ? end + 1 : end;
  }
  if (i >= json.size()) {
    return std::nullopt;  // unterminated
  }
  return out;
}

// The values of every string member named key inside the array member array_key, in order:
// the "text" of each record of the fault response's "log".
inline std::vector<std::string> json_strings_in_array(std::string_view json, std::string_view array_key,
                                                      std::string_view key) {
  std::vector<std::string> out;
  const std::string open = fmt::format(R"("{}":[)", array_key);
  const std::size_t at = json.find(open);
  if (at == std::string_view::npos) {
    return out;
  }
  const std::string pattern = fmt::format(R"("{}":")", key);
  std::size_t i = at + open.size();
  for (;;) {
    const std::size_t k = json.find(pattern, i);
    if (k == std::string_view::npos) {
      return out;
    }
    std::size_t end = k + pattern.size();
    while (end < json.size() && json[end] != '"') {
      end += json[end] == '\\' ? 2 : 1;
    }
    if (end >= json.size()) {
      return out;
    }
    out.push_back(json_unescape(json.substr(k + pattern.size(), end - k - pattern.size())));
    i = end + 1;
  }
}

}  // namespace mrskin::ctl
