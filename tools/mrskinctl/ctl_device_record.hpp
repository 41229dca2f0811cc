// The recording format of mrskinctl record / replay / plot (docs/cli.md, "record, replay"): NDJSON,
// one flat object per line. Line 1 is the header, then one line per event, t_s counted from the
// start of the recording (host time):
//   {"format": "mrskinctl-record", "version": 2, "uri": "mock://", "valves": 12, "fluid_cells": 13,
//    "sensors": 12, "sensor_unit": "m", "max_current_a": 0.1, "rendered": "truth"}
//   {"t_s": 0.001, "dir": "tx", "kind": "state", "request": "enable"}
//   {"t_s": 0.004, "dir": "tx", "kind": "currents", "values": [0.01, ...]}          (A, one per valve)
//   {"t_s": 0.004, "dir": "tx", "kind": "targets", "first": 6, "values": [K, D, F, T]}  (N/m, m, N, s)
//   {"t_s": 0.005, "dir": "rx", "kind": "telemetry", "device_time_s": 0.005, "first": 0, "values": [...]}
//   {"t_s": 0.006, "dir": "rx", "kind": "status", "state": "ENABLED", "fault": "none"}
//   {"t_s": 0.010, "dir": "rx", "kind": "cells", "rendered_n": [...], "target_n": [...], "law_n": [...],
//    "floor_n": [...], "ceiling_n": [...], "loaded": [0, 1, ...]}              (N, one per fluid cell)
// Version 2 adds the header's "rendered" (what rendered_n is: "truth" on the mock, "observer" on a
// unit, "none": no cells lines) and the cells lines (through mrskin-bridged); version 1 files read.
// Values are strings, numbers or arrays of numbers; nothing nests. The reader is strict and
// names the line of the first error.
#pragma once

#include <fmt/format.h>

#include <nlohmann/json.hpp>
#include <span>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "json_reply.hpp"
#include "json_text.hpp"
#include "mrskin/driver/errors.hpp"

namespace mrskin::ctl {

inline constexpr std::string_view kRecordFormat = "mrskinctl-record";
inline constexpr int kRecordVersion = 2;

// One line of a recording, parsed with nlohmann-json. Throws InvalidArgument("where: reason")
// when it is not a JSON object of strings, numbers and arrays of numbers, and from the accessors
// for a member that is missing or of another type. No nlohmann exception leaves it.
class RecordLine {
 public:
  RecordLine(std::string_view line, std::string where) : where_(std::move(where)) {
    try {
      object_ = nlohmann::json::parse(line);
    } catch (const nlohmann::json::parse_error& e) {
      fail(fmt::format("{} (column {})", json_error_text(e.what()), e.byte));
    } catch (const nlohmann::json::exception& e) {  // a number out of range
      fail(json_error_text(e.what()));
    }
    if (!object_.is_object()) {
      fail("not an object");
    }
    for (const auto& [key, value] : object_.items()) {
      check_flat(key, value);
    }
  }

  [[nodiscard]] std::string text(std::string_view key) const {
    return get(key, [](const nlohmann::json& v) { return v.is_string(); }).get<std::string>();
  }
  [[nodiscard]] double number(std::string_view key) const {
    return get(key, [](const nlohmann::json& v) { return v.is_number(); }).get<double>();
  }
  [[nodiscard]] std::vector<double> array(std::string_view key) const {
    return get(key, [](const nlohmann::json& v) { return v.is_array(); }).get<std::vector<double>>();
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
  [[noreturn]] void fail(std::string_view why) const {
    throw InvalidArgument(
        fmt::format("{}: {}; each line must be one flat JSON object (docs/cli.md)", where_, why));
  }
  // Only strings, numbers and arrays of numbers: the accessors' get<>() can then not throw.
  void check_flat(const std::string& key, const nlohmann::json& value) const {
    if (value.is_array()) {
      for (const nlohmann::json& item : value) {
        if (item.is_null()) {  // a non-finite value was written as null
          fail(fmt::format(R"("{}": null in a number array (a non-finite value))", key));
        }
        if (!item.is_number()) {
          fail(fmt::format(R"("{}": an array holds numbers only)", key));
        }
      }
    } else if (value.is_null()) {
      fail(fmt::format(R"("{}" is null (a non-finite value))", key));
    } else if (!value.is_string() && !value.is_number()) {
      fail(fmt::format(R"("{}" is not a string, a number or an array of numbers)", key));
    }
  }
  template <class Is>
  [[nodiscard]] const nlohmann::json& get(std::string_view key, Is is) const {
    const auto it = object_.find(key);
    if (it == object_.end()) {
      throw InvalidArgument(fmt::format("{}: missing \"{}\"", where_, key));
    }
    if (!is(*it)) {
      throw InvalidArgument(fmt::format("{}: \"{}\" has the wrong type", where_, key));
    }
    return *it;
  }

  nlohmann::json object_;
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
