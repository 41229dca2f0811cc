// Tissue models, presets, online estimation, stale policy, passive parameter changes and the
// passivity observer (bridge/include/mrskin/bridge/tissue.hpp). Random data use fixed seeds.
#include "mrskin/bridge/tissue.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <limits>
#include <random>
#include <set>
#include <string>
#include <utility>

#include "counting_new.hpp"
#include "mrskin/driver/errors.hpp"

#ifdef MRSKIN_HAVE_RAPIDCHECK
#include <rapidcheck.h>
#include <rapidcheck/gtest.h>
#endif

namespace {

using namespace mrskin::bridge;
using mrskin::model::CellState;
using mrskin::model::impedance_force_N;

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kPi = 3.14159265358979323846;

std::vector<TissueModel> sample_models() {
  return {TissueModel::kelvin_voigt(300.0, 0.5), TissueModel::hunt_crossley(2.0e4, 1.3, 5.0e4),
          TissueModel::hertz(2.5e3, 7.5e3), TissueModel::hertz_sphere(20e3, 0.45, 6e-3, 0.0),
          TissueModel::exponential(0.3, 400.0, 0.5)};
}

// ---- force laws --------------------------------------------------------------------------------

TEST(TissueModel, ForceLawsMatchTheirFormulas) {
  const double x = 3e-3;
  const double v = 8e-3;
  EXPECT_DOUBLE_EQ(TissueModel::kelvin_voigt(300.0, 0.5).force_N(x, v), 300.0 * x + 0.5 * v);
  EXPECT_DOUBLE_EQ(TissueModel::hunt_crossley(2.0e4, 1.3, 5.0e4).force_N(x, v),
                   std::pow(x, 1.3) * (2.0e4 + 5.0e4 * v));
  EXPECT_DOUBLE_EQ(TissueModel::hertz(2.5e3, 0.0).force_N(x, v), 2.5e3 * std::pow(x, 1.5));
  EXPECT_DOUBLE_EQ(TissueModel::exponential(0.3, 400.0, 0.5).force_N(x, v),
                   0.3 * std::expm1(400.0 * x) + 0.5 * v);
  // Hertz sphere: k = 4/3 E / (1 - nu^2) sqrt(R).
  const TissueModel h = TissueModel::hertz_sphere(20e3, 0.5, 4e-3, 0.0);
  EXPECT_NEAR(h.stiffness_N_per_m, 4.0 / 3.0 * 20e3 / 0.75 * std::sqrt(4e-3), 1e-9);
  EXPECT_EQ(h.kind, TissueKind::hertz);
  EXPECT_EQ(h.exponent, 1.5);
}

TEST(TissueModel, NoForceInAirAndNeverPulls) {
  for (const TissueModel& m : sample_models()) {
    SCOPED_TRACE(to_string(m.kind));
    EXPECT_TRUE(m.valid());
    EXPECT_EQ(m.force_N(0.0, 1.0), 0.0);
    EXPECT_EQ(m.force_N(-1e-3, 5.0), 0.0);
    EXPECT_EQ(m.force_N(kNaN, 0.0), 0.0);
    EXPECT_EQ(m.stored_energy_J(-1e-3), 0.0);
    // Fast unloading: damping would pull; the force is clamped at zero.
    EXPECT_GE(m.force_N(1e-3, -10.0), 0.0);
  }
}

TEST(TissueModel, MonotoneWithConsistentTangentEnergyAndInverses) {
  for (const TissueModel& m : sample_models()) {
    SCOPED_TRACE(to_string(m.kind));
    double last = 0.0;
    for (int i = 1; i <= 60; ++i) {
      const double x = 1e-4 * i;
      const double f = m.elastic_force_N(x);
      EXPECT_GT(f, last);
      last = f;
      // Tangent against a central difference.
      const double h = 1e-8;
      const double fd = (m.elastic_force_N(x + h) - m.elastic_force_N(x - h)) / (2 * h);
      EXPECT_NEAR(m.tangent_stiffness_N_per_m(x), fd, 1e-5 * fd + 1e-6);
      // Energy against Simpson's rule.
      const int n = 200;
      double s = m.elastic_force_N(0.0) + f;
      for (int j = 1; j < n; ++j) {
        s += (j % 2 == 1 ? 4.0 : 2.0) * m.elastic_force_N(x * j / n);
      }
      // Simpson converges slowly for x^1.3 (its curvature is singular at 0): 1e-6.
      EXPECT_NEAR(m.stored_energy_J(x), s * x / (3.0 * n), 1e-6 * m.stored_energy_J(x) + 1e-15);
      EXPECT_NEAR(m.depth_for_force_m(f), x, 1e-12);
      EXPECT_NEAR(m.depth_for_energy_m(m.stored_energy_J(x)), x, 1e-10);
    }
  }
}

// A unit of another design point renders the law through a change of units (DesignScale):
// F'(x, x') = f F(x / s, x' / s), exactly, for every kind, damping included.
TEST(TissueModel, RescaledIsTheSameLawInTheUnitsOfAnotherDesign) {
  TissueModel kv = TissueModel::kelvin_voigt(300.0, 2.0);
  kv.hc_damping_N_s_per_m = 0.0;
  TissueModel hc = TissueModel::hunt_crossley(4.0e4, 1.7, 1.4e4);
  hc.damping_N_s_per_m = 0.5;  // both damping terms at once
  const TissueModel laws[] = {kv, hc, TissueModel::hertz(2.0e5, 3.0e4),
                              TissueModel::exponential(0.2, 600.0, 1.5)};
  for (const TissueModel& law : laws) {
    for (const auto& [f, s] : {std::pair{0.01, 0.06}, std::pair{0.025, 0.1}, std::pair{3.0, 2.5}}) {
      const TissueModel scaled = law.rescaled(f, s);
      EXPECT_EQ(scaled.kind, law.kind);
      for (const double x_m : {0.0, 1e-4 * s, 1e-3 * s, 4e-3 * s}) {
        for (const double v_m_per_s : {-5e-3 * s, 0.0, 2e-3 * s, 2e-2 * s}) {
          const double want = f * law.force_N(x_m / s, v_m_per_s / s);
          EXPECT_NEAR(scaled.force_N(x_m, v_m_per_s), want, 1e-12 + 1e-12 * want)
              << to_string(law.kind) << " f " << f << " s " << s << " x " << x_m << " v " << v_m_per_s;
        }
      }
    }
  }
  // Scale 1, 1: the law itself.
  const TissueModel same = hc.rescaled(1.0, 1.0);
  EXPECT_EQ(same.stiffness_N_per_m, hc.stiffness_N_per_m);
  EXPECT_EQ(same.hc_damping_N_s_per_m, hc.hc_damping_N_s_per_m);
}

TEST(TissueModel, ConvertsToTheInversesImpedanceLaw) {
  for (const TissueModel& m : sample_models()) {
    SCOPED_TRACE(to_string(m.kind));
    for (const double x : {0.5e-3, 2e-3, 4e-3}) {
      for (const double v : {0.0, 5e-3, -2e-3}) {
        const double offset = 0.7e-3;
        const auto t = m.to_impedance_target(x, offset, 100.0, 1.0);
        EXPECT_EQ(t.surface_offset_m, offset);
        EXPECT_EQ(t.force_ceiling_N, 100.0);
        EXPECT_EQ(t.valid_until_s, 1.0);
        EXPECT_NEAR(impedance_force_N(t, CellState{x + offset, v}), m.force_N(x, v), 1e-12);
        if (m.kind == TissueKind::exponential) {
          // Local power law: same tangent stiffness at the conversion depth.
          const double k_tangent = t.exponent * t.stiffness_N_per_m * std::pow(x, t.exponent - 1.0);
          EXPECT_NEAR(k_tangent, m.tangent_stiffness_N_per_m(x), 1e-9 * k_tangent);
        }
      }
    }
  }
  // Exponential at the surface: linear with k = a beta.
  const auto t0 = TissueModel::exponential(0.3, 400.0, 0.0).to_impedance_target(0.0, 0.0, 2.0, 0.0);
  EXPECT_EQ(t0.exponent, 1.0);
  EXPECT_DOUBLE_EQ(t0.stiffness_N_per_m, 120.0);
}

// ---- presets -------------------------------------------------------------------------------------

TEST(TissuePresets, Table2ForcesAtTheDesignDepth) {
  // Paper Table 2: hand 0.6-0.9, neck 0.6-1.2, abdomen 0.4-1.3, thigh 0.7-1.2, back 1.0-1.5 N.
  struct Row {
    const char* name;
    double lo_N;
    double hi_N;
  };
  for (const Row& r : {Row{"hand", 0.6, 0.9}, Row{"neck", 0.6, 1.2}, Row{"abdomen", 0.4, 1.3},
                       Row{"thigh", 0.7, 1.2}, Row{"back", 1.0, 1.5}}) {
    SCOPED_TRACE(r.name);
    const TissuePreset* p = find_tissue_preset(r.name);
    ASSERT_NE(p, nullptr);
    EXPECT_EQ(p->force_min_N, r.lo_N);
    EXPECT_EQ(p->force_max_N, r.hi_N);
    EXPECT_EQ(p->model.kind, TissueKind::hertz);
    EXPECT_NEAR(p->model.elastic_force_N(5e-3), r.hi_N, 1e-12);
    // The lower force is reached inside the device's 0-5 mm.
    const double x_lo = p->model.depth_for_force_m(r.lo_N);
    EXPECT_GT(x_lo, 0.0);
    EXPECT_LT(x_lo, 5e-3);
  }
}

TEST(TissuePresets, StomachCurve) {
  const TissueModel* s = find_preset("stomach");
  ASSERT_NE(s, nullptr);
  EXPECT_EQ(s->kind, TissueKind::exponential);
  EXPECT_NEAR(s->elastic_force_N(4e-3), 1.2, 1e-9);                                  // ~1.2 N at 4 mm
  EXPECT_NEAR(s->elastic_force_N(4e-3) / 4e-3, 300.0, 1e-6);                         // secant ~300 N/m
  EXPECT_LT(s->tangent_stiffness_N_per_m(0.0), s->tangent_stiffness_N_per_m(4e-3));  // stiffens with depth
  const TissueModel* lin = find_preset("stomach_linear");
  ASSERT_NE(lin, nullptr);
  EXPECT_DOUBLE_EQ(lin->stiffness_N_per_m, 300.0);
}

TEST(TissuePresets, AllValidInDeviceRangeAndNamed) {
  std::set<std::string> names;
  ASSERT_EQ(preset_names().size(), tissue_presets().size());
  for (std::size_t i = 0; i < tissue_presets().size(); ++i) {
    const TissuePreset& p = tissue_presets()[i];
    SCOPED_TRACE(std::string(p.name));
    EXPECT_EQ(preset_names()[i], p.name);
    EXPECT_TRUE(names.insert(std::string(p.name)).second);
    EXPECT_TRUE(p.model.valid());
    EXPECT_LE(p.model.elastic_force_N(5e-3), 2.0);  // the skin's 0-2 N at 0-5 mm
    EXPECT_EQ(find_preset(p.name), &p.model);
  }
  EXPECT_EQ(find_preset("spleen"), nullptr);
}

// ---- estimator -------------------------------------------------------------------------------------

// A palpation that keeps contact: two sines between about 0.5 and 4.5 mm, 1 kHz, noisy.
struct Stream {
  double t_s = 0.0;
  std::mt19937 rng{12345};
  std::normal_distribution<double> force_noise{0.0, 5e-3};  // N
  std::normal_distribution<double> depth_noise{0.0, 2e-6};  // m
  static double depth_m(double t) {
    return 2.5e-3 + 1.5e-3 * std::sin(2 * kPi * 1.3 * t) + 0.5e-3 * std::sin(2 * kPi * 3.7 * t);
  }
  static double rate_m_per_s(double t) {
    return 1.5e-3 * 2 * kPi * 1.3 * std::cos(2 * kPi * 1.3 * t) +
           0.5e-3 * 2 * kPi * 3.7 * std::cos(2 * kPi * 3.7 * t);
  }
  TissueSample next(const TissueModel& truth, double dt_s = 1e-3) {
    t_s += dt_s;
    return TissueSample{t_s, truth.force_N(depth_m(t_s), rate_m_per_s(t_s)) + force_noise(rng),
                        depth_m(t_s) + depth_noise(rng)};
  }
};

TissueModel fit(TissueKind kind, const TissueModel& truth, double seconds, TissueEstimatorOptions o = {}) {
  o.kind = kind;
  TissueEstimator est(o);
  Stream s;
  const int n = static_cast<int>(seconds * 1000.0);
  for (int i = 0; i < n; ++i) {
    EXPECT_TRUE(est.push(s.next(truth)));
  }
  const TissueEstimate e = est.estimate(s.t_s);
  EXPECT_TRUE(e.fitted);
  EXPECT_GT(e.confidence, 0.9);
  EXPECT_EQ(e.freshness, TissueFreshness::fresh);
  EXPECT_EQ(est.stats().rejected_non_finite + est.stats().rejected_out_of_range, 0U);
  return e.model;
}

TEST(TissueEstimator, ConvergesKelvinVoigt) {
  const TissueModel truth = TissueModel::kelvin_voigt(300.0, 5.0);
  const TissueModel m = fit(TissueKind::kelvin_voigt, truth, 3.0);
  EXPECT_NEAR(m.stiffness_N_per_m, 300.0, 0.03 * 300.0);
  EXPECT_NEAR(m.damping_N_s_per_m, 5.0, 0.15 * 5.0);
}

TEST(TissueEstimator, ConvergesHuntCrossleyWithExponent) {
  for (const double n : {1.2, 1.5, 2.0}) {
    SCOPED_TRACE(n);
    // 1 N at 4 mm; damping 25 % of the elastic force at 10 mm/s.
    const double k = 1.0 / std::pow(4e-3, n);
    const TissueModel truth = TissueModel::hunt_crossley(k, n, 25.0 * k);
    const TissueModel m = fit(TissueKind::hunt_crossley, truth, 3.0);
    EXPECT_NEAR(m.exponent, n, 0.051);  // bank spacing 0.1
    // Compare at 4 mm where k and n trade off least.
    EXPECT_NEAR(m.elastic_force_N(4e-3), 1.0, 0.03);
    EXPECT_NEAR(m.hc_damping_N_s_per_m / m.stiffness_N_per_m, 25.0, 0.2 * 25.0);
  }
}

TEST(TissueEstimator, ConvergesHertz) {
  const TissueModel truth = *find_preset("back");
  TissueModel boosted = truth;
  boosted.hc_damping_N_s_per_m = 25.0 * truth.stiffness_N_per_m;
  const TissueModel m = fit(TissueKind::hertz, boosted, 3.0);
  EXPECT_EQ(m.kind, TissueKind::hertz);
  EXPECT_NEAR(m.stiffness_N_per_m, truth.stiffness_N_per_m, 0.03 * truth.stiffness_N_per_m);
}

TEST(TissueEstimator, ConvergesExponentialStomach) {
  const TissueModel truth = TissueModel::exponential(find_preset("stomach")->exp_scale_N, 400.0, 3.0);
  const TissueModel m = fit(TissueKind::exponential, truth, 3.0);
  // 400 /m falls between two bank rates (factor 1.25 apart): the curve, not beta, must match.
  EXPECT_NEAR(std::log(m.exp_rate_per_m / 400.0), 0.0, std::log(1.26));
  for (double x = 0.5e-3; x <= 4.5e-3; x += 0.5e-3) {
    EXPECT_NEAR(m.elastic_force_N(x), truth.elastic_force_N(x), 0.03 * truth.elastic_force_N(4.5e-3));
  }
  EXPECT_NEAR(m.damping_N_s_per_m, 3.0, 0.25 * 3.0);
}

TEST(TissueEstimator, TracksAStepInStiffness) {
  TissueEstimatorOptions o;
  o.kind = TissueKind::kelvin_voigt;
  TissueEstimator est(o);
  Stream s;
  for (int i = 0; i < 2000; ++i) {
    est.push(s.next(TissueModel::kelvin_voigt(300.0, 2.0)));
  }
  EXPECT_NEAR(est.estimate(s.t_s).model.stiffness_N_per_m, 300.0, 10.0);
  for (int i = 0; i < 1000; ++i) {  // 1 s after the step (memory about 0.2 s)
    est.push(s.next(TissueModel::kelvin_voigt(450.0, 2.0)));
  }
  EXPECT_NEAR(est.estimate(s.t_s).model.stiffness_N_per_m, 450.0, 15.0);
}

// The memory is a time, not a count of samples: a stream at 200 or 100 Hz (a bridge at 200 Hz
// takes every fifth sample of a 1 kHz stream; OpenIGTLink senders often send at 100 Hz) follows
// the step as a 1 kHz one does: 401 N/m 0.4 s after it at each rate. With a factor of 0.995 per
// sample the memory was 1 s at 200 Hz and 2 s at 100 Hz, which read 329 and 319 N/m there.
TEST(TissueEstimator, TracksAStepInStiffnessAtAnyStreamRate) {
  TissueEstimatorOptions o;
  o.kind = TissueKind::kelvin_voigt;
  for (const double rate_hz : {1000.0, 200.0, 100.0}) {
    SCOPED_TRACE(rate_hz);
    TissueEstimator est(o);
    Stream s;
    const double dt = 1.0 / rate_hz;
    const auto samples = [&](double seconds) { return static_cast<int>(std::lround(seconds * rate_hz)); };
    for (int i = 0; i < samples(2.0); ++i) {
      est.push(s.next(TissueModel::kelvin_voigt(300.0, 2.0), dt));
    }
    const TissueEstimate before = est.estimate(s.t_s);
    EXPECT_TRUE(before.fitted);
    EXPECT_NEAR(before.model.stiffness_N_per_m, 300.0, 10.0);
    for (int i = 0; i < samples(0.4); ++i) {  // two memories (0.2 s) after the step
      est.push(s.next(TissueModel::kelvin_voigt(450.0, 2.0), dt));
    }
    const double k = est.estimate(s.t_s).model.stiffness_N_per_m;
    std::printf("%5.0f Hz: %.1f N/m 0.4 s after a 300 -> 450 N/m step\n", rate_hz, k);
    EXPECT_NEAR(k, 401.0, 10.0);
  }
}

TEST(TissueEstimator, RejectsBadSamplesAndKeepsItsFit) {
  TissueEstimatorOptions o;
  o.kind = TissueKind::kelvin_voigt;
  TissueEstimator est(o);
  Stream s;
  const TissueModel truth = TissueModel::kelvin_voigt(300.0, 2.0);
  for (int i = 0; i < 2000; ++i) {
    est.push(s.next(truth));
  }
  const TissueModel before = est.raw_fit();
  const double t = s.t_s;
  EXPECT_FALSE(est.push({t + 1e-3, kNaN, 1e-3}));
  EXPECT_FALSE(est.push({t + 1e-3, 1.0, kInf}));
  EXPECT_FALSE(est.push({kNaN, 1.0, 1e-3}));
  EXPECT_FALSE(est.push({t + 1e-3, 1.0, 1.0}));   // 1 m deep
  EXPECT_FALSE(est.push({t + 1e-3, 1e6, 1e-3}));  // 1 MN
  EXPECT_FALSE(est.push({t - 1e-3, 1.0, 1e-3}));  // older than the last
  EXPECT_FALSE(est.push({t, 1.0, 1e-3}));         // the last one again
  EXPECT_EQ(est.stats().rejected_non_finite, 3U);
  EXPECT_EQ(est.stats().rejected_out_of_range, 2U);
  EXPECT_EQ(est.stats().rejected_out_of_order, 1U);
  EXPECT_EQ(est.stats().duplicates, 1U);
  EXPECT_EQ(est.raw_fit().stiffness_N_per_m, before.stiffness_N_per_m);
  EXPECT_EQ(est.raw_fit().damping_N_s_per_m, before.damping_N_s_per_m);
}

// A first press from rest to 3 mm in 1 s on lightly damped Kelvin-Voigt tissue (the sweep
// scene's stomach_linear: 300 N/m, 0.5 N s/m), as the bridge's default Hunt-Crossley bank sees
// it. The damping a Hunt-Crossley law can express drifts slightly negative part of the way; a
// regression projected onto lambda >= 0 at every sample stopped being a least-squares fit and
// ran k from 300 to 6e6 N/m^2.5 within 0.1 s. The law stays on the truth throughout.
TEST(TissueEstimator, FirstPressOnLightlyDampedTissueStaysOnTheTruth) {
  const TissueModel truth = TissueModel::kelvin_voigt(300.0, 0.5);
  TissueEstimatorOptions o;
  o.kind = TissueKind::hunt_crossley;
  o.prior = TissueModel::kelvin_voigt(200.0, 0.0);
  o.min_confidence = 0.9;
  TissueEstimator est(o);
  std::mt19937 rng(7);
  std::normal_distribution<double> noise(0.0, 5e-3);  // N, the scenes' slave-side noise
  int checked = 0;
  for (int k = 1; k <= 1500; ++k) {
    const double t = k * 1e-3;
    const double u = std::min(t, 1.0);
    const double x = 3e-3 * u * u * (3.0 - 2.0 * u);
    const double v = t < 1.0 ? 3e-3 * 6.0 * u * (1.0 - u) : 0.0;
    ASSERT_TRUE(est.push({t, truth.force_N(x, v) + noise(rng), x}));
    const TissueEstimate e = est.estimate(t);
    if (e.fitted && k % 10 == 0) {
      ++checked;
      EXPECT_NEAR(e.model.elastic_force_N(3e-3), 0.9, 0.05 * 0.9) << "t " << t;
      EXPECT_LT(e.model.force_N(3e-3, 5e-3) - e.model.elastic_force_N(3e-3), 0.02) << "t " << t;
    }
  }
  EXPECT_GT(checked, 50);
  EXPECT_LT(est.estimate(1.5).model.exponent, 1.15);
}

// Holding still excites nothing: no confidence from a standing press, and forgetting must not
// wind the covariance up without bound (capped, counted) or drift a good fit.
TEST(TissueEstimator, HoldingStillNeitherConvincesNorWindsUp) {
  TissueEstimatorOptions o;
  o.kind = TissueKind::kelvin_voigt;
  TissueEstimator still(o);
  for (int i = 1; i <= 3000; ++i) {
    still.push({i * 1e-3, 0.9, 3e-3});
  }
  EXPECT_LT(still.confidence(), o.min_confidence);
  EXPECT_FALSE(still.estimate(3.0).fitted);

  TissueEstimator est(o);
  Stream s;
  const TissueModel truth = TissueModel::kelvin_voigt(300.0, 5.0);
  for (int i = 0; i < 2000; ++i) {
    est.push(s.next(truth));
  }
  const double x = Stream::depth_m(s.t_s);
  for (int i = 0; i < 10000; ++i) {  // 10 s standing press, quantised depth: no rate at all
    s.t_s += 1e-3;
    est.push({s.t_s, truth.force_N(x, 0.0) + s.force_noise(s.rng), x});
  }
  EXPECT_GT(est.stats().covariance_limits, 0U);
  EXPECT_NEAR(est.estimate(s.t_s).model.stiffness_N_per_m, 300.0, 0.05 * 300.0);
}

TEST(TissueEstimator, UsesThePriorUntilConfident) {
  TissueEstimatorOptions o;
  o.kind = TissueKind::hertz;
  o.prior = *find_preset("hand");
  TissueEstimator est(o);
  EXPECT_EQ(est.estimate(0.0).freshness, TissueFreshness::no_data);
  EXPECT_EQ(est.estimate(0.0).model.force_N(3e-3, 0.0), 0.0);  // safe state without data
  Stream s;
  for (int i = 0; i < 10; ++i) {  // too few samples for confidence
    est.push(s.next(*find_preset("back")));
  }
  const TissueEstimate e = est.estimate(s.t_s);
  EXPECT_FALSE(e.fitted);
  EXPECT_EQ(e.model.stiffness_N_per_m, find_preset("hand")->stiffness_N_per_m);
}

TEST(TissueEstimator, HoldsThenFadesToTheSafeState) {
  TissueEstimatorOptions o;
  o.kind = TissueKind::kelvin_voigt;
  o.fresh_s = 0.02;
  o.hold_s = 0.1;
  o.fade_s = 0.2;
  TissueEstimator est(o);
  Stream s;
  for (int i = 0; i < 2000; ++i) {
    est.push(s.next(TissueModel::kelvin_voigt(300.0, 2.0)));
  }
  const double t0 = s.t_s;  // the stream stops here
  const double k = est.estimate(t0).model.stiffness_N_per_m;
  const TissueEstimate fresh = est.estimate(t0 + 0.01);
  EXPECT_EQ(fresh.freshness, TissueFreshness::fresh);
  EXPECT_EQ(fresh.scale, 1.0);
  const TissueEstimate held = est.estimate(t0 + 0.09);
  EXPECT_EQ(held.freshness, TissueFreshness::holding);
  EXPECT_EQ(held.model.stiffness_N_per_m, k);
  const TissueEstimate half = est.estimate(t0 + 0.2);
  EXPECT_EQ(half.freshness, TissueFreshness::fading);
  EXPECT_NEAR(half.scale, 0.5, 1e-9);
  EXPECT_NEAR(half.model.stiffness_N_per_m, 0.5 * k, 1e-6 * k);
  double last = half.model.force_N(3e-3, 0.0);
  for (double age = 0.21; age < 0.3; age += 0.01) {  // strictly fading
    const double f = est.estimate(t0 + age).model.force_N(3e-3, 0.0);
    EXPECT_LT(f, last);
    last = f;
  }
  EXPECT_NEAR(half.valid_until_s, t0 + 0.3, 1e-12);
  const TissueEstimate safe = est.estimate(t0 + 0.31);
  EXPECT_EQ(safe.freshness, TissueFreshness::safe);
  EXPECT_EQ(safe.model.force_N(3e-3, 0.01), 0.0);
  // A fresh sample restores the model at once.
  s.t_s = t0 + 0.5;
  est.push(s.next(TissueModel::kelvin_voigt(300.0, 2.0)));
  EXPECT_EQ(est.estimate(s.t_s).scale, 1.0);
}

TEST(TissueEstimator, SurvivesLossGapsAndLeavingContact) {
  TissueEstimatorOptions o;
  o.kind = TissueKind::kelvin_voigt;
  TissueEstimator est(o);
  Stream s;
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  const TissueModel truth = TissueModel::kelvin_voigt(300.0, 5.0);
  for (int i = 0; i < 4000; ++i) {
    TissueSample x = s.next(truth);
    if (i % 1000 == 500) {
      s.t_s += 0.2;  // a long gap
    }
    if (i % 700 < 40) {
      x.indentation_m = -1e-3;  // off the tissue
      x.force_N = 0.0;
    }
    if (u(rng) < 0.05) {
      continue;  // 5 % loss
    }
    est.push(x);
  }
  EXPECT_GE(est.stats().gaps, 3U);
  EXPECT_NEAR(est.estimate(s.t_s).model.stiffness_N_per_m, 300.0, 0.05 * 300.0);
}

TEST(TissueEstimator, RejectsUnusableOptions) {
  TissueEstimatorOptions o;
  o.memory_s = 0.0;
  EXPECT_THROW(TissueEstimator{o}, mrskin::InvalidArgument);
  o.memory_s = kNaN;
  EXPECT_THROW(TissueEstimator{o}, mrskin::InvalidArgument);
  o = {};
  o.min_contact_s = 0.0;
  EXPECT_THROW(TissueEstimator{o}, mrskin::InvalidArgument);
  o = {};
  o.memory_s = kInf;  // forgets nothing
  EXPECT_NO_THROW(TissueEstimator{o});
  o = {};
  o.bank_size = 0;
  EXPECT_THROW(TissueEstimator{o}, mrskin::InvalidArgument);
  o = {};
  o.prior.stiffness_N_per_m = -1.0;
  EXPECT_THROW(TissueEstimator{o}, mrskin::InvalidArgument);
  o = {};
  o.hold_s = 0.01;
  o.fresh_s = 0.02;
  EXPECT_THROW(TissueEstimator{o}, mrskin::InvalidArgument);
}

// Property (seeded loops; also a rapidcheck version below): any stream, including junk, leaves a
// finite, valid, bounded model.
void check_any_stream(std::uint32_t seed, TissueKind kind) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  TissueEstimatorOptions o;
  o.kind = kind;
  TissueEstimator est(o);
  double t = 0.0;
  const double junk[] = {kNaN, kInf, -kInf, 1e300, -1e300, 0.0, -0.0, 1e-300};
  for (int i = 0; i < 3000; ++i) {
    t += u(rng) < 0.02 ? -1e-3 : 1e-3 * (0.1 + 3.0 * u(rng));
    TissueSample s{t, 4.0 * u(rng) - 1.0, 8e-3 * u(rng) - 1e-3};
    if (u(rng) < 0.05) {
      s.force_N = junk[rng() % 8];
    }
    if (u(rng) < 0.05) {
      s.indentation_m = junk[rng() % 8];
    }
    est.push(s);
    const TissueModel m = est.raw_fit();
    ASSERT_TRUE(m.valid()) << "seed " << seed << " sample " << i;
    ASSERT_LE(m.elastic_force_N(o.reference_depth_m), o.max_elastic_force_at_ref_N * (1 + 1e-9));
    const TissueEstimate e = est.estimate(t);
    ASSERT_TRUE(e.model.valid());
    ASSERT_TRUE(std::isfinite(e.confidence));
    ASSERT_TRUE(e.confidence >= 0.0 && e.confidence <= 1.0);
  }
}

