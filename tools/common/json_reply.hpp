// Reading JSON text in the tools (the daemon's replies, its statistics file) with nlohmann-json,
// behind plain types: only json_reply.cpp compiles the library (mrskin_tools_json).
#pragma once

#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

namespace mrskin::ctl {

// One JSON text, parsed once; lookups read the members of its top-level object. Text that is
// not a JSON object (garbage from a daemon of another kind) has no members: nothing throws.
class JsonReply {
 public:
  explicit JsonReply(std::string_view text);
  JsonReply(const JsonReply&) = delete;
  JsonReply& operator=(const JsonReply&) = delete;
  JsonReply(JsonReply&& other) noexcept;
  JsonReply& operator=(JsonReply&& other) noexcept;
  ~JsonReply();

  [[nodiscard]] bool is_object() const noexcept;
  // A string member's characters; any other member as its JSON text ("true", "12.5", "null").
  [[nodiscard]] std::optional<std::string> text(std::string_view key) const;
  // A number member; nullopt when absent or not a number (null included).
  [[nodiscard]] std::optional<double> number(std::string_view key) const;
  // An array of numbers, null read as NaN; nullopt when absent or anything else is in it.
  [[nodiscard]] std::optional<std::vector<double>> numbers(std::string_view key) const;
  // The string member key of each object in the array member array_key, in order (the fault
  // reply's log: its "text" lines).
  [[nodiscard]] std::vector<std::string> strings_in_array(std::string_view array_key,
                                                          std::string_view key) const;

 private:
  struct Parsed;
  std::unique_ptr<const Parsed> parsed_;
};

// One member of one JSON text: JsonReply(json).text(key).
std::optional<std::string> json_field(std::string_view json, std::string_view key);

// A nlohmann-json exception's what() without its "[json.exception.parse_error.101] parse error at
// line 1, column 9: " lead-in, for messages that say where themselves.
inline std::string json_error_text(std::string_view what) {
  if (const std::size_t tag = what.find("] ");
      what.starts_with("[json.exception.") && tag != std::string_view::npos) {
    what.remove_prefix(tag + 2);
  }
  if (const std::size_t colon = what.find(": ");
      what.starts_with("parse error") && colon != std::string_view::npos) {
    what.remove_prefix(colon + 2);
  }
  return std::string(what);
}

}  // namespace mrskin::ctl
