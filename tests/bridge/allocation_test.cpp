// Counts heap allocations: after start-up, a tick of the whole slice allocates nothing.
#include <gtest/gtest.h>

#include <atomic>
#include <cstdlib>
#include <new>
#include <vector>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/driver/device.hpp"

namespace {
std::atomic<std::uint64_t> g_allocations{0};
}  // namespace

// Replaceable global allocation functions, counting every call. g++ flags the inlined
// malloc/free pairing as mismatched; it is the definition of these very operators.
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic ignored "-Wmismatched-new-delete"
#endif
void* operator new(std::size_t n) {
  g_allocations.fetch_add(1, std::memory_order_relaxed);
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

namespace mrskin::bridge {
namespace {

TEST(Allocation, NoHeapAllocationPerTickAfterStartUp) {
  SimulatedClock clock;
  OpenOptions open;
  open.synchronous_mock = true;
  OpenedDevice dev = open_device("mock://?seed=5", clock, open);
  auto scene = make_scene("demo");
  Bridge loop(*dev.session, *scene);
  loop.set_perf_clock(&clock);
  scene->set_start(clock.now());
  ASSERT_EQ(loop.enable(), ResultCode::ok);
  std::vector<double> finger(dev.mock->layout().fluid_cell_count());
  auto tick = [&] {
    scene->finger(to_seconds(clock.now() - scene->start()), dev.mock->layout(), finger);
    dev.mock->set_finger_indentation(finger);
    dev.mock->step(clock.now());
    (void)loop.step(clock.now());
    clock.advance(std::chrono::milliseconds(1));
  };
  for (int k = 0; k < 100; ++k) {  // start-up
    tick();
  }
  const std::uint64_t before = g_allocations.load();
  for (int k = 0; k < 5000; ++k) {  // press, hold and release: every code path of the tick
    tick();
  }
  EXPECT_EQ(g_allocations.load() - before, 0U);
  EXPECT_EQ(loop.stats().ticks, 5100U);
}

}  // namespace
}  // namespace mrskin::bridge
