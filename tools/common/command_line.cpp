// The only tools' file that compiles CLI11 (command_line.hpp says why).
#include "command_line.hpp"

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cstddef>
#include <optional>
#include <string>
#include <utility>
#include <vector>

namespace mrskin::tools {

template <class T>
CliOption& CliOption::range(T lo, T hi) {
  option_->check(CLI::Range(lo, hi));
  return *this;
}
template CliOption& CliOption::range<int>(int, int);
template CliOption& CliOption::range<std::size_t>(std::size_t, std::size_t);
template CliOption& CliOption::range<double>(double, double);

CliOption& CliOption::one_of(std::initializer_list<const char*> values) {
  option_->check(CLI::IsMember(std::vector<std::string>(values.begin(), values.end())));
  return *this;
}

CliOption& CliOption::existing_file() {
  option_->check(CLI::ExistingFile);
  return *this;
}

CliOption& CliOption::check(std::function<std::string(const std::string&)> validate) {
  option_->check(std::move(validate));
  return *this;
}

CliOption& CliOption::transform(const std::function<std::string(std::string)>& rewrite) {
  option_->transform(rewrite);
  return *this;
}

CliOption& CliOption::show_default() {
  option_->capture_default_str();
  return *this;
}

CliOption& CliOption::required() {
  option_->required();
  return *this;
}

CliOption& CliOption::value_optional() {
  option_->expected(0, 1);
  return *this;
}

CliOption& CliOption::excludes(const CliOption& other) {
  option_->excludes(other.option_);
  return *this;
}

CliOption& CliOption::delimiter(char separator) {
  option_->delimiter(separator);
  return *this;
}

bool CliOption::given() const { return option_ != nullptr && option_->count() > 0; }

CliCommand CliCommand::subcommand(const std::string& name, const std::string& help) {
  return CliCommand(*app_->add_subcommand(name, help));
}

template <class T>
CliOption CliCommand::option(const std::string& name, T& into, const std::string& help) {
  return CliOption(app_->add_option(name, into, help));
}
template CliOption CliCommand::option<std::string>(const std::string&, std::string&, const std::string&);
template CliOption CliCommand::option<double>(const std::string&, double&, const std::string&);
template CliOption CliCommand::option<int>(const std::string&, int&, const std::string&);
template CliOption CliCommand::option<std::size_t>(const std::string&, std::size_t&, const std::string&);
template CliOption CliCommand::option<std::optional<double>>(const std::string&, std::optional<double>&,
                                                             const std::string&);
template CliOption CliCommand::option<std::optional<std::size_t>>(const std::string&,
                                                                  std::optional<std::size_t>&,
                                                                  const std::string&);
template CliOption CliCommand::option<std::optional<int>>(const std::string&, std::optional<int>&,
                                                          const std::string&);
template CliOption CliCommand::option<std::optional<std::string>>(const std::string&,
                                                                  std::optional<std::string>&,
                                                                  const std::string&);
template CliOption CliCommand::option<std::vector<std::size_t>>(const std::string&, std::vector<std::size_t>&,
                                                                const std::string&);

CliOption CliCommand::flag(const std::string& name, bool& into, const std::string& help) {
  return CliOption(app_->add_flag(name, into, help));
}

CliOption CliCommand::flag(const std::string& name, std::optional<bool>& into, const std::string& help) {
  return CliOption(app_->add_flag(name, into, help));
}

CliOption CliCommand::find(const std::string& name) const {
  return CliOption(app_->get_option_no_throw(name));
}

CliCommand& CliCommand::footer(const std::string& text) {
  app_->footer(text);
  return *this;
}

CliCommand& CliCommand::callback(std::function<void()> run) {
  app_->callback(std::move(run));
  return *this;
}

CliCommand& CliCommand::require_subcommand(int count) {
  app_->require_subcommand(count);
  return *this;
}

CliCommand& CliCommand::allow_extras() {
  app_->allow_extras();
  return *this;
}

CliCommand& CliCommand::fallthrough() {
  app_->fallthrough();
  return *this;
}

bool CliCommand::parsed() const { return app_->parsed(); }

CliCommand& CliCommand::version_flag(const std::string& name, const std::string& text) {
  app_->set_version_flag(name, text);
  return *this;
}

CliApp::CliApp(const std::string& description) : app_(std::make_unique<CLI::App>(description)) {}

CliApp::~CliApp() = default;

CliParse CliApp::parse(int argc, char** argv) {
  try {
    app_->parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return CliParse{.run = false, .exit_code = app_->exit(e), .message = {}};
  }
  return CliParse{.run = true, .exit_code = 0, .message = {}};
}

CliParse CliApp::parse_quietly(std::vector<std::string> args) {
  std::reverse(args.begin(), args.end());  // CLI11 takes a vector in reverse order
  try {
    app_->parse(args);
  } catch (const CLI::ParseError& e) {
    return CliParse{.run = false, .exit_code = e.get_exit_code(), .message = e.what()};
  }
  return CliParse{.run = true, .exit_code = 0, .message = {}};
}

}  // namespace mrskin::tools