TEST(TissueEstimator, AnyStreamGivesABoundedValidModel) {
  for (std::uint32_t seed = 1; seed <= 20; ++seed) {
    for (const TissueKind k :
         {TissueKind::kelvin_voigt, TissueKind::hunt_crossley, TissueKind::hertz, TissueKind::exponential}) {
      check_any_stream(seed, k);
    }
  }
}

#ifdef MRSKIN_HAVE_RAPIDCHECK
// Fixed default seed so runs repeat; RC_PARAMS overrides.
const bool kSeedSet = [] {
  setenv("RC_PARAMS", "seed=20261122 max_success=100", 0);
  return true;
}();

RC_GTEST_PROP(TissueEstimatorProperty, RandomStreamsStayBounded, ()) {
  const auto seed = *rc::gen::arbitrary<std::uint32_t>();
  const auto kind = *rc::gen::element(TissueKind::kelvin_voigt, TissueKind::hunt_crossley, TissueKind::hertz,
                                      TissueKind::exponential);
  check_any_stream(seed, kind);
}
#endif

// The table in docs/tissue.md (estimator accuracy): fits after 0.3, 1 and 3 s of the noisy
// two-sine palpation (5 mN force noise, 2 um depth noise, 1 kHz), printed; each must be within 5 %
// of the true force at 4 mm after 1 s.
TEST(TissueFigures, EstimatorTable) {
  struct Case {
    const char* name = "";
    TissueKind kind = TissueKind::kelvin_voigt;
    TissueModel truth;
  };
  const double k15 = 1.0 / std::pow(4e-3, 1.5);
  const Case cases[] = {
      {"kelvin_voigt 300 N/m, 5 N s/m", TissueKind::kelvin_voigt, TissueModel::kelvin_voigt(300.0, 5.0)},
      {"hunt_crossley n 1.5, 1 N at 4 mm", TissueKind::hunt_crossley,
       TissueModel::hunt_crossley(k15, 1.5, 25 * k15)},
      {"hunt_crossley fit of stomach", TissueKind::hunt_crossley, *find_preset("stomach")},
      {"hertz fit of back", TissueKind::hertz, *find_preset("back")},
      {"exponential fit of stomach", TissueKind::exponential, *find_preset("stomach")},
  };
  std::printf("%-34s %6s %10s %10s %10s %10s\n", "case", "t_s", "confidence", "F4mm_N", "true_N", "shape");
  for (const Case& c : cases) {
    TissueEstimatorOptions o;
    o.kind = c.kind;
    TissueEstimator est(o);
    Stream s;
    for (int i = 1; i <= 3000; ++i) {
      est.push(s.next(c.truth));
      if (i == 300 || i == 1000 || i == 3000) {
        const TissueEstimate e = est.estimate(s.t_s);
        const double shape = c.kind == TissueKind::exponential ? e.model.exp_rate_per_m : e.model.exponent;
        std::printf("%-34s %6.1f %10.3f %10.4f %10.4f %10.4g\n", c.name, s.t_s, e.confidence,
                    e.model.elastic_force_N(4e-3), c.truth.elastic_force_N(4e-3), shape);
        if (i >= 1000) {
          EXPECT_NEAR(e.model.elastic_force_N(4e-3), c.truth.elastic_force_N(4e-3),
                      0.05 * c.truth.elastic_force_N(4e-3))
              << c.name;
        }
      }
    }
  }
}

