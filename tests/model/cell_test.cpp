// Contact patch, cell force and envelope on the default profile.
#include <gtest/gtest.h>

#include <cmath>
#include <string>
#include <vector>

#include "mrskin/driver/model/device_model.hpp"

namespace {

using namespace mrskin::model;

const std::string kDir = MRSKIN_TEST_PROFILE_DIR;

// The shipped 5 x 5 with its reservoir at ambient (p0 = 0): the closed-form floors below are
// the membrane's alone. shipped() keeps the precharge.
const DeviceModel& model() {
  static const DeviceModel m([] {
    DeviceProfile p = load_profile(kDir + "/mr-skin-5x5.toml");
    p.reservoir.initial_pressure_Pa = 0.0;
    return p;
  }());
  return m;
}
const DeviceModel& shipped() {
  static const DeviceModel m(load_profile(kDir + "/mr-skin-5x5.toml"));
  return m;
}

std::size_t centre() { return model().fluid_cell_index(2, 2).value; }

TEST(ModelContact, EffectiveAreaAndCompliance) {
  MembraneParams m;
  m.pretension_N_per_m = 5.0;
  const double a = 0.03 / std::sqrt(kPi);
  const double c = 0.006;
  const ContactPatch p = contact_patch(m, a, c).value;
  EXPECT_NEAR(p.effective_area_m2, kPi * (a * a - c * c) / (2 * std::log(a / c)), 1e-15);
  EXPECT_GT(p.effective_area_m2, p.contact_area_m2);  // the cone around the pad displaces fluid too
  // N2 has a closed form: pi/2 (a^2 - c^2) [(a^2 - c^2)(1 - 1/L) + 2 c^2].
  const double l = std::log(a / c);
  const double n2 = 0.5 * kPi * (a * a - c * c) * ((a * a - c * c) * (1 - 1 / l) + 2 * c * c);
  EXPECT_NEAR(p.bulge_normalisation_m4 / n2, 1.0, 1e-10);
  // A pad as large as the cell is capped at 0.9 a; a tiny one is degenerate.
  EXPECT_NEAR(contact_patch(m, a, 2 * a).value.contact_radius_m, 0.9 * a, 1e-15);
  EXPECT_EQ(contact_patch(m, a, 1e-3 * a).status, Status::degenerate);
  // Larger pads displace more (A_eff grows with c), and A_eff -> pi a^2 as c -> a.
  double prev = 0.0;
  for (double cc = 0.05 * a; cc <= 0.9 * a; cc += 0.05 * a) {
    const double area = contact_patch(m, a, cc).value.effective_area_m2;
    EXPECT_GT(area, prev);
    prev = area;
  }
  EXPECT_GT(prev, 0.9 * kPi * a * a);
}

TEST(ModelContact, BulgeLawLinearPartIsTheExactTensionedMembrane) {
  // With pre-tension only (no stretching, no bending) the bulge mode is the exact solution:
  // compliance C = N2 / (4 T0) = pi (a^2 - c^2) / (8 T0) [(a^2 - c^2)(1 - 1/L) + 2 c^2].
  MembraneParams m;
  m.pretension_N_per_m = 20.0;
  m.youngs_modulus_Pa = 1e-6;
  const double a = 0.017;
  const double c = 0.008;
  const ContactPatch p = contact_patch(m, a, c).value;
  const double l = std::log(a / c);
  const double compliance = kPi * (a * a - c * c) / (8 * 20.0) * ((a * a - c * c) * (1 - 1 / l) + 2 * c * c);
  EXPECT_NEAR(bulge_volume_m3(p, 100.0).value / (100.0 * compliance), 1.0, 1e-6);
  // Stretching stiffens a narrower annulus (a wider pad): the cubic coefficient grows with c.
  MembraneParams e;
  double prev = 0.0;
  for (double cc = 0.1 * a; cc < 0.9 * a; cc += 0.1 * a) {
    const double k3 = contact_patch(e, a, cc).value.bulge_cubic_Pa_per_m9;
    EXPECT_GT(k3, prev);
    prev = k3;
  }
}

TEST(ModelCell, WorkBalanceForceIsTheEnergyGradient) {
  const ContactPatch& p = model().contact();
  // F = dU/dd + A_eff p and p = dU/ds, checked by central differences.
  const double d = 4e-3;
  const double s = 0.3 * p.effective_area_m2 * d;
  const double h = 1e-9;
  const double dudd = (stored_energy_J(p, d + h, s).value - stored_energy_J(p, d - h, s).value) / (2 * h);
  const double hs = 1e-9 * s;
  const double duds = (stored_energy_J(p, d, s + hs).value - stored_energy_J(p, d, s - hs).value) / (2 * hs);
  EXPECT_NEAR(dudd / pad_membrane_force_N(p, d).value, 1.0, 1e-6);
  EXPECT_NEAR(duds / bulge_pressure_Pa(p, s), 1.0, 1e-6);
  EXPECT_NEAR(bulge_volume_m3(p, bulge_pressure_Pa(p, s)).value / s, 1.0, 1e-12);
}

TEST(ModelCell, DesignPointRendersTwoNewtonsWithinTheCurrentRange) {
  const DeviceModel& m = shipped();
  const DeviceProfile& pr = m.profile();
  const double d = pr.design.indentation_m;
  const CellEnvelope e = m.envelope(centre(), d, 0.0).value;
  // The floor: membrane plus the precharge's p0 A_eff (0.22 + 0.19 N at 5 mm).
  EXPECT_NEAR(e.force_min_N,
              pad_membrane_force_N(m.contact(), d).value +
                  pr.reservoir.initial_pressure_Pa * m.contact().effective_area_m2,
              1e-9);
  EXPECT_LT(e.force_min_N, 0.25 * pr.design.force_range_N);
  EXPECT_GT(e.force_max_N, pr.design.force_range_N);
  const double i2 = m.current_for_force_A(centre(), d, 0.0, pr.design.force_range_N).value;
  const double frac = i2 / pr.coil.max_current_A;
  EXPECT_GT(frac, 0.7);   // 0..2 N spans most of the current range...
  EXPECT_LT(frac, 0.95);  // ...with headroom for calibration
  // One count of current is well under 1 % of the force range.
  const double f_hi = m.cell_force_uniform(centre(), d, 0.0, i2).value.force_N;
  const double f_lo = m.cell_force_uniform(centre(), d, 0.0, i2 - pr.coil.current_resolution_A).value.force_N;
  EXPECT_LT((f_hi - f_lo) / pr.design.force_range_N, 0.01);
  EXPECT_GT(f_hi - f_lo, 0.0);
}

TEST(ModelCell, ForceRisesWithCurrentAndIndentationWhileLoading) {
  const DeviceModel& m = model();
  const double imax = m.profile().coil.max_current_A;
  for (const double v : {0.0, 1e-3, 5e-3}) {
    double prev = -1.0;
    for (int k = 0; k <= 40; ++k) {
      const double f = m.cell_force_uniform(centre(), 4.5e-3, v, imax * k / 40.0).value.force_N;
      EXPECT_GE(f, prev) << "v " << v << " k " << k;
      prev = f;
    }
    prev = -1.0;
    for (int k = 1; k <= 40; ++k) {
      const double f = m.cell_force_uniform(centre(), 6e-3 * k / 40.0, v, 0.5 * imax).value.force_N;
      EXPECT_GE(f, prev) << "v " << v << " k " << k;
      prev = f;
    }
  }
}

TEST(ModelCell, ViscousFloorGrowsWithRate) {
  const DeviceModel& m = model();
  // Valves open (zero current): the floor is the membrane plus A_eff * dp_viscous(A_eff v).
  const double fm = m.cell_force_uniform(centre(), 5e-3, 0.0, 0.0).value.force_N;
  const double f1 = m.cell_force_uniform(centre(), 5e-3, 1e-3, 0.0).value.force_N;
  const double f2 = m.cell_force_uniform(centre(), 5e-3, 2e-3, 0.0).value.force_N;
  EXPECT_NEAR(fm, pad_membrane_force_N(m.contact(), 5e-3).value, 1e-12);
  EXPECT_NEAR((f2 - fm) / (f1 - fm), 2.0, 1e-6);  // Newtonian: linear in the rate
  // Its size: A_eff^2 v times the network's resistance.
  const double a = m.contact().effective_area_m2;
  const double dp = m.valve_network_pressure_uniform_Pa(centre(), a * 1e-3, 0.0).value;
  EXPECT_NEAR(f1 - fm, a * dp, 1e-12);
}

TEST(ModelCell, ChambersInSeriesDoubleTheYieldThreshold) {
  const DeviceModel& m = model();
  const double tau = 40.0;
  const double single = m.valve_law().yield_pressure_Pa(tau);
  for (std::size_t c = 0; c < m.layout().fluid_cell_count(); ++c) {
    EXPECT_NEAR(m.valve_network_pressure_uniform_Pa(c, 0.0, tau).value, 2.0 * single, 1e-9 * single);
  }
  // The "direct" topology (one passage between the two cells) has the single threshold.
  DeviceProfile p = m.profile();
  p.topology = "direct";
  p.links.clear();
  for (std::size_t v = 0; v < m.layout().valve_count(); ++v) {
    const auto& cells = m.layout().cells_of_valve(v);
    for (std::size_t i = 0; i + 1 < cells.size(); ++i) {
      p.links.push_back({{NodeKind::fluid_cell, static_cast<std::uint32_t>(cells[i])},
                         {NodeKind::fluid_cell, static_cast<std::uint32_t>(cells[i + 1])},
                         static_cast<std::int32_t>(v)});
    }
  }
  const DeviceModel direct(p);
  EXPECT_NEAR(direct.valve_network_pressure_uniform_Pa(centre(), 0.0, tau).value, single, 1e-9 * single);
}

TEST(ModelCell, NetworkPressureConservesFlowAndMatchesTheSymmetricHandSolution) {
  const DeviceModel& m = model();
  // Centre cell: 4 identical branches, each inlet then a chamber with 3 outlets to cells.
  // By symmetry each inlet carries Q/4 and each outlet Q/12: p = dp(Q/4) + dp(Q/12).
  const double tau = 30.0;
  for (const double q : {1e-8, 1e-6, 1e-5}) {
    const double p = m.valve_network_pressure_uniform_Pa(centre(), q, tau).value;
    const ValveLaw& v = m.valve_law();
    const double hand = v.pressure_exact_Pa(q / 4, tau).value + v.pressure_exact_Pa(q / 12, tau).value;
    EXPECT_NEAR(p / hand, 1.0, 1e-9) << q;
  }
  // Per-valve yield stresses: raising one valve's yield stress raises the pressure.
  std::vector<double> taus(m.layout().valve_count(), 30.0);
  const double base = m.valve_network_pressure_Pa(centre(), 1e-6, taus).value;
  taus[m.layout().valves_of_cell(centre())[0]] = 300.0;
  EXPECT_GT(m.valve_network_pressure_Pa(centre(), 1e-6, taus).value, base);
}

TEST(ModelCell, EnvelopeOrderingAndUnloading) {
  const DeviceModel& m = model();
  const double imax = m.profile().coil.max_current_A;
  for (const double d : {1e-3, 3e-3, 5e-3}) {
    for (const double v : {-5e-3, -0.5e-3, 0.0, 1e-3, 10e-3}) {
      const CellEnvelope e = m.envelope(centre(), d, v).value;
      EXPECT_LE(e.force_min_N, e.force_max_N);
      EXPECT_GE(e.force_min_N, 0.0);
      for (int k = 0; k <= 10; ++k) {
        const double f = m.cell_force_uniform(centre(), d, v, imax * k / 10.0).value.force_N;
        EXPECT_GE(f, e.force_min_N - 1e-12);
        EXPECT_LE(f, e.force_max_N + 1e-12);
      }
    }
  }
  // Unloading: the valves can only take force away; at best the membrane and p0 remain.
  const CellLoad slow = m.cell_force_uniform(centre(), 5e-3, -0.1e-3, 0.0).value;
  EXPECT_EQ(slow.mode, CellMode::refilling);
  EXPECT_LT(slow.force_N, pad_membrane_force_N(m.contact(), 5e-3).value);
  EXPECT_EQ(m.cell_force_uniform(centre(), 5e-3, -0.1e-3, imax).value.mode, CellMode::released);
}

TEST(ModelCell, ShallowPressBulgesTheCellsOwnMembrane) {
  const DeviceModel& m = model();
  const double imax = m.profile().coil.max_current_A;
  // At 1 mm the free annulus takes the displaced volume at a pressure below the valves':
  // the current makes no difference.
  const CellLoad a = m.cell_force_uniform(centre(), 1e-3, 1e-3, imax).value;
  EXPECT_EQ(a.mode, CellMode::bulging);
  EXPECT_EQ(a.valve_flow_m3_per_s, 0.0);
  EXPECT_NEAR(a.bulge_volume_m3, m.contact().effective_area_m2 * 1e-3, 1e-18);
}

TEST(ModelCell, DegenerateInputsAreExplicitErrors) {
  const DeviceModel& m = model();
  EXPECT_EQ(m.cell_force_uniform(99, 1e-3, 0.0, 0.0).status, Status::out_of_range);
  EXPECT_EQ(m.cell_force_uniform(centre(), std::nan(""), 0.0, 0.0).status, Status::not_finite);
  EXPECT_EQ(m.cell_force_uniform(centre(), 1e-3, 0.0, -0.01).status, Status::out_of_range);
  EXPECT_EQ(m.cell_force_uniform(centre(), 1e-3, 0.0, 1.0).status, Status::out_of_range);
  EXPECT_EQ(m.cell_force_uniform(centre(), 0.05, 0.0, 0.0).status, Status::out_of_range);  // below the floor
  EXPECT_EQ(m.cell_force_uniform(centre(), -1e-3, 0.0, 0.0).value.force_N, 0.0);           // no contact
  EXPECT_EQ(m.fluid_cell_index(0, 1).status, Status::out_of_range);
  EXPECT_EQ(m.fluid_cell_index(5, 0).status, Status::out_of_range);
  std::vector<double> wrong(3, 0.0);
  EXPECT_EQ(m.cell_force(centre(), 1e-3, 0.0, wrong).status, Status::out_of_range);
}

TEST(ModelCell, FluidCellIndexMatchesTheLayout) {
  const DeviceModel& m = model();
  for (std::size_t i = 0; i < m.layout().fluid_cell_count(); ++i) {
    const mrskin::GridCell g = m.layout().fluid_cells()[i];
    EXPECT_EQ(m.fluid_cell_index(g.row, g.col).value, i);
  }
}

TEST(ModelCell, YieldTableFollowsTheExactCircuit) {
  const DeviceModel& m = model();
  EXPECT_LT(m.yield_table_max_error_Pa(), 1e-6);
  const double imax = m.profile().coil.max_current_A;
  for (int k = 0; k <= 37; ++k) {
    const double i = imax * k / 37.0;
    EXPECT_NEAR(m.yield_stress_at_current_Pa(i).value, m.gap_field(i).value.yield_stress_Pa, 1e-6);
  }
}

}  // namespace
