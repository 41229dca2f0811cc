// libFuzzer target: udp://'s datagram parser (issue 25). Entry logic in
// fuzz_sources.hpp (shared with the corpus replay test). Build with the clang preset; docs/reliability.md.
#include <cstdio>
#include <cstdlib>

#include "fuzz_sources.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (const char* failure = mrskin::fuzz::udp_entry(data, size)) {
    std::fputs("invariant broken: ", stderr);
    std::fputs(failure, stderr);
    std::fputs("\n", stderr);
    std::abort();
  }
  return 0;
}
