// The functions meant for the real-time path allocate nothing and throw nothing.
#include <gtest/gtest.h>

#include <atomic>
#include <cstdlib>
#include <new>
#include <string>
#include <vector>

#include "counting_new.hpp"
#include "mrskin/driver/model/device_model.hpp"

namespace {

using namespace mrskin::model;

TEST(ModelRealtime, LoopLawsAllocateNothing) {
  const DeviceModel m(load_profile(std::string(MRSKIN_TEST_PROFILE_DIR) + "/mr-skin-5x5.toml"));
  const std::vector<double> currents(m.layout().valve_count(), 0.05);
  const std::size_t centre = m.fluid_cell_index(2, 2).value;
  const ValveLaw& v = m.valve_law();
  double sink = 0.0;
  const auto before = mrskin::test::allocation_count();
  for (int k = 0; k < 100; ++k) {
    const double q = 1e-9 * (k + 1);
    sink += v.pressure_fast_Pa(q, 30.0).value + v.pressure_exact_Pa(q, 30.0).value +
            v.pressure_wereley_pang_Pa(q, 30.0).value + v.flow_m3_per_s(1e4, 30.0).value;
    sink += m.yield_stress_at_current_Pa(0.001 * k).value;
    sink += m.cell_force(centre, 4e-3, 1e-3 * (k % 7), currents).value.force_N;
    sink += m.cell_force_uniform(centre, 4e-3, -1e-3, 0.05).value.force_N;
    sink += m.envelope(centre, 1e-4 * k, 2e-3).value.force_max_N;
    sink += m.gap_field(0.001 * k).value.yield_stress_Pa;
    CoilState s{};
    sink += coil_step(m.profile().coil, s, 0.05, 1e-3).value.current_A;
  }
  EXPECT_EQ(mrskin::test::allocation_count(), before);
  EXPECT_GT(sink, 0.0);
  static_assert(noexcept(m.cell_force(centre, 0.0, 0.0, currents)));
  static_assert(noexcept(m.envelope(centre, 0.0, 0.0)));
  static_assert(noexcept(v.pressure_fast_Pa(0.0, 0.0)));
  static_assert(noexcept(coil_step(m.profile().coil, CoilState{}, 0.0, 0.0)));
}

}  // namespace
