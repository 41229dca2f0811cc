// The tools' command lines: a thin facade over CLI11 so that only command_line.cpp includes
// CLI11's header. CLI11 2.1 is header-only: each file that includes it cost about 12 s of g++ -O3,
// 25 s of clang with ASan and 20 s of clang-tidy, in every CI build; behind the facade it compiles
// once. The calls map one to one onto CLI11's, so the help, the parsing and the error messages
// are CLI11's own.
#pragma once

#include <cstdint>
#include <functional>
#include <initializer_list>
#include <memory>
#include <optional>
#include <string>
#include <vector>

namespace CLI {
class App;
class Option;
}  // namespace CLI

namespace mrskin::tools {

// One option of a command (CLI::Option). A default-constructed one stands for no option.
class CliOption {
 public:
  CliOption() = default;
  explicit CliOption(CLI::Option* option) : option_(option) {}

  // CLI::Range(lo, hi): instantiated for int, std::size_t and double (command_line.cpp).
  template <class T>
  CliOption& range(T lo, T hi);
  CliOption& one_of(std::initializer_list<const char*> values);  // CLI::IsMember
  CliOption& existing_file();                                    // CLI::ExistingFile
  // check(): the function returns "" for a good value, else what is wrong with it.
  CliOption& check(std::function<std::string(const std::string&)> validate);
  CliOption& transform(const std::function<std::string(std::string)>& rewrite);
  CliOption& show_default();  // capture_default_str()
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
  // add_option: instantiated in command_line.cpp for the types the tools bind (a missing one
  // fails to link, naming it).
  template <class T>
  CliOption option(const std::string& name, T& into, const std::string& help);
  CliOption flag(const std::string& name, bool& into, const std::string& help);
  CliOption flag(const std::string& name, std::optional<bool>& into, const std::string& help);
  // get_option_no_throw: exists() is false when the command has no such option.
  [[nodiscard]] CliOption find(const std::string& name) const;
  // set_version_flag: the flag prints text and the tool exits 0.
  CliCommand& version_flag(const std::string& name, const std::string& text);

  CliCommand& footer(const std::string& text);
  // Runs after a successful parse, during CLI11's parse (exceptions propagate to the caller).
  CliCommand& callback(std::function<void()> run);
  CliCommand& require_subcommand(int count);
  CliCommand& allow_extras();
  CliCommand& fallthrough();          // the parent's options may follow this command's
  [[nodiscard]] bool parsed() const;  // this (sub)command was on the command line

 private:
  CLI::App* app_;
};

// What parsing a command line ended in.
struct CliParse {
  bool run = false;     // parsed: the tool goes on
  int exit_code = 0;    // CLI11's code when it stopped: 0 after --help or --version
  std::string message;  // CLI11's message for a bad argument ("" otherwise)
};

// A tool's command line (the root CLI::App).
class CliApp {
 public:
  explicit CliApp(const std::string& description);
  ~CliApp();
  CliApp(const CliApp&) = delete;
  CliApp& operator=(const CliApp&) = delete;
  CliApp(CliApp&&) = delete;
  CliApp& operator=(CliApp&&) = delete;

  [[nodiscard]] CliCommand root() const { return CliCommand(*app_); }
  // Parses argv. After --help or --version, or on a bad argument, CLI11 has printed the help, the
  // version or the error (stdout, or stderr for an error) and run is false.
  CliParse parse(int argc, char** argv);
  // Parses args (the program's name left out) without printing anything: for tests.
  CliParse parse_quietly(std::vector<std::string> args);

 private:
  std::unique_ptr<CLI::App> app_;
};

}  // namespace mrskin::tools
