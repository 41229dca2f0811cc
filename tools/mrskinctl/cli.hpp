// mrskinctl's command line: a thin facade over CLI11 so that only cli.cpp and main.cpp include
// CLI11's header. Every file that includes it costs about 12 s of g++ -O3 and 20 s of clang-tidy
// (CLI11 2.1 is header-only), and every command file registers options: behind the facade the
// option types are instantiated once. The calls map one to one onto CLI11's, so the help, the
// parsing and the error messages are CLI11's own.
#pragma once

#include <functional>
#include <initializer_list>
#include <string>

namespace CLI {
class App;
class Option;
}  // namespace CLI

namespace mrskin::ctl {

// One option of a command (CLI::Option). A default-constructed one stands for no option.
class CliOption {
 public:
  CliOption() = default;
  explicit CliOption(CLI::Option* option) : option_(option) {}

  // CLI::Range(lo, hi): instantiated for int, std::size_t and double (cli.cpp).
  template <class T>
  CliOption& range(T lo, T hi);
  CliOption& one_of(std::initializer_list<const char*> values);  // CLI::IsMember
  CliOption& show_default();                                     // capture_default_str()
  CliOption& required();
  CliOption& value_optional();  // expected(0, 1): "--bridge" alone or "--bridge SOCKET"
  CliOption& excludes(const CliOption& other);
  CliOption& delimiter(char separator);

  [[nodiscard]] bool given() const;  // on the command line, with or without a value
  [[nodiscard]] bool exists() const { return option_ != nullptr; }

 private:
  CLI::Option* option_ = nullptr;
};

// A command or subcommand (CLI::App) that options and subcommands are added to.
class CliCommand {
 public:
  explicit CliCommand(CLI::App& app) : app_(&app) {}

  CliCommand subcommand(const std::string& name, const std::string& help);
  // add_option: instantiated in cli.cpp for the types the commands bind (a missing one fails to
  // link, naming it).
  template <class T>
  CliOption option(const std::string& name, T& into, const std::string& help);
  CliOption flag(const std::string& name, bool& into, const std::string& help);
  // get_option_no_throw: exists() is false when the command has no such option.
  [[nodiscard]] CliOption find(const std::string& name) const;

  CliCommand& footer(const std::string& text);
  // Runs after a successful parse, during CLI11's parse (exceptions propagate to main).
  CliCommand& callback(std::function<void()> run);
  CliCommand& require_subcommand(int count);
  CliCommand& allow_extras();

  [[nodiscard]] CLI::App& app() const { return *app_; }

 private:
  CLI::App* app_;
};

}  // namespace mrskin::ctl