// ---- passivity -------------------------------------------------------------------------------------

// Load 0 -> 4 mm in 1 s, unload in 1 s, at 1 kHz; `switch_law` at the peak.
template <typename Render>
PassivityStats cycle(Render&& render) {
  PassivityObserver po;
  const double dt = 1e-3;
  for (int i = 0; i <= 2000; ++i) {
    const double t = i * dt;
    const double x = t <= 1.0 ? 4e-3 * t : 4e-3 * (2.0 - t);
    const double v = t < 1.0 ? 4e-3 : -4e-3;
    po.observe(render(i, x, v), x);
  }
  return po.stats();
}

TEST(Passivity, KelvinVoigtCycleIsPassive) {
  const TissueModel kv = TissueModel::kelvin_voigt(300.0, 0.5);
  const PassivityStats s = cycle([&](int, double x, double v) { return kv.force_N(x, v); });
  EXPECT_EQ(s.active_samples, 0U);
  EXPECT_GE(s.min_energy_J, -1e-9);
  // What remains is what the damper took: b v^2 over 2 s, less what the zero clamp keeps.
  EXPECT_NEAR(s.energy_J, 0.5 * 4e-3 * 4e-3 * 2.0, 2e-6);
  EXPECT_EQ(s.samples, 2001U);
}

