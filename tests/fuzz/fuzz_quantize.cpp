// libFuzzer target: quantize decoder. Entry logic in fuzz_entry.hpp (shared with the corpus
// replay test). Build with the clang preset; see docs/protocol.md, section "Fuzzing".
#include <cstdio>
#include <cstdlib>

#include "fuzz_entry.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (const char* failure = mrskin::fuzz::quantize_entry(data, size)) {
    std::fprintf(stderr, "invariant broken: %s\n", failure);
    std::abort();
  }
  return 0;
}
