// The recording format of mrskinctl record / replay (docs/cli.md, "record, replay"): NDJSON, one
// flat object per line. Line 1 is the header, then one line per event, t_s counted from the
// start of the recording (host time):
//   {"format": "mrskinctl-record", "version": 1, "uri": "mock://", "valves": 12, "fluid_cells": 13,
//    "sensors": 12, "sensor_unit": "m", "max_current_a": 0.1}
//   {"t_s": 0.001, "dir": "tx", "kind": "state", "request": "enable"}
//   {"t_s": 0.004, "dir": "tx", "kind": "currents", "values": [0.01, ...]}          (A, one per valve)
//   {"t_s": 0.004, "dir": "tx", "kind": "targets", "first": 6, "values": [K, D, F, T]}  (N/m, m, N, s)
//   {"t_s": 0.005, "dir": "rx", "kind": "telemetry", "device_time_s": 0.005, "first": 0, "values": [...]}
//   {"t_s": 0.006, "dir": "rx", "kind": "status", "state": "ENABLED", "fault": "none"}
// Values are strings, numbers or arrays of numbers; nothing nests. The reader is strict and
// names the line of the first error.
#pragma once

#include <fmt/format.h>

#include <cctype>
#include <cstdlib>
#include <map>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "json_text.hpp"
#include "mrskin/driver/errors.hpp"

namespace mrskin::ctl {

inline constexpr std::string_view kRecordFormat = "mrskinctl-record";
inline constexpr int kRecordVersion = 1;

struct RecordValue {
  enum class Type : unsigned char { string, number, array };
  Type type = Type::number;
  std::string text;
  double number = 0.0;
  std::vector<double> array;
};
using RecordObject = std::map<std::string, RecordValue, std::less<>>;

// Parses one line; throws InvalidArgument("where: reason").
class RecordLineParser {
 public:
  RecordLineParser(std::string_view line, std::string where) : s_(line), where_(std::move(where)) {}
  RecordObject parse() {
    RecordObject out;
    skip();
    expect('{');
    skip();
    if (peek() == '}') {
      ++i_;
    } else {
      for (;;) {
        skip();
        std::string key = string();
        skip();
        expect(':');
        skip();
        out[key] = value();
        skip();
        if (peek() == ',') {
          ++i_;
          continue;
        }
        expect('}');
        break;
      }
    }
    skip();
    if (i_ != s_.size()) {
      fail("text after the closing '}'");
    }
    return out;
  }

 private:
  [[noreturn]] void fail(std::string_view why) const {
    throw InvalidArgument(fmt::format(
        "{}: {} (column {}); each line must be one flat JSON object (docs/cli.md)", where_, why, i_ + 1));
  }
  [[nodiscard]] char peek() const { return i_ < s_.size() ? s_[i_] : '\0'; }
  void skip() {
    while (i_ < s_.size() && std::isspace(static_cast<unsigned char>(s_[i_])) != 0) {
      ++i_;
    }
  }
  void expect(char c) {
    if (peek() != c) {
      fail(fmt::format("expected '{}'", c));
    }
    ++i_;
  }
  std::string string() {
    expect('"');
    std::string out;
    while (i_ < s_.size() && s_[i_] != '"') {
      if (s_[i_] == '\\' && i_ + 1 < s_.size()) {
        ++i_;
        const char c = s_[i_];
        out += c == 'n' ? '\n' : c == 't' ? '\t' : c == 'r' ? '\r' : c;
      } else {
        out += s_[i_];
      }
      ++i_;
    }
    expect('"');
    return out;
  }
  double number() {
    const std::size_t start = i_;
    while (i_ < s_.size() && (std::isdigit(static_cast<unsigned char>(s_[i_])) != 0 || s_[i_] == '-' ||
                              s_[i_] == '+' || s_[i_] == '.' || s_[i_] == 'e' || s_[i_] == 'E')) {
      ++i_;
    }
    const std::string text(s_.substr(start, i_ - start));
    char* end = nullptr;
    const double v = std::strtod(text.c_str(), &end);
    if (text.empty() || end != text.c_str() + text.size()) {
      i_ = start;
      fail("expected a number");
    }
    return v;
  }
  RecordValue value() {
    RecordValue v;
    if (peek() == '"') {
      v.type = RecordValue::Type::string;
      v.text = string();
    } else if (peek() == '[') {
      v.type = RecordValue::Type::array;
      ++i_;
      skip();
      if (peek() == ']') {
        ++i_;
        return v;
      }
      for (;;) {
        skip();
        if (s_.substr(i_, 4) == "null") {  // a non-finite value was written as null
          fail("null in a number array (a non-finite value)");
        }
        v.array.push_back(number());
        skip();
        if (peek() == ',') {
          ++i_;
          continue;
        }
        expect(']');
        break;
      }
    } else {
      v.type = RecordValue::Type::number;
      v.number = number();
    }
    return v;
  }

  std::string_view s_;
  std::string where_;
  std::size_t i_ = 0;
};

// Field access with line-numbered errors.
class RecordFields {
 public:
  RecordFields(const RecordObject& o, std::string where) : o_(o), where_(std::move(where)) {}
  [[nodiscard]] const RecordValue& get(std::string_view key, RecordValue::Type type) const {
    const auto it = o_.find(key);
    if (it == o_.end()) {
      throw InvalidArgument(fmt::format("{}: missing \"{}\"", where_, key));
    }
    if (it->second.type != type) {
      throw InvalidArgument(fmt::format("{}: \"{}\" has the wrong type", where_, key));
    }
    return it->second;
  }
  [[nodiscard]] const std::string& text(std::string_view key) const {
    return get(key, RecordValue::Type::string).text;
  }
  [[nodiscard]] double number(std::string_view key) const {
    return get(key, RecordValue::Type::number).number;
  }
  [[nodiscard]] const std::vector<double>& array(std::string_view key) const {
    return get(key, RecordValue::Type::array).array;
  }
  [[nodiscard]] std::size_t index(std::string_view key) const {
    const double v = number(key);
    if (!(v >= 0.0 && v < 1e6 && v == static_cast<double>(static_cast<std::size_t>(v)))) {
      throw InvalidArgument(fmt::format("{}: \"{}\" must be a non-negative integer", where_, key));
    }
    return static_cast<std::size_t>(v);
  }
  [[nodiscard]] const std::string& where() const noexcept { return where_; }

 private:
  const RecordObject& o_;
  std::string where_;
};

inline std::string record_numbers(std::span<const double> values) {
  std::string out = "[";
  for (std::size_t i = 0; i < values.size(); ++i) {
    out += (i == 0 ? "" : ", ") + json_number(values[i]);
  }
  return out + "]";
}

}  // namespace mrskin::ctl
