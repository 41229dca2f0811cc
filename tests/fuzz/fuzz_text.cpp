// libFuzzer targets for the parsers of untrusted text (issue 25), one per MRSKIN_FUZZ_TEXT_* macro:
//   control_line  a control-socket request line (bridged::parse_request)
//   config        a mrskin-bridged configuration file (bridged::load_settings)
//   profile       a device profile (model::parse_profile), as a unit or a file supplies it
//   calibration   a calibration (model::parse_calibration), as a unit stores it
//   replay        a stream file (replay://, bridge::open_stream)
//   recording     a recording of mrskinctl record (ctl::read_recording: replay and plot read it)
// The bytes are the text. A parser may refuse it with mrskin::Error (InvalidArgument and
// ConfigError are kinds of it); any other exception, a crash or a sanitizer report is a finding.
// Files are read through a memfd (no disk), by the path /proc/self/fd/N.
#include <sys/mman.h>
#include <unistd.h>

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <string>
#include <string_view>

#include "mrskin/driver/errors.hpp"
#if defined(MRSKIN_FUZZ_TEXT_CONTROL_LINE)
#include "control_server.hpp"
#elif defined(MRSKIN_FUZZ_TEXT_CONFIG)
#include "config.hpp"
#elif defined(MRSKIN_FUZZ_TEXT_PROFILE) || defined(MRSKIN_FUZZ_TEXT_CALIBRATION)
#include "mrskin/driver/model/calibration.hpp"
#include "mrskin/driver/model/profile.hpp"
#elif defined(MRSKIN_FUZZ_TEXT_REPLAY)
#include <chrono>

#include "mrskin/bridge/sources.hpp"
#elif defined(MRSKIN_FUZZ_TEXT_RECORDING)
#include "recording.hpp"
#endif

namespace {

#if defined(MRSKIN_FUZZ_TEXT_CONFIG) || defined(MRSKIN_FUZZ_TEXT_REPLAY) || \
    defined(MRSKIN_FUZZ_TEXT_RECORDING)
// The bytes as a file at a path, for parsers that read paths.
class MemFile {
 public:
  MemFile(const std::uint8_t* data, std::size_t size) : fd_(::memfd_create("fuzz", MFD_CLOEXEC)) {
    if (fd_ < 0 || ::write(fd_, data, size) != static_cast<ssize_t>(size)) {
      std::perror("memfd");
      std::abort();
    }
  }
  MemFile(const MemFile&) = delete;
  MemFile& operator=(const MemFile&) = delete;
  ~MemFile() { ::close(fd_); }
  [[nodiscard]] std::string path() const { return "/proc/self/fd/" + std::to_string(fd_); }

 private:
  int fd_;
};
#endif

void run(const std::uint8_t* data, std::size_t size) {
  const std::string_view text(reinterpret_cast<const char*>(data), size);  // NOLINT: bytes as text
#if defined(MRSKIN_FUZZ_TEXT_CONTROL_LINE)
  mrskin::bridged::ControlRequest r;
  std::string error;
  if (mrskin::bridged::parse_request(text, r, error) == !error.empty()) {
    std::fputs("parse_request: the result and the error disagree\n", stderr);
    std::abort();
  }
#elif defined(MRSKIN_FUZZ_TEXT_CONFIG)
  const MemFile f(data, size);
  const mrskin::bridged::Settings s = mrskin::bridged::load_settings(f.path());
  mrskin::bridged::validate(s, "fuzz");
#elif defined(MRSKIN_FUZZ_TEXT_PROFILE)
  (void)mrskin::model::parse_profile(text, "fuzz");
#elif defined(MRSKIN_FUZZ_TEXT_CALIBRATION)
  (void)mrskin::model::parse_calibration(text, "fuzz", 12, 12);
#elif defined(MRSKIN_FUZZ_TEXT_REPLAY)
  const MemFile f(data, size);
  mrskin::bridge::SourceOptions o;
  o.max_replay_samples = 4096;  // bounded work per input
  auto src = mrskin::bridge::open_stream("replay://" + f.path() + "?speed=max", o);
  mrskin::bridge::SlaveSample sample;
  for (int k = 0; k < 64 && src->latest(mrskin::TimePoint{std::chrono::milliseconds(k)}, sample); ++k) {
  }
  (void)src->stats();
#elif defined(MRSKIN_FUZZ_TEXT_RECORDING)
  const MemFile f(data, size);
  (void)mrskin::ctl::read_recording(f.path());
#endif
  (void)text;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  try {
    run(data, size);
  } catch (const mrskin::Error&) {  // refused with a reason: the expected way out
  } catch (const std::exception& e) {
    std::fprintf(stderr, "unexpected exception: %s\n", e.what());
    std::abort();
  }
  return 0;
}
