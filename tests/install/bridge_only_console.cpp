// A console application linked against mrskin::bridge alone: it carries no simulation
// (library_split.sh checks its DT_NEEDED), and mock:// tells it which library to link.
#include <cstdio>
#include <string>

#include "mrskin/bridge/bridge.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/driver/errors.hpp"

int main() {
  mrskin::SimulatedClock clock;
  // A symbol of the bridge library, so that it is needed.
  const auto scene = mrskin::bridge::make_scene("demo");
  if (scene == nullptr) {
    std::puts("bridge-only console: no demo scene");
    return 1;
  }
  try {
    (void)mrskin::open_device("mock://", clock);
  } catch (const mrskin::InvalidArgument& e) {
    const std::string what = e.what();
    if (what.find("mrskin::sim") != std::string::npos) {
      std::printf("bridge-only console: %s\n", e.what());
      return 0;
    }
    std::printf("bridge-only console: unexpected message: %s\n", e.what());
    return 1;
  }
  std::puts("bridge-only console: mock:// opened without the simulation library");
  return 1;
}