TEST(Passivity, NaiveStiffnessJumpIsFlaggedActive) {
  const TissueModel soft = TissueModel::kelvin_voigt(300.0, 0.0);
  const TissueModel hard = TissueModel::kelvin_voigt(600.0, 0.0);
  const PassivityStats s =
      cycle([&](int i, double x, double v) { return (i < 1000 ? soft : hard).force_N(x, v); });
  EXPECT_GT(s.active_samples, 0U);
  // Stored 300 x^2 / 2 at 4 mm, returned 600 x^2 / 2: 2.4 mJ injected.
  EXPECT_NEAR(s.energy_J, -0.5 * 300.0 * 16e-6, 1e-5);
  PassivityObserver po;
  po.observe(0.0, 0.0);
  po.observe(-1.0, 1e-3);  // an active sample
  EXPECT_GT(po.controller_damping_N_s_per_m(-4e-3, 1e-3, 1e9), 0.0);
  EXPECT_EQ(po.controller_damping_N_s_per_m(-4e-3, 1e-3, 50.0), 50.0);
  EXPECT_GT(po.stats().max_controller_damping_N_s_per_m, 0.0);
  po.observe(kNaN, 0.0);
  EXPECT_EQ(po.stats().rejected_samples, 1U);
  // Totals: one active cell is not hidden by a passive one with more energy.
  PassivityStats total;
  accumulate(total, s);
  accumulate(total, cycle([](int, double x, double v) {
               return TissueModel::kelvin_voigt(900.0, 0.0).force_N(x, v);
             }));
  EXPECT_LT(total.min_energy_J, -1e-3);
  EXPECT_EQ(total.active_samples, s.active_samples);
  EXPECT_EQ(total.samples, 2 * s.samples);
}

