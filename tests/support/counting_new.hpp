// Counting replacements of the global allocation functions. Include from exactly one
// source file of a test executable; read mrskin::test::allocation_count().
#pragma once

#include <atomic>
#include <cstdint>
#include <cstdlib>
#include <new>

namespace mrskin::test {
inline std::atomic<std::uint64_t> g_allocations{0};
inline std::uint64_t allocation_count() noexcept { return g_allocations.load(std::memory_order_relaxed); }
}  // namespace mrskin::test

// g++ flags the inlined malloc/free pairing as mismatched; it is the definition of these
// very operators.
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic ignored "-Wmismatched-new-delete"
#endif
void* operator new(std::size_t n) {
  mrskin::test::g_allocations.fetch_add(1, std::memory_order_relaxed);
  if (void* p = std::malloc(n == 0 ? 1 : n)) {
    return p;
  }
  throw std::bad_alloc();
}
void* operator new[](std::size_t n) { return ::operator new(n); }
void operator delete(void* p) noexcept { std::free(p); }
void operator delete[](void* p) noexcept { std::free(p); }
void operator delete(void* p, std::size_t /*n*/) noexcept { std::free(p); }
void operator delete[](void* p, std::size_t /*n*/) noexcept { std::free(p); }
