// Test support for the tools' tests: a child process with its output in files, and a bounded
// poll. POSIX only; header-only.
#pragma once

#include <fcntl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <csignal>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

namespace mrskin::test {

// A real-time daemon's closed-loop figures are judged only when its loop skipped at most this
// fraction of its periods: on a machine that starves the loop, the skipped time decides them.
inline constexpr double kMaxSkippedFraction = 0.02;

inline std::string slurp(const std::filesystem::path& p) {
  std::ifstream in(p);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

// Runs args[0] with args; stdout to out, stderr to err (the same file when err == out). Killed
// (SIGKILL) if still running when destroyed.
class ChildProcess {
 public:
  ChildProcess(const std::filesystem::path& out, const std::filesystem::path& err,
               std::vector<std::string> args)
      : out_(out), err_(err), pid_(::fork()) {
    if (pid_ == 0) {
      // A loaded machine (ctest -j, sanitizers) may starve a loop for 100 ms, the mock's
      // heartbeat watchdog: scale every session timeout (docs/api.md) unless the caller did.
      ::setenv("MRSKIN_TIME_SCALE", "10", 0);
      const int o = ::open(out.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0600);  // NOLINT(*-vararg)
      const int e =
          err == out ? o : ::open(err.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0600);  // NOLINT(*-vararg)
      ::dup2(o, 1);
      ::dup2(e, 2);
      std::vector<char*> argv;
      argv.reserve(args.size() + 1);
      for (std::string& a : args) {
        argv.push_back(a.data());
      }
      argv.push_back(nullptr);
      ::execv(argv[0], argv.data());
      ::_exit(127);
    }
  }
  ChildProcess(const ChildProcess&) = delete;
  ChildProcess& operator=(const ChildProcess&) = delete;
  ChildProcess(ChildProcess&&) = delete;
  ChildProcess& operator=(ChildProcess&&) = delete;
  ~ChildProcess() {
    if (pid_ > 0 && !exited_) {
      ::kill(pid_, SIGKILL);
      (void)wait(std::chrono::seconds(60));
    }
  }
  void signal(int sig) const { ::kill(pid_, sig); }
  [[nodiscard]] pid_t pid() const noexcept { return pid_; }
  // The exit code (128 + signal when killed), or -1 when it did not exit within timeout.
  int wait(std::chrono::seconds timeout) {
    const auto end = std::chrono::steady_clock::now() + timeout;
    while (std::chrono::steady_clock::now() < end) {
      int status = 0;
      if (::waitpid(pid_, &status, WNOHANG) == pid_) {
        exited_ = true;
        return WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    return -1;
  }
  [[nodiscard]] std::string out() const { return slurp(out_); }
  [[nodiscard]] std::string err() const { return slurp(err_); }

 private:
  std::filesystem::path out_;
  std::filesystem::path err_;
  pid_t pid_ = -1;
  bool exited_ = false;
};

// Polls until pred holds or the bound passes (generous: the suite shares a loaded machine).
inline bool eventually(const std::function<bool()>& pred,
                       std::chrono::seconds bound = std::chrono::seconds(20)) {
  const auto end = std::chrono::steady_clock::now() + bound;
  while (std::chrono::steady_clock::now() < end) {
    if (pred()) {
      return true;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  return pred();
}

}  // namespace mrskin::test