TEST(Passivity, TheUpdateRuleKeepsAStiffnessJumpPassive) {
  const TissueModel soft = TissueModel::kelvin_voigt(300.0, 0.0);
  const TissueModel hard = TissueModel::kelvin_voigt(600.0, 0.0);
  PassiveTissueUpdate rule;
  double before = 0.0;
  double after = 0.0;
  const PassivityStats s = cycle([&](int i, double x, double v) {
    if (i == 1000) {
      before = rule.force_N(x, v);
    }
    rule.update(i < 1000 ? soft : hard, x);
    if (i == 1000) {
      after = rule.force_N(x, v);
    }
    return rule.force_N(x, v);
  });
  EXPECT_EQ(s.active_samples, 0U);
  EXPECT_GE(s.min_energy_J, -1e-9);
  EXPECT_NEAR(after, before, 1e-9);  // force continuous at the switch
  EXPECT_EQ(rule.offset_raises(), 1U);
  EXPECT_EQ(rule.surface_offset_m(), 0.0);  // back at the true surface after the release
}

TEST(Passivity, TheUpdateRuleDropsForceForASofterLaw) {
  const TissueModel hard = TissueModel::kelvin_voigt(600.0, 0.0);
  const TissueModel soft = TissueModel::kelvin_voigt(300.0, 0.0);
  PassiveTissueUpdate rule;
  const PassivityStats s = cycle([&](int i, double x, double v) {
    rule.update(i < 1000 ? hard : soft, x);
    return rule.force_N(x, v);
  });
  EXPECT_EQ(s.active_samples, 0U);
  EXPECT_EQ(rule.force_drops(), 1U);
  EXPECT_NEAR(s.energy_J, 0.5 * 300.0 * 16e-6, 1e-5);  // 600 in, 300 back
}

