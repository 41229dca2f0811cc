// The C++ side of tests/python/test_bridge.py: a scene on the simulated clock through the C++
// tests' rig, its statistics as JSON on stdout.
//   python_scene_stats SCENE SECONDS DEVICE_URI
#include <cstdlib>
#include <exception>
#include <iostream>
#include <string>

#include "mrskin/bridge/stats.hpp"
#include "scene_rig.hpp"

int main(int argc, char** argv) {
  if (argc != 4) {
    std::cerr << "usage: python_scene_stats SCENE SECONDS DEVICE_URI\n";
    return 2;
  }
  try {
    const mrskin::bridge::test::SceneRun run =
        mrskin::bridge::test::run_scene(argv[1], std::strtod(argv[2], nullptr), argv[3]);
    std::cout << mrskin::bridge::to_json(run.stats, 1e-3);
    return 0;
  } catch (const std::exception& e) {
    std::cerr << "python_scene_stats: " << e.what() << "\n";
    return 1;
  }
}
