#include "json_reply.hpp"

#include <cmath>
#include <nlohmann/json.hpp>

namespace mrskin::ctl {

// Parsed without exceptions (a bad text is `discarded`, not an object), and read only through
// type-checked accessors: no nlohmann exception can leave this file.
struct JsonReply::Parsed {
  nlohmann::json value;

  [[nodiscard]] const nlohmann::json* member(std::string_view key) const {
    if (!value.is_object()) {
      return nullptr;
    }
    const auto it = value.find(key);
    return it == value.end() ? nullptr : &*it;
  }
};

JsonReply::JsonReply(std::string_view text)
    : parsed_(std::make_unique<const Parsed>(Parsed{nlohmann::json::parse(text, nullptr, false)})) {}
JsonReply::JsonReply(JsonReply&&) noexcept = default;
JsonReply& JsonReply::operator=(JsonReply&&) noexcept = default;
JsonReply::~JsonReply() = default;

bool JsonReply::is_object() const noexcept { return parsed_ && parsed_->value.is_object(); }

std::optional<std::string> JsonReply::text(std::string_view key) const {
  const nlohmann::json* v = parsed_ ? parsed_->member(key) : nullptr;
  if (v == nullptr) {
    return std::nullopt;
  }
  if (v->is_string()) {
    return v->get<std::string>();
  }
  return v->dump(-1, ' ', false, nlohmann::json::error_handler_t::replace);
}

std::optional<double> JsonReply::number(std::string_view key) const {
  const nlohmann::json* v = parsed_ ? parsed_->member(key) : nullptr;
  if (v == nullptr || !v->is_number()) {
    return std::nullopt;
  }
  return v->get<double>();
}

std::optional<std::vector<double>> JsonReply::numbers(std::string_view key) const {
  const nlohmann::json* v = parsed_ ? parsed_->member(key) : nullptr;
  if (v == nullptr || !v->is_array()) {
    return std::nullopt;
  }
  std::vector<double> out;
  out.reserve(v->size());
  for (const nlohmann::json& item : *v) {
    if (item.is_null()) {
      out.push_back(NAN);  // the daemon writes a non-finite value as null
    } else if (item.is_number()) {
      out.push_back(item.get<double>());
    } else {
      return std::nullopt;
    }
  }
  return out;
}

std::vector<std::string> JsonReply::strings_in_array(std::string_view array_key, std::string_view key) const {
  std::vector<std::string> out;
  const nlohmann::json* v = parsed_ ? parsed_->member(array_key) : nullptr;
  if (v == nullptr || !v->is_array()) {
    return out;
  }
  for (const nlohmann::json& item : *v) {
    if (!item.is_object()) {
      continue;
    }
    if (const auto it = item.find(key); it != item.end() && it->is_string()) {
      out.push_back(it->get<std::string>());
    }
  }
  return out;
}

std::optional<std::string> json_field(std::string_view json, std::string_view key) {
  return JsonReply(json).text(key);
}

}  // namespace mrskin::ctl