TEST(Passivity, StaleFadeAndRecoveryThroughTheRuleArePassive) {
  // A stomach press; the stream stops at 0.3 s, fades out, and returns at 0.8 s.
  TissueEstimatorOptions o;
  o.kind = TissueKind::exponential;
  o.prior = *find_preset("stomach");
  o.min_confidence = 2.0 / 3.0;
  TissueEstimator est(o);
  PassiveTissueUpdate rule;
  PassivityObserver po;
  Stream stream;
  for (int i = 0; i <= 2000; ++i) {
    const double t = i * 1e-3;
    if (t < 0.3 || t > 0.8) {
      stream.t_s = t - 1e-3;
      est.push(stream.next(*find_preset("stomach")));
    }
    const double x = t <= 1.0 ? 4e-3 * t : 4e-3 * (2.0 - t);
    const double v = t < 1.0 ? 4e-3 : -4e-3;
    rule.update(est.estimate(t).model, x);
    po.observe(rule.force_N(x, v), x);
  }
  EXPECT_EQ(po.stats().active_samples, 0U);
  EXPECT_GE(po.stats().min_energy_J, -1e-9);
  EXPECT_GT(rule.offset_raises(), 0U);  // the recovery rose from the faded law
}

// The rule's invariant for arbitrary law pairs and depths: stored energy plus tank never rises,
// the tank stays within its bounds and the force never jumps up.
TEST(Passivity, RuleNeverRaisesStoredEnergyOrForce) {
  std::mt19937 rng(99);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  // Both draws before the call, in the order g++ took them: g++ and clang evaluate a call's
  // arguments in opposite orders.
  auto random_law = [&]() {
    const unsigned kind = rng() % 4;
    const double b = u(rng);
    const double a = u(rng);
    switch (kind) {
      case 0:
        return TissueModel::kelvin_voigt(50.0 + 1000.0 * a, b);
      case 1:
        return TissueModel::hunt_crossley(1e3 + 1e5 * a, 1.0 + 1.5 * b, 0.0);
      case 2:
        return TissueModel::hertz(500.0 + 5e3 * a, 0.0);
      default:
        return TissueModel::exponential(0.05 + a, 100.0 + 900.0 * b, 0.0);
    }
  };
  for (int i = 0; i < 5000; ++i) {
    PassiveTissueUpdate rule(u(rng) * 1e-3);
    double x = 0.0;
    rule.update(random_law(), x);
    for (int step = 0; step < 5; ++step) {
      x += 2e-3 * u(rng) - 0.5e-3;  // mostly deeper, sometimes back
      rule.update(rule.model(), x);
      const double f_old = rule.force_N(x, 0.0);
      const double e_old = rule.model().stored_energy_J(x - rule.surface_offset_m()) + rule.tank_J();
      rule.update(random_law(), x);
      const double f_new = rule.force_N(x, 0.0);
      const double e_new = rule.model().stored_energy_J(x - rule.surface_offset_m()) + rule.tank_J();
      ASSERT_LE(e_new, e_old * (1 + 1e-9) + 1e-15) << i;
      ASSERT_LE(f_new, f_old * (1 + 1e-9) + 1e-12) << i;
      ASSERT_GE(rule.surface_offset_m(), 0.0);
      ASSERT_GE(rule.tank_J(), 0.0);
    }
  }
}

