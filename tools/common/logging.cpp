#include "logging.hpp"

#include <spdlog/pattern_formatter.h>
#include <spdlog/sinks/stdout_sinks.h>
#include <spdlog/spdlog.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cstdlib>
#include <memory>
#include <utility>

namespace mrskin::tools {
namespace {

constexpr std::array<std::pair<std::string_view, spdlog::level::level_enum>, 7> kLevels{{
    {"trace", spdlog::level::trace},
    {"debug", spdlog::level::debug},
    {"info", spdlog::level::info},
    {"warn", spdlog::level::warn},
    {"error", spdlog::level::err},
    {"critical", spdlog::level::critical},
    {"off", spdlog::level::off},
}};

// "%*": the line's syslog priority in sd-daemon's form, "<N>".
class JournalPriority final : public spdlog::custom_flag_formatter {
 public:
  void format(const spdlog::details::log_msg& msg, const std::tm& /*tm*/,
              spdlog::memory_buf_t& dest) override {
    const char* p = "<6>";
    switch (msg.level) {
      case spdlog::level::trace:
      case spdlog::level::debug:
        p = "<7>";
        break;
      case spdlog::level::warn:
        p = "<4>";
        break;
      case spdlog::level::err:
        p = "<3>";
        break;
      case spdlog::level::critical:
        p = "<2>";
        break;
      default:
        break;
    }
    dest.append(p, p + 3);
  }
  [[nodiscard]] std::unique_ptr<custom_flag_formatter> clone() const override {
    return std::make_unique<JournalPriority>();
  }
};

}  // namespace

bool stderr_is_journal() noexcept {
  const char* stream = std::getenv("JOURNAL_STREAM");  // NOLINT(concurrency-mt-unsafe): main, at start
  if (stream == nullptr) {
    return false;
  }
  struct stat st {};
  if (::fstat(STDERR_FILENO, &st) != 0) {
    return false;
  }
  char* end = nullptr;
  const unsigned long long dev = std::strtoull(stream, &end, 10);
  if (end == stream || *end != ':') {
    return false;
  }
  const char* ino_text = end + 1;
  const unsigned long long ino = std::strtoull(ino_text, &end, 10);
  return end != ino_text && *end == '\0' && dev == st.st_dev && ino == st.st_ino;
}

void init_logging(std::string_view tool) {
  auto logger =
      std::make_shared<spdlog::logger>(std::string(tool), std::make_shared<spdlog::sinks::stderr_sink_st>());
  auto formatter = std::make_unique<spdlog::pattern_formatter>();
  if (stderr_is_journal()) {
    formatter->add_flag<JournalPriority>('*').set_pattern("%*%l: %v");
  } else {
    formatter->set_pattern(std::string(tool) + ": %l: %v");
  }
  logger->set_formatter(std::move(formatter));
  logger->set_level(spdlog::level::info);
  spdlog::set_default_logger(std::move(logger));
}

bool is_log_level(std::string_view name) noexcept {
  return std::ranges::any_of(kLevels, [name](const auto& entry) { return entry.first == name; });
}

CliOption add_log_level_option(CliCommand app, std::string& level) {
  return app
      .option("--log-level", level,
              std::string("log messages at this level and above: ") + kLogLevels + " (default info)")
      .check([](const std::string& v) {
        return is_log_level(v) ? std::string() : std::string("must be one of ") + kLogLevels;
      });
}

void set_log_level(std::string_view name) {
  for (const auto& [n, level] : kLevels) {
    if (n == name) {
      spdlog::set_level(level);
      return;
    }
  }
}

}  // namespace mrskin::tools