// Estimate noise on a held press: without the tank every up-down pair would lose force.
TEST(Passivity, TankStopsNoiseRatchetingAHeldForceDown) {
  std::mt19937 rng(3);
  std::normal_distribution<double> noise(0.0, 3e-3);
  PassiveTissueUpdate with_tank;
  PassiveTissueUpdate without_tank(0.0);
  const double x = 3e-3;
  for (PassiveTissueUpdate* r : {&with_tank, &without_tank}) {
    r->update(TissueModel::kelvin_voigt(300.0, 0.0), 0.0);
  }
  for (int i = 0; i < 2000; ++i) {
    const TissueModel m = TissueModel::kelvin_voigt(300.0 * (1.0 + noise(rng)), 0.0);
    with_tank.update(m, x);
    without_tank.update(m, x);
  }
  const TissueModel last = TissueModel::kelvin_voigt(300.0, 0.0);
  with_tank.update(last, x);
  without_tank.update(last, x);
  std::printf("held force after 2000 noisy updates: with tank %.4f N, without %.4f N (0.9 N)\n",
              with_tank.force_N(x, 0.0), without_tank.force_N(x, 0.0));
  EXPECT_NEAR(with_tank.force_N(x, 0.0), 0.9, 0.02 * 0.9);
  EXPECT_LT(without_tank.force_N(x, 0.0), 0.8 * 0.9);
}

// The per-tick parts allocate nothing (estimator built at set-up; presets looked up once).
TEST(TissueRealtime, NoAllocationPerSample) {
  for (const TissueKind kind :
       {TissueKind::kelvin_voigt, TissueKind::hunt_crossley, TissueKind::hertz, TissueKind::exponential}) {
    TissueEstimatorOptions o;
    o.kind = kind;
    TissueEstimator est(o);
    PassiveTissueUpdate rule;
    PassivityObserver po;
    Stream s;
    const TissueModel truth = *find_preset("stomach");
    const std::uint64_t before = mrskin::test::allocation_count();
    double sum_N = 0.0;
    for (int i = 0; i < 2000; ++i) {
      est.push(s.next(truth));
      const double x = Stream::depth_m(s.t_s);
      rule.update(est.estimate(s.t_s).model, x);
      const double f = rule.force_N(x, Stream::rate_m_per_s(s.t_s));
      po.observe(f, x);
      sum_N +=
          rule.target(x, 2.0, s.t_s).stiffness_N_per_m + po.controller_damping_N_s_per_m(1e-3, 1e-3, 10.0);
    }
    EXPECT_EQ(mrskin::test::allocation_count(), before);
    EXPECT_TRUE(std::isfinite(sum_N));
  }
}

TEST(Passivity, ImpedanceTargetCarriesTheOffset) {
  PassiveTissueUpdate rule;
  // A first law arriving mid-press starts at the current depth (from zero force)...
  rule.update(TissueModel::kelvin_voigt(300.0, 0.0), 2e-3);
  EXPECT_NEAR(rule.surface_offset_m(), 2e-3, 1e-15);
  EXPECT_EQ(rule.force_N(2e-3, 0.0), 0.0);
  // ...and one that arrived before contact renders from the true surface.
  rule = PassiveTissueUpdate{};
  rule.update(TissueModel::kelvin_voigt(300.0, 0.0), 0.0);
  rule.update(TissueModel::kelvin_voigt(300.0, 0.0), 2e-3);
  EXPECT_EQ(rule.surface_offset_m(), 0.0);
  rule.update(TissueModel::kelvin_voigt(600.0, 0.0), 2e-3);
  EXPECT_NEAR(rule.surface_offset_m(), 1e-3, 1e-12);
  const auto t = rule.target(2.5e-3, 2.0, 1.0);
  EXPECT_NEAR(impedance_force_N(t, CellState{2.5e-3, 0.0}), rule.force_N(2.5e-3, 0.0), 1e-12);
  EXPECT_NEAR(impedance_force_N(t, CellState{2.5e-3, 0.0}), 0.9, 1e-9);
}

}  // namespace
